"""Press again and fuse: a recognition of several presses of one object (the simulator's
presses through a scripted controller, the analysis and the fusion run in-process, a
scripted VLM, a real store), and the two fusions on their own."""

from __future__ import annotations

import asyncio
import json
from dataclasses import replace

import numpy as np
import pytest

from edge.core.config import Config, RuntimeConfig, from_dict
from edge.core.errors import BadRequest, BusyError, ConfigError
from edge.interfaces.requests import validate_presses
from edge.runtime.compute import FUSIONS, analyse_press, fuse_presses
from edge.runtime.domain import Hello, PressResult, PressState, Status
from edge.runtime.press import PressOutcome
from edge.runtime.recognition import AUTO
from tests.runtime.test_recognition import (
    CANDIDATES,
    MODEL,
    InProcessCompute,
    ScriptedPress,
    ScriptedVLM,
    drain,
    pressed,
    recognizer,
)
from tests.support.daemon import (
    FOOD,
    base_config,
    gripper_open,
    recording_events,
    sim_daemon,
    store_consistent,
    wait_health,
)
from tests.support.presses import recording_of
from tests.support.waits import wait_until

JOINT = 12


def with_fusion(fusion: str) -> Config:
    cfg = Config()
    return replace(cfg, runtime=replace(cfg.runtime, fusion=fusion))


@pytest.mark.asyncio
@pytest.mark.parametrize("fusion", FUSIONS)
async def test_three_presses_are_fused_into_one_question(tmp_path, fusion):
    press = ScriptedPress(pressed(3), pressed(4), pressed(5))
    vlm = ScriptedVLM(["macaron"])
    compute = InProcessCompute()
    rec, events = recognizer(tmp_path, press, vlm, compute, cfg=with_fusion(fusion))
    with events.subscribe(Hello(PressState.IDLE, None)) as sub:
        episode = await rec.recognize(CANDIDATES, None, True, 10, "api", presses=3,
                                      pause_s=0)
        seen = await drain(sub)
    cues = [e for e in seen if e["type"] == "press_again"]
    assert [(e["press"], e["presses"], e["episode"]) for e in cues] == [
        (2, 3, episode.id), (3, 3, episode.id)]
    assert cues[0]["message"] == "move the object slightly on the table: press 2 of 3 in 0 s"
    assert episode.status == Status.DONE and episode.label == "macaron"
    assert not press.outcomes and len(vlm.asked) == 1  # three presses, one question
    assert not rec.lock.locked()
    expected = fuse_presses(MODEL, [recording_of("macaron", s) for s in (3, 4, 5)], fusion)
    print(fusion, [(n.label, round(n.distance, 3)) for n in episode.topk],
          [p["topk"][0]["label"] for p in episode.presses])
    assert [(n.label, n.distance) for n in episode.topk] == expected.topk
    assert vlm.asked[0][1] == episode.description == expected.description
    assert episode.fusion == fusion and len(episode.presses) == 3
    for i, p in enumerate(episode.presses):
        alone = analyse_press(MODEL, recording_of("macaron", 3 + i))
        assert p["topk"] == [{"label": lb, "distance": d} for lb, d in alone.topk]
        assert p["result"] == "ok" and p["press_s"] > 0 and p["encode_s"] > 0
        assert 0 < p["agreement"] <= 1 and p["agreement"] == alone.agreement
    assert episode.presses[0]["t"] <= episode.presses[1]["t"] <= episode.presses[2]["t"]
    assert "fuse_s" in episode.timings
    assert compute.calls.count("analyse_press") == 3 and "fuse_presses" in compute.calls
    files = sorted(p.name for p in (tmp_path / "episodes" / episode.id).iterdir())
    assert files == ["episode.json", "model_io-2.npz", "model_io-3.npz", "model_io-fused.npz",
                     "model_io.npz", "press-2.press.npz", "press-3.press.npz",
                     "press.press.npz"]
    stored = json.loads((tmp_path / "episodes" / episode.id / "episode.json").read_text())
    assert stored["fusion"] == fusion and len(stored["presses"]) == 3


@pytest.mark.asyncio
async def test_one_press_stays_the_papers_episode(tmp_path):
    rec, _ = recognizer(tmp_path, ScriptedPress(pressed()), ScriptedVLM(["macaron"]))
    episode = await rec.recognize(CANDIDATES, None, True, 10, "api")
    stored = json.loads((tmp_path / "episodes" / episode.id / "episode.json").read_text())
    assert "presses" not in stored and "fusion" not in stored


@pytest.mark.asyncio
async def test_a_later_press_that_fails_fails_the_recognition_naming_it(tmp_path):
    failed = PressOutcome(result=PressResult.NO_CONTACT, message="no contact")
    press = ScriptedPress(pressed(3), failed)
    vlm = ScriptedVLM([])
    rec, _ = recognizer(tmp_path, press, vlm)
    episode = await rec.recognize(CANDIDATES, None, True, 10, "api", presses=2, pause_s=0)
    assert episode.status == Status.FAILED and episode.error == "press 2: no contact"
    assert not vlm.asked and not rec.lock.locked()
    files = sorted(p.name for p in (tmp_path / "episodes" / episode.id).iterdir())
    assert "press.press.npz" in files and "model_io.npz" in files  # the first kept


@pytest.mark.asyncio
@pytest.mark.parametrize("lost", [1, 2])
async def test_an_arm_lost_after_a_press_keeps_every_press_so_far(tmp_path, lost):
    # On the emulated robot: a joint stops answering while the arm returns from press
    # ``lost`` of 2 (slow moves: the return takes 2 s).
    cfg = base_config(move_time_s=2.0, tare_s=0.15)
    async with sim_daemon(tmp_path / "state", cfg=cfg) as (robot, d), \
            recording_events(d) as events:
        status, ep = await d.post("/v1/recognize", {"candidates": FOOD, "presses": 2,
                                                     "pause_s": 0})
        assert status == 202, ep
        for _ in range(lost):  # (held at the threshold: the press touched)
            await d.wait_press_state({"holding"})
            await d.wait_press_state({"returning"})
        robot.dxl.set_missing(JOINT)
        ep = await d.wait_status(ep["id"], {"failed"}, 30)
        print(f"arm lost after press {lost}: {ep['error']}")
        # The gripper opened, as on every fault path; no press after the one lost.
        assert gripper_open(robot)
        assert sum(e["type"] == "press_again" for e in events) == lost - 1
        assert ep["error"].startswith(f"press {lost}: return failed") and "motor 12" in ep["error"]
        assert [p["result"] for p in ep["presses"]] == ["ok"] * (lost - 1) + ["error"]
        assert all(p["topk"] and p["press_s"] > 0 for p in ep["presses"])
        assert ep["press"]["result"] == "error" and ep["topk"]
        # Every press so far kept, whole: its recording and the model's input and output.
        (kept,) = store_consistent(d.store.root)
        assert kept["id"] == ep["id"] and kept["status"] == "failed"
        files = sorted(p.name for p in (d.store.root / ep["id"]).iterdir())
        presses = {1: ["model_io.npz", "press.press.npz"],
                   2: ["model_io-2.npz", "model_io-fused.npz", "model_io.npz",
                       "press-2.press.npz", "press.press.npz"]}[lost]
        assert files == sorted(["episode.json", "image.jpg", *presses]), files
        robot.dxl.set_missing(JOINT, False)
        await wait_health(d, True, 10)


@pytest.mark.asyncio
async def test_the_lock_is_held_between_the_presses_and_freed_if_cancelled(tmp_path):
    press = ScriptedPress(pressed(3), pressed(4))
    rec, _ = recognizer(tmp_path, press, ScriptedVLM(["macaron"]))
    await rec.recognize(CANDIDATES, None, False, None, "api", presses=2, pause_s=60)
    await wait_until(lambda: len(press.outcomes) == 1, 10, "the first press")
    await asyncio.sleep(0.1)
    # The first press taken (its end, its analysis or the operator's 60 s pause under way):
    # no other press may start until the recognition's last press has ended.
    assert len(press.outcomes) == 1 and rec.lock.locked()
    with pytest.raises(BusyError):
        await rec.recognize(CANDIDATES, None, False, None, "api")
    for task in rec.work:
        task.cancel()
    await asyncio.gather(*rec.work, return_exceptions=True)
    assert not rec.lock.locked() and len(press.outcomes) == 1


def seed_where(pressed_again: bool, seeds: range = range(12)) -> int:
    """The first macaron press whose own analysis asks for (or not) a second press: its
    subsampling offsets disagree or it is unfamiliar. Found, not pinned, so that a re-released
    model (whose presses land elsewhere) keeps both cases tested."""
    for seed in seeds:
        alone = analyse_press(MODEL, recording_of("macaron", seed))
        print(f"seed {seed}: agreement {alone.agreement}, familiarity {alone.familiarity}, "
              f"unfamiliar {alone.unfamiliar}")
        if (alone.agreement < 1 or alone.unfamiliar) is pressed_again:
            return seed
    raise AssertionError(f"no macaron press of seeds {seeds} that "
                         f"{'asks' if pressed_again else 'does not ask'} for a second press")


@pytest.mark.asyncio
@pytest.mark.parametrize("pressed_again", [False, True])
async def test_auto_presses_again_only_when_the_offsets_disagree_or_unfamiliar(
        tmp_path, pressed_again):
    seed = seed_where(pressed_again)
    press = ScriptedPress(pressed(seed), pressed(seed + 10))
    rec, _ = recognizer(tmp_path, press, ScriptedVLM(["macaron"]))
    episode = await rec.recognize(CANDIDATES, None, True, 10, "api", presses=AUTO, pause_s=0)
    assert episode.status == Status.DONE
    assert len(press.outcomes) == (0 if pressed_again else 1)
    assert (episode.presses is not None and len(episode.presses) == 2) is pressed_again


@pytest.mark.asyncio
@pytest.mark.parametrize("presses", [0, 6, -1, 2.0, True, "two", "AUTO", None])
async def test_a_bad_number_of_presses_is_refused_naming_the_field(tmp_path, presses):
    with pytest.raises(BadRequest, match=r"presses must be an integer 1\.\.5 or 'auto'"):
        validate_presses({"presses": presses})
    press = ScriptedPress(pressed())
    rec, _ = recognizer(tmp_path, press, ScriptedVLM([]))
    with pytest.raises(BadRequest, match="presses must be"):
        await rec.recognize(CANDIDATES, None, True, 10, "api", presses=presses)
    assert len(press.outcomes) == 1 and rec.store.list() == []


def test_the_fusions_on_their_own():
    recs = [recording_of("macaron", s) for s in (3, 4, 5)]
    votes = fuse_presses(MODEL, recs, "votes")
    mean = fuse_presses(MODEL, recs, "mean")
    print("votes", votes.topk, votes.agreement, "mean", mean.topk, mean.agreement)
    for fused in (votes, mean):
        assert len(fused.topk) == 3 and len({lb for lb, _ in fused.topk}) == 3
        assert 0 <= fused.agreement <= 1 and len(fused.z) == len(votes.z)
    # Votes name a class some press's offsets found first; the mean embedding's nearest class
    # may be one no single look found first (its agreement 0).
    assert votes.agreement > 0
    # Both summarise the same embeddings: the mean is one vector, shared.
    assert np.allclose(votes.z, mean.z) and votes.code == mean.code
    # A press whose offsets agree keeps its nearest class when they vote.
    agreed = recording_of("macaron", seed_where(pressed_again=False))
    one = fuse_presses(MODEL, [agreed], "votes")
    assert one.topk[0][0] == analyse_press(MODEL, agreed).topk[0][0] and one.agreement == 1
    with pytest.raises(ValueError, match="fusion 'median'"):
        fuse_presses(MODEL, recs, "median")


def test_the_fusion_setting_names_the_field():
    assert RuntimeConfig().fusion in FUSIONS
    assert from_dict(RuntimeConfig, {"fusion": "mean"}, "runtime").fusion == "mean"
    with pytest.raises(ConfigError, match=r"runtime\.fusion = .*must be \"votes\" or \"mean\""):
        from_dict(RuntimeConfig, {"fusion": "median"}, "runtime")
