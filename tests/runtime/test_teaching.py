"""Teaching the running daemon on the emulated robot, through its HTTP API: presses of an object
taught as a new class answer the next recognition, survive a reload (SIGHUP) and a restart,
and are gone from the next recognition once removed; a teaching a class would refuse is
refused in one line before the gripper moves; an episode's press is taught as what it was;
the CLI asks the running daemon; references another model embedded are listed stale, logged
at start and never used."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time
from dataclasses import replace

import pytest

from edge.cli import main
from edge.core.errors import BadRequest
from edge.core.model import load_model
from edge.runtime.references import ReferenceStore, references_dir
from edge.sim.robot import SimRobot
from tests.support.daemon import (
    LOADED_HOST_ERRORS,
    LOADED_HOST_TRIES,
    ROOT,
    Daemon,
    base_config,
    fast_config,
    gripper_open,
    joints,
    recognize,
    recording_events,
    sim_daemon,
)
from tests.support.presses import recording_of
from tests.support.waits import wait_until

# The object on the table and a name for it: no class of the shipped model is a konjac, and
# its feel is its own (models/eval/teaching: every fresh press finds it after one taught
# press), so a taught class must answer it: a clear test. (A macaron feels like the reference
# cubes: on the model released at floor 0.3 two taught presses moved no fresh one.)
OBJECT = "konjac"
TAUGHT = "lab_konjac"
DESCRIPTION = "lab konjac (a Japanese yam cake)"
PRESSES = 2


def near(ep: dict) -> bool:
    """The taught class among a recognition's neighbours. One emulated press of the object
    can land nearer another class than the two taught ones (a restart's press found
    kiwi_piece at 0.71, the taught class at 0.79, once in make test): where the references
    are is what these checks are about, the nearest of one press is noise."""
    return TAUGHT in [n["label"] for n in ep["topk"]]


def loaded_host(error: str | None) -> bool:
    return any(e in (error or "") for e in LOADED_HOST_ERRORS)


async def top_up(d: Daemon, run: dict) -> dict:
    """``run`` as ended, where a press failed for a loaded host's reason (the stream stale
    for a moment, a stall past the Bus Watchdog: the press did what it must and the teaching
    stopped, its presses taught kept) with the presses left taught again (append), up to
    LOADED_HOST_TRIES: its taught presses' episodes and references."""
    for _ in range(LOADED_HOST_TRIES):
        if run["status"] == "done" or not loaded_host(run["error"]):
            break
        print(f"  a press failed on a loaded host, taught again: {run['error']}")
        status, more = await d.post("/v1/teach", {
            "label": run["label"], "description": DESCRIPTION, "append": True,
            "presses": run["presses"] - len(run["references"]), "pause_s": 0.2,
            "wait": True})
        assert status == 200, more
        run = {**more, "presses": run["presses"],
               "episodes": run["episodes"][:len(run["references"])] + more["episodes"],
               "references": run["references"] + more["references"],
               "press_s": run["press_s"] + more["press_s"]}
    return run


async def still(robot: SimRobot, d: Daemon) -> tuple:
    """Where the arm and gripper stand."""
    return (*joints(robot, d.cfg), robot.dxl.true_position(d.cfg.bus.gripper_id))


@pytest.mark.asyncio
async def test_taught_presses_answer_the_next_recognition_until_removed(tmp_path):
    async with SimRobot(OBJECT, seed=5, cfg=base_config()) as robot:
        async with Daemon(robot, fast_config(), tmp_path) as d:
            # Refused before anything moves, in one line: a class pressed at another x_th
            # (the gelatins' references at 0.003, this robot at 0.004), a description that
            # says how the object feels, a known label without append, hostile fields.
            where = await still(robot, d)
            refusals = [
                ({"label": "gelatin_hard", "append": True}, "x_th"),
                ({"label": TAUGHT, "description": "a soft bun"}, "soft"),
                ({"label": "otedama"}, "append"),
                ({"label": TAUGHT}, "description"),
                ({"label": TAUGHT, "description": DESCRIPTION, "presses": 0}, "presses"),
                ({"label": TAUGHT, "description": DESCRIPTION, "presses": True}, "presses"),
                ({"label": ["x"]}, "label"),
                ({"label": TAUGHT, "description": DESCRIPTION, "pause_s": 1e9}, "pause_s"),
                ({"label": "../etc", "description": DESCRIPTION}, "label"),
                ({"label": TAUGHT, "description": DESCRIPTION, "speed": 2}, "speed"),
            ]
            for body, field in refusals:
                status, answer = await d.post("/v1/teach", {**body, "wait": True})
                print(f"  {json.dumps(body)} -> {status} {answer['error']}")
                assert status == 400 and field in answer["error"], (body, answer)
                assert "\n" not in answer["error"]
            assert await still(robot, d) == where
            assert (await d.get("/v1/episodes"))[1] == {"episodes": []}
            status, _ = await d.get("/v1/teach")
            assert status == 404

            # Two presses taught as a new class; meanwhile a recognition is busy.
            t0 = time.monotonic()
            status, run = await d.post("/v1/teach", {"label": TAUGHT, "presses": PRESSES,
                                                      "description": DESCRIPTION,
                                                      "pause_s": 0.2})
            assert status == 202 and run["status"] == "running", run
            status, busy = await d.post("/v1/recognize", {"candidates": ["a", "b"]})
            assert status == 409 and "teaching" in busy["error"]

            async def ended():
                _, now = await d.get("/v1/teach")
                return now if now["status"] != "running" else None

            run = await wait_until(ended, 60, "the teaching's end", interval_s=0.1)
            elapsed = time.monotonic() - t0
            run = await top_up(d, run)
            assert run["status"] == "done", run
            assert len(run["episodes"]) == len(run["references"]) == PRESSES
            print(f"\ntaught {PRESSES} presses in {elapsed:.1f} s: "
                  f"{elapsed / PRESSES:.1f} s per taught press (pause 0.2 s included; "
                  f"press to reference {run['press_s']} s)")
            for eid in run["episodes"]:
                _, ep = await d.get(f"/v1/episodes/{eid}")
                assert ep["status"] == "pressed" and ep["candidates"] == [TAUGHT]
            _, listing = await d.get("/v1/references")
            refs = listing["references"]
            assert [r["id"] for r in refs] == run["references"]
            assert {r["label"] for r in refs} == {TAUGHT} and not any(r["stale"] for r in refs)
            assert [r["episode"] for r in refs] == run["episodes"]
            assert all(r["source"] == "api" and "z" not in r for r in refs)

            # The next recognition looks the press up with them: no restart, no retraining.
            # (Among its neighbours, as after the reload and the restart below: which class is
            # first moves with how deep a loaded host lets a press go; make test beside
            # stress-ng saw a konjac press at sponge_cube 0.94, the taught class 1.52.)
            ep = await recognize(d)
            print(f"  next recognition's neighbours: {ep['topk']}")
            assert near(ep)
            # A reload (what SIGHUP runs) keeps them.
            assert await d.runtime.reload()
            ep = await recognize(d)
            print(f"  after a reload: {ep['topk']}")
            assert near(ep)

        # A restart on the same state directory keeps them.
        async with Daemon(robot, fast_config(), tmp_path) as d:
            _, listing = await d.get("/v1/references")
            assert [r["id"] for r in listing["references"]] == run["references"]
            ep = await recognize(d)
            print(f"  after a restart: {ep['topk']}")
            assert near(ep)

            # Removed, one by its id and the rest by label: gone from the next recognition.
            first, *_ = run["references"]
            async with d.http.delete(f"{d.url}/v1/references/{first}") as resp:
                assert resp.status == 200
                assert [r["id"] for r in (await resp.json())["removed"]] == [first]
            async with d.http.delete(f"{d.url}/v1/references/{first}") as resp:
                assert resp.status == 404
            async with d.http.delete(f"{d.url}/v1/references?label={TAUGHT}") as resp:
                assert resp.status == 200 and len((await resp.json())["removed"]) == PRESSES - 1
            async with d.http.delete(f"{d.url}/v1/references") as resp:
                assert resp.status == 400 and "label" in (await resp.json())["error"]
            assert (await d.get("/v1/references"))[1]["references"] == []
            after = await recognize(d)
            assert TAUGHT not in [n["label"] for n in after["topk"]], after["topk"]

            # "This was...": the last recognition's press joins the references.
            status, ref = await d.post(f"/v1/episodes/{after['id']}/teach",
                                       {"label": TAUGHT, "description": DESCRIPTION})
            assert status == 200 and ref["episode"] == after["id"], ref
            assert ref["label"] == TAUGHT and ref["description"] == DESCRIPTION
            status, again = await d.post(f"/v1/episodes/{after['id']}/teach",
                                         {"label": TAUGHT})
            assert status == 400 and "taught already" in again["error"], again
            status, missing = await d.post("/v1/episodes/20200101T000000000Z-abcdef/teach",
                                           {"label": TAUGHT})
            assert status == 404, missing


def test_the_robot_s_stream_rate_and_threshold_are_checked_against_the_class(tmp_path):
    """What the daemon checks before the arm moves (ReferenceStore.check): a stream at
    another rate, or a threshold off the class's, in one line naming both figures."""
    model = load_model(ROOT / "models")
    store = ReferenceStore(tmp_path / "references")
    assert store.check(model, TAUGHT, DESCRIPTION, source="api", append=False, x_th=0.004,
                       rate_hz=125.0) == DESCRIPTION
    with pytest.raises(BadRequest) as slow:
        store.check(model, TAUGHT, DESCRIPTION, source="api", append=False, x_th=0.004,
                    rate_hz=100.0)
    with pytest.raises(BadRequest) as soft:
        store.check(model, "gelatin_soft", None, source="cli", append=True, x_th=0.004,
                    rate_hz=125.0)
    print(f"\n{slow.value}\n{soft.value}")
    assert "the tactile stream at 100.0 frames/s" in str(slow.value)
    assert "[press] x_th = 0.004" in str(soft.value) and "x_th = 0.003" in str(soft.value)
    # The description a known class is taught with by default: its own.
    assert store.check(model, "otedama", None, source="page", append=True, x_th=0.004,
                       rate_hz=None) == model.database.description("otedama")


@pytest.mark.asyncio
async def test_the_cli_teaches_reviews_removes_and_exports_through_the_running_daemon(
        tmp_path, capsys, caplog):
    state = tmp_path / "state"
    conf = tmp_path / "robot.toml"
    conf.write_text(f'[runtime]\nstate_dir = "{state}"\n')

    def cli(*argv: str) -> tuple[int, str]:
        code = main([*argv, "--config", str(conf)])
        return code, capsys.readouterr().out

    async with sim_daemon(state, OBJECT) as (_robot, d):
        for _ in range(LOADED_HOST_TRIES):
            code, out = await asyncio.to_thread(
                cli, "teach", TAUGHT, "--description", DESCRIPTION, "--presses", "1",
                "--url", d.url)
            print(out)
            if not (code == 1 and loaded_host(out)):
                break
        assert code == 0 and f"taught {TAUGHT}: 1 press(es)" in out
        code, out = await asyncio.to_thread(cli, "teach", TAUGHT, "--url", d.url)
        assert code == 2 and "append" in caplog.text  # a known label needs --append
        ep = await recognize(d)
        code, out = await asyncio.to_thread(cli, "teach", "--episode", ep["id"], TAUGHT,
                                            "--url", d.url)
        assert code == 0 and f"episode {ep['id']} taught as {TAUGHT}" in out
        code, out = await asyncio.to_thread(cli, "references", "list", "--url", d.url)
        print(out)
        assert code == 0 and out.count(TAUGHT) == 2 and ep["id"] in out
        # Export reads the references directly: the collection the build folds in.
        code, out = await asyncio.to_thread(cli, "references", "export",
                                            str(tmp_path / "taught"))
        dataset = json.loads((tmp_path / "taught" / "dataset.json").read_text())
        [taught] = dataset["classes"]
        assert taught["label"] == TAUGHT and taught["presses"] == 2
        assert taught["description"] == DESCRIPTION
        assert len(list((tmp_path / "taught" / TAUGHT).glob("*.press.npz"))) == 2
        code, out = await asyncio.to_thread(cli, "references", "remove", "--label", TAUGHT,
                                            "--url", d.url)
        assert code == 0 and out.count("removed") == 2
        code, out = await asyncio.to_thread(cli, "references", "list", "--url", d.url)
        assert "no taught references" in out
        url = d.url
    caplog.clear()
    # The daemon down: one line saying so.
    code, out = await asyncio.to_thread(cli, "references", "list", "--url", url)
    assert code == 2 and "no daemon answers" in caplog.text
    assert len(caplog.text.strip().splitlines()) == 1 and "Traceback" not in caplog.text


@pytest.mark.asyncio
async def test_references_another_model_embedded_are_listed_stale_logged_and_not_used(
        tmp_path, caplog):
    state = tmp_path / "state"
    store = ReferenceStore(references_dir(state))
    store.add(load_model(ROOT / "models"), replace(recording_of(OBJECT, 1), label="unknown"),
              TAUGHT, DESCRIPTION, source="cli")
    # As if taught before the model was replaced: its embedding is another model's.
    index = json.loads(store.index.read_text())
    index["references"][0]["model"] = "0" * 64
    store.index.write_text(json.dumps(index))
    async with sim_daemon(state, OBJECT) as (_robot, d):
        _, listing = await d.get("/v1/references")
        [ref] = listing["references"]
        assert ref["stale"] and ref["label"] == TAUGHT
        assert "1 taught references were embedded by another model and are not used" \
            in caplog.text
        ep = await recognize(d)
        assert TAUGHT not in [n["label"] for n in ep["topk"]], ep["topk"]
        # The health says them (the daemon is healthy without them); removed, it does not.
        _, health = await d.get("/healthz")
        print(f"/healthz with a stale reference: ok {health['ok']}, stale_references "
              f"{health['stale_references']}, labels {health['stale_reference_labels']}")
        assert health["stale_references"] == 1 and health["stale_reference_labels"] == [TAUGHT]
        async with d.http.delete(f"{d.url}/v1/references/{ref['id']}") as resp:
            assert resp.status == 200, await resp.text()
        _, health = await d.get("/healthz")
        assert health["stale_references"] == 0 and health["stale_reference_labels"] == []


@pytest.mark.asyncio
async def test_a_press_that_fails_mid_teaching_ends_it_failed_keeping_what_was_taught(
        tmp_path):
    async with sim_daemon(tmp_path / "state", OBJECT) as (robot, d):
        async with recording_events(d) as events:
            status, run = await d.post("/v1/teach", {"label": TAUGHT, "presses": 3,
                                                      "description": DESCRIPTION,
                                                      "pause_s": 1.0})
            assert status == 202, run
            await wait_until(lambda: any(e["type"] == "teach" and e["step"] == "move"
                                         for e in events), 30, "the first press taught")
            # During the pause: the next press closes for 50 ms only, and finds nothing.
            cfg = d.runtime.press.cfg
            d.runtime.press.cfg = replace(cfg, runtime=replace(cfg.runtime,
                                                               close_timeout_s=0.05))
            await wait_until(lambda: any(e["type"] == "teach" and e["step"] == "failed"
                                         for e in events), 30, "the teaching's end")
        _, run = await d.get("/v1/teach")
        print(f"\n{run['error']}")
        assert run["status"] == "failed" and "press 2 of 3" in run["error"], run
        assert len(run["episodes"]) == 2 and len(run["references"]) == 1
        _, ep = await d.get(f"/v1/episodes/{run['episodes'][1]}")
        assert ep["status"] == "failed" and ep["press"]["result"] == "no_contact", ep
        _, listing = await d.get("/v1/references")
        assert [r["id"] for r in listing["references"]] == run["references"]
        await d.wait_idle()
        assert gripper_open(robot)
        steps = [e["step"] for e in events if e["type"] == "teach"]
        assert steps == ["pressing", "taught", "move", "pressing", "failed"], steps


@pytest.mark.asyncio
async def test_a_teaching_waiting_between_presses_ends_with_the_daemon(tmp_path, caplog):
    async with sim_daemon(tmp_path / "state", OBJECT) as (robot, d):
        async with recording_events(d) as events:
            status, _ = await d.post("/v1/teach", {"label": TAUGHT, "presses": 3,
                                                    "description": DESCRIPTION,
                                                    "pause_s": 30})
            assert status == 202
            await wait_until(lambda: any(e["type"] == "teach" and e["step"] == "move"
                                         for e in events), 30, "the first press taught")
            # A button or SIGUSR1 between two taught presses presses nothing.
            before = set(d.store.ids())
            os.kill(os.getpid(), signal.SIGUSR1)
            await wait_until(lambda: "SIGUSR1 trigger ignored: a teaching is under way"
                             in caplog.text, 10, "the trigger ignored")
            assert set(d.store.ids()) == before
        runtime = d.runtime
    run = runtime.teaching()
    assert run.status == "failed" and run.error == "the daemon stopped", run
    assert len(run.references) == 1 and not runtime.teacher.active
    assert gripper_open(robot)
