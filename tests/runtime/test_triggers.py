"""Triggers besides the API (button, SIGUSR1), server-sent events, and SIGHUP reload."""

import asyncio
import json
import os
import signal
from dataclasses import replace

import pytest

from edge.app import model_ref
from edge.sim.catalogue import names
from edge.sim.robot import SimRobot
from tests.support.daemon import QUICK_OBJECT, Daemon, base_config
from tests.support.fakes import FakeButton
from tests.support.waits import wait_until

CUBE = names("cube")


def with_defaults(cfg):
    return replace(cfg, api=replace(cfg.api, default_candidates=tuple(CUBE)))


async def next_episode(d, before):
    ids = await wait_until(lambda: set(d.store.ids()) - before, 10, "a new stored episode",
                           interval_s=0.05)
    return ids.pop()


@pytest.mark.asyncio
async def test_button_and_sigusr1_trigger_with_the_default_candidates(tmp_path):
    cfg = with_defaults(base_config())
    async with SimRobot(QUICK_OBJECT, seed=21, cfg=cfg) as robot:
        d = Daemon(robot, cfg, tmp_path)
        button = FakeButton()
        d.button = button
        async with d:
            button.press()
            first = await next_episode(d, set())
            ep = await d.wait_status(first, {"not_configured"})
            assert ep["source"] == "button" and ep["candidates"] == CUBE
            os.kill(os.getpid(), signal.SIGUSR1)
            second = await next_episode(d, {first})
            ep = await d.wait_status(second, {"not_configured"})
            assert ep["source"] == "SIGUSR1"


@pytest.mark.asyncio
async def test_events_stream_the_press_states_and_the_result(tmp_path):
    async with SimRobot(QUICK_OBJECT, seed=22, cfg=base_config()) as robot:
        async with Daemon(robot, base_config(), tmp_path) as d:
            events = []

            async def listen():
                async with d.http.get(d.url + "/v1/events") as resp:
                    assert resp.headers["Content-Type"].startswith("text/event-stream")
                    async for line in resp.content:
                        if line.startswith(b"data: "):
                            events.append(json.loads(line[6:]))
                            if events[-1].get("type") == "result":
                                return

            listener = asyncio.create_task(listen())
            await asyncio.sleep(0.2)
            _, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            await asyncio.wait_for(listener, 10)
    states = [e["state"] for e in events if e["type"] == "state"]
    assert states[:4] == ["above", "lowered", "tare", "closing"] and "holding" in states
    assert any(e["type"] == "tactile" and e["description"] for e in events)
    assert events[-1]["status"] == "not_configured" and events[-1]["episode"] == ep["id"]


@pytest.mark.asyncio
async def test_sighup_reloads_between_presses_never_during_one(tmp_path):
    async with SimRobot("gelatin_soft", seed=23, cfg=base_config()) as robot:
        async with Daemon(robot, base_config(), tmp_path) as d:
            old = d.runtime.model
            new = model_ref(d.cfg)
            new_press = replace(d.cfg.press, x_th=0.0045)
            d.runtime.reloader = lambda: (replace(d.cfg, press=new_press), new, d.vlm)
            _, ep = await d.post("/v1/recognize", {"candidates": CUBE})
            while d.runtime.press.state != "closing":  # noqa: ASYNC110
                await asyncio.sleep(0.01)
            os.kill(os.getpid(), signal.SIGHUP)
            await asyncio.sleep(0.1)
            assert d.runtime.model is old  # not swapped under the running press
            done = await d.wait_status(ep["id"], {"not_configured"})
            assert done["x_th"] == 0.004 and done["press"]["contact"]
            for _ in range(100):
                if d.runtime.model is new:
                    break
                await asyncio.sleep(0.05)
            assert d.runtime.model is new and d.runtime.cfg.press.x_th == 0.0045


@pytest.mark.asyncio
async def test_systemd_ready_watchdog_only_while_frames_arrive_and_stopping(tmp_path,
                                                                        monkeypatch):
    import socket

    from edge.runtime.systemd import Notifier

    path = tmp_path / "notify.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(path))
    server.setblocking(False)
    monkeypatch.setenv("WATCHDOG_USEC", "200000")  # a ping every 0.1 s
    monkeypatch.delenv("WATCHDOG_PID", raising=False)

    def drain():
        out = []
        while True:
            try:
                out.append(server.recv(4096).decode())
            except BlockingIOError:
                return out

    async with SimRobot(QUICK_OBJECT, seed=24, cfg=base_config()) as robot:
        d = Daemon(robot, base_config(), tmp_path)
        d.notifier = Notifier(str(path))
        async with d:
            await asyncio.sleep(0.5)
            alive = drain()
            assert any(m.startswith("READY=1") for m in alive)
            assert alive.count("WATCHDOG=1") >= 3
            await robot.xela.stop()  # the sensor path stops making progress
            await asyncio.sleep(1.5)
            drain()
            await asyncio.sleep(0.5)
            assert "WATCHDOG=1" not in drain()  # systemd will restart us
        assert "STOPPING=1" in drain()
    server.close()


@pytest.mark.asyncio
async def test_sighup_rehashes_every_model_file_and_refuses_a_damaged_one(tmp_path, caplog):
    import shutil

    models = tmp_path / "models"
    shutil.copytree(base_config().runtime.models_dir, models)
    cfg = base_config()
    cfg = replace(cfg, runtime=replace(cfg.runtime, models_dir=str(models)))
    async with SimRobot(QUICK_OBJECT, seed=25, cfg=cfg) as robot, \
            Daemon(robot, cfg, tmp_path / "state") as d:
        running = d.runtime.model
        encoder = models / "encoder.onnx"
        data = bytearray(encoder.read_bytes())
        data[len(data) // 2] ^= 0x01  # one byte flipped; the manifest as it was
        encoder.write_bytes(bytes(data))
        os.kill(os.getpid(), signal.SIGHUP)
        refused = await wait_until(
            lambda: [r.getMessage() for r in caplog.records
                     if r.getMessage().startswith("reload refused")], 20, "the reload refused")
        print(refused)
        assert "encoder.onnx" in refused[0] and "does not match the manifest" in refused[0]
        assert d.runtime.model is running
        # The running model keeps answering.
        status, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
        assert status == 200 and ep["status"] == "not_configured" and ep["description"], ep
