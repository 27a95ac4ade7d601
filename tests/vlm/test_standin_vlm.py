"""The simulated VLM: it knows only words and pictures, never the simulator's physics or the
pressed object's label, and behaves as the paper saw a VLM behave."""

from __future__ import annotations

import ast
import asyncio
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import aiohttp
import pytest

from edge.sim import catalogue, common_sense, standin_vlm
from edge.sim.camera import render
from edge.sim.standin_vlm import DEFAULT, VISION_LED, decide
from edge.vlm.client import OpenAIVLM
from tests.support.waits import free_port
from tests.vlm.helpers import image_bytes, vlm_config

ROOT = Path(__file__).resolve().parents[2]
CUBE = ["raw_kabocha_squash", "boiled_kabocha_squash", "raw_kiri_mochi", "boiled_kiri_mochi"]
FOOD = catalogue.names("foodreplica")
SOFT_TOUCH = ("otedama (a small Japanese cloth beanbag filled with beans), piece of kiwi "
              "fruit, cube of white bread")
HARD_TOUCH = "wood cube, stainless steel cube, acrylic cube"
MIDDLE_TOUCH = "silicone rubber cube, lump of modelling clay"
STANDIN_MODULES = ("edge/sim/standin_vlm.py", "edge/sim/common_sense.py")
# Where the simulator keeps its physics and the truth about the pressed object.
FORBIDDEN_MODULES = ("edge.sim.catalogue", "edge.sim.contact", "edge.sim.world",
                     "edge.sim.press", "edge.sim.skin", "edge.sim.record", "edge.sim.robot",
                     "edge.sim.xela_server", "edge.sim.dxl_emulator", "edge.sim.virtual",
                     "edge.sim.xela_replay", "edge.ops", "edge.lab", "edge.bench")
PHYSICS_NAMES = {"youngs_pa", "prony", "damping_ns_per_m", "yield_n", "mu", "bulge",
                 "width_sd_m", "youngs_cv", "exponent", "elastic_exponent", "x_th", "REFERENCE",
                 "FOODREPLICA", "CUBE", "DATASETS", "ObjectClass", "catalogue"}


def answer(description: str, shown: str, candidates=CUBE, profile=DEFAULT) -> str:
    return decide(profile, render(shown), description, candidates).label


@pytest.mark.parametrize("path", STANDIN_MODULES)
def test_it_imports_and_names_no_physics_and_no_truth(path):
    tree = ast.parse((ROOT / path).read_text())
    imported = set()
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            imported |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Attribute):
            names.add(node.attr)
        elif isinstance(node, ast.Name):
            names.add(node.id)
    assert not {m for m in imported if m.startswith(FORBIDDEN_MODULES)}
    assert not names & PHYSICS_NAMES, names & PHYSICS_NAMES
    # Its only window on the simulation is the camera's picture of a name.
    assert {m for m in imported if m.startswith("edge.")} <= {
        "edge.sim", "edge.sim.common_sense", "edge.sim.fake_vlm",
        "edge.sim.fake_vlm.FakeRequest", "edge.sim.fake_vlm.FakeVLM",
        "edge.sim.fake_vlm.plain_reason",
        "edge.sim.camera", "edge.sim.camera.render"}


def _questions():
    out = []
    for shown in (*CUBE, *FOOD):
        cands = CUBE if shown in CUBE else FOOD
        for touch in ("", SOFT_TOUCH, HARD_TOUCH, "rubber eraser, cork cube, rubber cube"):
            out.append((shown, touch, tuple(cands)))
    return out


def test_altered_physics_changes_nothing(monkeypatch):
    questions = _questions()
    before = [(decide(p, render(s), t, c)) for s, t, c in questions
              for p in (DEFAULT, VISION_LED)]
    # Every object's physics turned upside down: stiff things soft and soft things stiff,
    # other relaxation, damping, friction, yield. Nothing the stand-in answers may move.
    for name in catalogue.names():
        obj = catalogue.get(name)
        upside_down = dataclasses.replace(
            obj, youngs_pa=1e15 / obj.youngs_pa, prony=((0.5, 0.01),), damping_ns_per_m=99.0,
            yield_n=0.01, mu=0.01, bulge=0.9, youngs_cv=0.5)
        monkeypatch.setitem(catalogue._BY_NAME, name, upside_down)
    for ds, objects in catalogue.DATASETS.items():
        monkeypatch.setitem(catalogue.DATASETS, ds,
                            tuple(catalogue._BY_NAME[o.name] for o in objects))
    standin_vlm._thumb_of_name.cache_clear()
    try:
        after = [(decide(p, render(s), t, c)) for s, t, c in questions
                 for p in (DEFAULT, VISION_LED)]
    finally:
        standin_vlm._thumb_of_name.cache_clear()
    assert after == before


def test_sight_alone_takes_a_replica_for_the_real_food_and_cannot_tell_raw_from_boiled():
    # The picture of a replica is the picture of the food: the request carries no label.
    assert render("resin_replica_macaron") == render("macaron")
    for real in ("macaron", "canele", "cream_puff"):
        assert answer("", f"resin_replica_{real}", FOOD) == real
        assert answer("", real, FOOD) == real
    # Raw and boiled look alike: sight answers the first of the pair, right half the time.
    assert [answer("", c) for c in CUBE] == ["raw_kabocha_squash", "raw_kabocha_squash",
                                             "raw_kiri_mochi", "raw_kiri_mochi"]
    # It sees the kind of food: a kiri mochi photo never gets a kabocha answer.
    seen = standin_vlm.seen_candidates(render("boiled_kiri_mochi"), CUBE)
    assert seen == ["raw_kiri_mochi", "boiled_kiri_mochi"]


def test_touch_names_it_knows_move_it_as_in_the_paper():
    # Boiled kiri mochi felt like otedama and kiwi (soft); raw like wood and steel (hard).
    assert answer(SOFT_TOUCH, "boiled_kiri_mochi") == "boiled_kiri_mochi"
    assert answer(HARD_TOUCH, "raw_kiri_mochi") == "raw_kiri_mochi"
    # A replica that feels like hard things is read as the replica; a soft press as food.
    assert answer(HARD_TOUCH, "macaron", FOOD) == "resin_replica_macaron"
    assert answer(SOFT_TOUCH, "cream_puff", FOOD) == "cream_puff"
    # A canele (a crust) pressed hard is about as hard as its replica: read as the replica.
    assert answer(HARD_TOUCH, "canele", FOOD) == "resin_replica_canele"
    # Kabocha that feels like silicone and clay is read as boiled, raw or not; like cork
    # and erasers (give 0.37: nearer raw's 0.1 than boiled's 0.65) as raw.
    assert answer(MIDDLE_TOUCH, "raw_kabocha_squash") == "boiled_kabocha_squash"
    assert answer("rubber eraser, cork cube, rubber cube", "boiled_kabocha_squash") == \
        "raw_kabocha_squash"
    d = decide(DEFAULT, render("raw_kiri_mochi"), SOFT_TOUCH, CUBE)
    assert d.sight == "raw_kiri_mochi" and d.touch_give == pytest.approx(
        (0.75 + 0.75 / 2 + 0.85 / 3) / (1 + 1 / 2 + 1 / 3))


def test_the_words_decide_not_the_press():
    # Same photo, same candidates: only the names in the sentence differ.
    assert answer("cotton ball, marshmallow", "raw_kiri_mochi") == "boiled_kiri_mochi"
    assert answer("glass marble, aluminium cube", "raw_kiri_mochi") == "raw_kiri_mochi"
    # Names it does not know leave it with its sight.
    d = decide(DEFAULT, render("macaron"), "zorblax, quux", FOOD)
    assert d.label == "macaron" and d.touch_give is None
    # Tactile adjectives are words it understands too (the ablation).
    assert answer("a soft wobbly gelatin that yields", "raw_kiri_mochi") == "boiled_kiri_mochi"
    # The nearest reference weighs most.
    assert answer("marshmallow, wood cube, glass marble", "raw_kiri_mochi") == \
        "boiled_kiri_mochi"


def test_the_vision_led_profile_hardly_uses_touch():
    # Touch that is only fairly clear moves the default profile, not the vision-led one.
    assert answer(MIDDLE_TOUCH, "raw_kabocha_squash") == "boiled_kabocha_squash"
    assert answer(MIDDLE_TOUCH, "raw_kabocha_squash", profile=VISION_LED) == \
        "raw_kabocha_squash"
    assert answer(HARD_TOUCH, "macaron", FOOD, VISION_LED) == "macaron"
    # Only touch that is extreme and far from its sight's answer (by more than 0.8 of the
    # 0..1 give scale) gets through: cotton and marshmallow (0.98) against raw mochi (0.05).
    assert answer("cotton ball, marshmallow", "raw_kiri_mochi", profile=VISION_LED) == \
        "boiled_kiri_mochi"


def test_a_photo_it_cannot_match_leaves_every_candidate():
    assert standin_vlm.seen_candidates(image_bytes(noise=True), FOOD) == FOOD
    assert standin_vlm.seen_candidates(b"not an image", CUBE) == CUBE
    assert standin_vlm.seen_candidates(None, CUBE) == CUBE
    # Unknown candidate names: no picture to compare, no common sense to use.
    d = decide(DEFAULT, render("macaron"), SOFT_TOUCH, ["thing_a", "thing_b"])
    assert d.label == "thing_a"


def test_common_sense_reads_names_longest_phrase_first():
    assert common_sense.give_of("raw_kiri_mochi") == 0.05
    assert common_sense.give_of("boiled_kiri_mochi") == 0.95
    assert common_sense.give_of("resin_replica_cream_puff") == 0.05
    assert common_sense.give_of("piece of raw apple") == 0.2
    assert common_sense.give_of("silicone rubber cube") == 0.55
    assert common_sense.give_of("zorblax") is None
    assert common_sense.items("otedama (a small, cloth beanbag), wood cube") == [
        "otedama (a small, cloth beanbag)", "wood cube"]
    assert common_sense.is_imitation("resin_replica_gyoza")
    assert not common_sense.is_imitation("gyoza")
    # Every shipped reference description and every test label is something it knows.
    for obj in (*catalogue.REFERENCE, *catalogue.FOODREPLICA, *catalogue.CUBE):
        assert common_sense.give_of(obj.description or obj.name) is not None, obj.name


@pytest.mark.asyncio
async def test_served_through_the_robots_client_with_both_profiles():
    async with standin_vlm.server() as fake:
        answers = {}
        for model in ("simulated-vlm", "simulated-vlm-vision-led"):
            client = OpenAIVLM(vlm_config(fake.base_url, model=model))
            try:
                answers[model] = await client.ask(render("raw_kabocha_squash"),
                                                  MIDDLE_TOUCH, CUBE)
            finally:
                await client.close()
        async with aiohttp.ClientSession() as session:
            async with session.get(f"{fake.base_url}/models") as resp:
                listed = [m["id"] for m in (await resp.json())["data"]]
    assert answers["simulated-vlm"].label == "boiled_kabocha_squash"
    assert answers["simulated-vlm-vision-led"].label == "raw_kabocha_squash"
    for a in answers.values():
        assert a.status == "ok" and a.response["system_fingerprint"] == "vtzero-simulated-vlm"
    assert listed == ["simulated-vlm", "simulated-vlm-vision-led"]


@pytest.mark.asyncio
async def test_asked_for_a_reason_it_says_what_it_saw_and_felt_and_answers_the_same():
    questions = [("raw_kabocha_squash", MIDDLE_TOUCH, CUBE), ("macaron", HARD_TOUCH, FOOD),
                 ("raw_kiri_mochi", "quux widget", CUBE)]
    async with standin_vlm.server() as fake:
        answers = {}
        for ask_reason in (False, True):
            for mode in ("json_schema", "none"):
                client = OpenAIVLM(vlm_config(fake.base_url, model="simulated-vlm",
                                              ask_reason=ask_reason, structured_output=mode))
                try:
                    for shown, touch, cands in questions:
                        answers[ask_reason, mode, shown] = await client.ask(
                            render(shown), touch, cands)
                finally:
                    await client.close()
    for (ask_reason, mode, shown), a in answers.items():
        print(f"{mode} {shown}: {a.label} ({a.reason})")
        assert a.status == "ok" and a.label == answers[False, mode, shown].label
        assert (a.reason is None) is not ask_reason
    squash = answers[True, "json_schema", "raw_kabocha_squash"]
    assert squash.label == "boiled_kabocha_squash"
    decision = decide(DEFAULT, render("raw_kabocha_squash"), MIDDLE_TOUCH, CUBE)
    assert squash.reason == standin_vlm.say_why(decision, CUBE)
    assert squash.reason.startswith("The photo could show raw_kabocha_squash, "
                                    "boiled_kabocha_squash; touch suggests give ")
    assert "nearest boiled_kabocha_squash" in squash.reason
    assert answers[True, "none", "raw_kiri_mochi"].reason.endswith(
        "sight only (touch names nothing known).")


def test_standalone_it_says_simulated_vlm_on_every_line():
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with subprocess.Popen([sys.executable, "-m", "edge.sim.standin_vlm", "--port", str(port)],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          env=env, cwd=ROOT) as proc:
        try:
            first = ""
            while "at http" not in first:  # its log line, then the ready line
                line = proc.stdout.readline()
                assert line, first
                first += line
            assert f"simulated VLM at http://127.0.0.1:{port}/v1" in first
            assert "no real model" in first

            async def ask():
                client = OpenAIVLM(vlm_config(f"http://127.0.0.1:{port}/v1",
                                              model="simulated-vlm"))
                try:
                    return await client.ask(render("macaron"), HARD_TOUCH, FOOD)
                finally:
                    await client.close()

            assert asyncio.run(ask()).label == "resin_replica_macaron"
        finally:
            proc.terminate()
            rest = proc.stdout.read()
            assert proc.wait(timeout=10) == 0
    lines = [line for line in (first + rest).splitlines() if line.strip()]
    assert lines and all("simulated VLM" in line for line in lines), lines


def test_common_sense_table_is_the_size_its_docstring_says():
    assert f"for {len(common_sense.GIVE)} everyday" in common_sense.__doc__
    assert all(0.0 <= g <= 1.0 for g in common_sense.GIVE.values())
