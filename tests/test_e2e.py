"""End to end: emulated robot + the real drivers + the daemon runtime + HTTP API + a fake
OpenAI-compatible VLM on loopback."""

import asyncio
import contextlib
import json

import numpy as np
import pytest

from edge.core import recording
from edge.hw.arm import gripper_raw
from edge.sim.catalogue import names
from edge.sim.fake_vlm import FakeVLM, Reply
from edge.sim.robot import SimRobot
from tests.support.daemon import CUBE, OPEN_WIDTH_M, Daemon, base_config


@pytest.mark.asyncio
async def test_recognize_returns_the_label_and_keeps_the_whole_episode(tmp_path):
    async with FakeVLM(model="fake-vlm") as fake, \
            SimRobot("boiled_kiri_mochi", seed=4, cfg=base_config()) as robot:
        fake.script(Reply(label="boiled_kiri_mochi"))
        async with Daemon(robot, base_config(fake.base_url), tmp_path) as d:
            status, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            assert status == 200, ep
            assert ep["status"] == "done" and ep["label"] == "boiled_kiri_mochi"
            press = ep["press"]
            print(f"stop latency {press['stop_latency_ms']:.2f} ms, top-3 {ep['topk']}, "
                  f"timings {ep['timings']}")
            assert press["contact"] and press["t_stop"] > press["t_cross"]
            assert len({t["label"] for t in ep["topk"]}) == 3
            assert ep["description"].count(",") >= 2
            episode_dir = d.store.root / ep["id"]
            rec = recording.load(episode_dir / "press.press.npz")
            assert rec.frames.shape[1] == 96 and rec.t_stop == press["t_stop"]
            with np.load(episode_dir / "model_io.npz") as io:
                assert io["x"].shape == (25, 96) and io["window"].shape == (125, 96)
            assert (episode_dir / "image.jpg").read_bytes()[:3] == b"\xff\xd8\xff"
            assert ep["vlm"]["request"] and ep["vlm"]["response"]
            assert "base64" not in json.dumps(ep["vlm"]["request"])  # image elided in store
            for key in ("press_s", "encode_s", "vlm_s"):
                assert ep["timings"][key] > 0
    req = fake.chat_requests[-1]
    assert req.body["temperature"] == 0 and "seed" in req.body
    schema = req.body["response_format"]["json_schema"]["schema"]
    assert schema["properties"]["label"]["enum"] == CUBE
    assert req.image_mimes == ["image/jpeg"] and req.images[0][:2] == b"\xff\xd8"
    assert ep["description"] in req.prompt


@pytest.mark.asyncio
async def test_busy_answer_then_vlm_down_pending_completed_after_restart(tmp_path):
    # A port with nothing listening: the VLM is down.
    async with FakeVLM(model="fake-vlm") as probe:
        url, port = probe.base_url, probe.port
    async with SimRobot("raw_kiri_mochi", seed=5, cfg=base_config()) as robot:
        async with Daemon(robot, base_config(url), tmp_path) as d:
            status, first = await d.post("/v1/recognize", {"candidates": CUBE})
            assert status == 202
            status, busy = await d.post("/v1/recognize", {"candidates": CUBE})
            assert status == 409 and busy["episode"] == first["id"]
            # Stored as pending while its first question is still in flight; then asked and
            # refused: still pending, now with why.
            ep = await d.wait_status(first["id"], {"pending"},
                                     until=lambda ep: ep.get("attempts", 0) >= 1)
            assert ep["last_error"] and ep.get("label") is None
        # Restart the daemon with the VLM back: the pending episode completes.
        async with FakeVLM(model="fake-vlm", port=port) as fake, \
                Daemon(robot, base_config(url), tmp_path) as d2:
            fake.script(Reply(label="raw_kiri_mochi"))
            ep = await d2.wait_status(first["id"], {"done"})
            assert ep["label"] == "raw_kiri_mochi" and ep["attempts"] >= 2


@pytest.mark.asyncio
async def test_answer_outside_candidates_never_becomes_a_label(tmp_path):
    async with FakeVLM(model="fake-vlm") as fake, \
            SimRobot("raw_kabocha_squash", seed=6, cfg=base_config()) as robot:
        fake.script(Reply(label="a_brick"), Reply(label="still_a_brick"))
        async with Daemon(robot, base_config(fake.base_url), tmp_path) as d:
            status, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
    assert status == 200 and ep["status"] == "invalid_answer" and ep["label"] is None


@pytest.mark.asyncio
async def test_sensor_dies_mid_press_gripper_opens_daemon_keeps_serving(tmp_path):
    async with SimRobot("gelatin_soft", seed=7, cfg=base_config()) as robot:
        async with Daemon(robot, base_config(), tmp_path) as d:
            status, ep = await d.post("/v1/recognize", {"candidates": CUBE})
            while d.runtime.press.state != "closing":  # noqa: ASYNC110
                await asyncio.sleep(0.01)
            await robot.xela.stop()  # the sensor server dies mid-press
            failed = await d.wait_status(ep["id"], {"failed"})
            assert "stale" in failed["error"]
            assert robot.dxl.true_position(15) > gripper_raw(OPEN_WIDTH_M) - 20  # gripper opened
            status, health = await d.get("/healthz")
            assert status == 503 and health["state"] == "idle"  # serving, says why
            status, refused = await d.post("/v1/recognize", {"candidates": CUBE,
                                                               "wait": True})
            assert status == 200 and refused["status"] == "failed"
            assert "stale" in refused["error"]
            with contextlib.suppress(Exception):
                await robot.xela.start()


@pytest.mark.asyncio
async def test_no_vlm_gives_the_prompt_and_no_label(tmp_path):
    async with SimRobot("canele", seed=8, cfg=base_config()) as robot:
        async with Daemon(robot, base_config(), tmp_path) as d:
            status, ep = await d.post("/v1/recognize", {"candidates": names("foodreplica"),
                                                        "wait": True})
    assert status == 200 and ep["status"] == "not_configured" and ep["label"] is None
    assert ep["description"] in ep["vlm"]["prompt"]


@pytest.mark.asyncio
async def test_bad_requests_get_clear_4xx_and_never_move_the_arm(tmp_path):
    async with SimRobot("wood_cube", seed=9, cfg=base_config()) as robot:
        async with Daemon(robot, base_config(), tmp_path) as d:
            before = robot.dxl.true_position(11), robot.dxl.true_position(15)
            cases = [
                ({"candidates": []}, "non-empty"),
                ({"candidates": ["a", "a"]}, "duplicate candidate"),
                ({"candidates": ["a"] * 0 + [str(i) for i in range(40)]}, "too many"),
                ({"candidates": ["a"], "colour": "red"}, "unknown field 'colour'"),
                ({"candidates": ["a"], "image": "bm90IGFuIGltYWdl"}, "JPEG or PNG"),
                ({"candidates": ["a"], "image": "***"}, "not valid base64"),
                ({"candidates": [""]}, "non-empty string"),
                ({"candidates": ["a"], "wait": "yes"}, "wait must be"),
            ]
            for body, needle in cases:
                status, answer = await d.post("/v1/recognize", body)
                assert status == 400 and needle in answer["error"], (body, answer)
            async with d.http.post(d.url + "/v1/recognize", data=b"x" * (11 * 1024 * 1024),
                                   headers={"Content-Type": "application/json"}) as resp:
                assert resp.status == 413
            status, _ = await d.get("/v1/episodes/20200101T000000000Z-abcdef")
            assert status == 404
            status, _ = await d.get("/v1/episodes/..%2f..%2fetc")
            assert status == 404
            async with d.http.get(d.url + "/metrics") as resp:
                text = await resp.text()
            assert "vtzero_presses_total" in text and "vtzero_stop_latency_seconds" in text
            assert (robot.dxl.true_position(11), robot.dxl.true_position(15)) == before
            assert d.store.ids() == []
