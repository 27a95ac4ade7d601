"""``vt-edge run`` fails early and clearly: a configuration that would fail every press
exits 2 with one line and torque never on; an absent xela_server starts the daemon degraded
(torque off) until its stream arrives; a camera failing at recognition names itself."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from edge.app import assemble
from edge.cli import main as cli_main
from edge.core import tomledit
from edge.core.config import CameraConfig
from edge.core.errors import StartError
from edge.runtime.systemd import Notifier
from edge.sim import camera as sim_camera
from edge.sim.fake_vlm import FakeVLM, Reply
from edge.sim.robot import SimRobot
from edge.sim.xela_server import XelaServerEmulator
from tests.support.daemon import (
    CUBE,
    QUICK_OBJECT,
    Daemon,
    base_config,
    fast_config,
    gripper_open,
    joints,
    store_consistent,
    wait_health,
)
from tests.support.waits import free_port, wait_until

pytestmark = pytest.mark.asyncio

ROOT = Path(__file__).resolve().parents[2]
RUN_TIMEOUT_S = 120.0


def torque_registers(robot: SimRobot, cfg) -> set[int]:
    return {robot.dxl.get_register(i, "Torque Enable")
            for i in (*cfg.bus.joint_ids, cfg.bus.gripper_id)}


async def vt_edge_run(tmp_path: Path, robot: SimRobot, sections: dict) -> tuple[int, str]:
    """``vt-edge run`` as a user starts it, on configs/sim.toml pointed at ``robot`` and
    changed by ``sections``; its exit code and stderr (log level WARNING, as a supervisor
    quietens it: what is left is what went wrong)."""
    updates: dict = {
        "sensor": {"url": robot.xela.url},
        "bus": {"port": robot.dxl.port},
        "camera": {"kind": "http", "url": f"{robot.control_url}/camera.jpg"},
        "api": {"port": free_port()},
    }
    for name, values in sections.items():
        updates[name] = {**updates.get(name, {}), **values}
    config = tmp_path / "run.toml"
    tomledit.update(ROOT / "configs" / "sim.toml", config, updates)
    env = dict(os.environ, VTZERO_STATE_DIR=str(tmp_path / "state"), PYTHONUNBUFFERED="1",
               VTZERO_LOG_LEVEL="WARNING")
    for key in ("VTZERO_VLM_URL", "VTZERO_VLM_MODEL", "JOURNAL_STREAM", "NOTIFY_SOCKET"):
        env.pop(key, None)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "edge", "run", "--config", str(config), cwd=ROOT, env=env,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
    try:
        _, err = await asyncio.wait_for(proc.communicate(), RUN_TIMEOUT_S)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    return proc.returncode, err.decode(errors="replace")


@contextlib.contextmanager
def pty_without_modem_lines():
    """A serial device that opens but has no modem-control lines, as a pty."""
    master, slave = os.openpty()
    try:
        yield os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("case", ["taxels", "camera", "button"])
async def test_a_start_that_would_fail_every_press_exits_2_in_one_line_torque_never_on(
        tmp_path, case):
    with pty_without_modem_lines() as port:
        sections, says = {
            "taxels": ({"sensor": {"taxels_per_pad": 24}},
                       ["configured 2 x XR1944 (24 taxels each)", "with 16 taxels",
                        "sensor.taxels_per_pad"]),
            "camera": ({"camera": {"kind": "command", "command": "/nonexistent/snap {out}"},
                        "vlm": {"mode": "vision_tactile"}},
                       ["camera command '/nonexistent/snap {out}' cannot start",
                        "No such file", "vision_tactile", 'mode = "tactile_only"']),
            "button": ({"button": {"kind": "serial", "port": port, "line": "cts"}},
                       [f"button port {port} has no modem lines", "CTS/DSR",
                        'kind = "gpio"']),
        }[case]
        async with SimRobot(QUICK_OBJECT, seed=11, cfg=base_config()) as robot:
            code, err = await vt_edge_run(tmp_path, robot, sections)
            print(f"{case}: exit {code}, stderr:\n{err}")
            assert code == 2
            lines = err.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("vt-edge: "), lines
            for words in says:
                assert words in lines[0]
            assert robot.dxl.torque_enables == 0
            assert torque_registers(robot, base_config()) == {0}


@pytest.mark.parametrize("sensor, says", [
    ({"pads": 1}, ["configured 1 x XR1944", "2 sensors", "sensor.pads"]),
    ({"model": "uSPa46"}, ["configured 2 x uSPa46", "model XR1944", "sensor.model"]),
])
async def test_a_pad_count_or_model_not_what_the_server_sends_fails_the_start(
        tmp_path, sensor, says):
    async with SimRobot(QUICK_OBJECT, seed=12, cfg=base_config()) as robot:
        cfg = base_config()
        cfg = robot.runtime_config(replace(cfg, sensor=replace(cfg.sensor, **sensor),
                                           runtime=replace(cfg.runtime,
                                                           state_dir=str(tmp_path))))
        with pytest.raises(StartError) as err:
            async with assemble(cfg):
                pytest.fail("the daemon started with a layout the server does not send")
        print(err.value)
        for words in says:
            assert words in str(err.value)
        assert robot.dxl.torque_enables == 0


def degraded_config(vlm_url: str = ""):
    """Quick to give up on the first frame at start and quick to redial: the server comes
    up within the test, not within the shipped backoff."""
    cfg = fast_config(vlm_url)
    return replace(cfg, sensor=replace(cfg.sensor, connect_timeout_s=0.3,
                                       reconnect_max_backoff_s=0.1))


async def listen(sock: socket.socket, said: list[str]) -> None:
    """systemd's side of sd_notify: every datagram read as it comes (a full queue would
    block the sender)."""
    loop = asyncio.get_running_loop()
    while True:
        said.append((await loop.sock_recv(sock, 4096)).decode())


async def test_a_start_without_xela_server_serves_degraded_until_its_stream_arrives(
        tmp_path, monkeypatch):
    # Under systemd: READY=1 and the watchdog fed while degraded (torque off), as documented.
    monkeypatch.setenv("WATCHDOG_USEC", "100000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    systemd = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    systemd.bind(str(tmp_path / "notify.sock"))
    systemd.setblocking(False)
    said: list[str] = []
    listener = asyncio.create_task(listen(systemd, said))
    async with FakeVLM(model="fake-vlm") as fake, \
            SimRobot(QUICK_OBJECT, seed=13, cfg=base_config()) as robot:
        await robot.xela.stop()
        d = Daemon(robot, degraded_config(fake.base_url), tmp_path)
        d.wait_ready = False
        d.notifier = Notifier(str(tmp_path / "notify.sock"))
        async with d:
            # The user: /healthz 503 naming the sensor server; a press is refused at once.
            status, health = await d.get("/healthz")
            print(f"degraded: {health['sensor_error']}")
            assert status == 503 and not health["ready"] and health["torque_on"] is False
            assert f"sensor server {robot.xela.url} unreachable" in health["sensor_error"]
            before = joints(robot, d.cfg), robot.dxl.true_position(d.cfg.bus.gripper_id)
            status, refused = await d.post("/v1/recognize", {"candidates": CUBE,
                                                             "wait": True})
            assert status == 503 and robot.xela.url in refused["error"], refused
            assert "torque off" in refused["error"]
            # The robot: never powered, nothing moved; nothing stored.
            await asyncio.sleep(0.3)
            assert (joints(robot, d.cfg),
                    robot.dxl.true_position(d.cfg.bus.gripper_id)) == before
            assert robot.dxl.torque_enables == 0 and torque_registers(robot, d.cfg) == {0}
            assert store_consistent(d.store.root) == []
            print(f"sd_notify while degraded: {said}")
            ready = [m for m in said if m.startswith("READY=1")]
            assert len(ready) == 1 and "STATUS=degraded: sensor server" in ready[0]
            assert said.count("WATCHDOG=1") >= 2
            # The sensor comes up: torque on, /healthz 200, and a recognition ends done.
            t0 = asyncio.get_running_loop().time()
            await robot.xela.start()
            health = await wait_health(d, True, timeout_s=10)
            print(f"stream back: healthy after "
                  f"{asyncio.get_running_loop().time() - t0:.2f} s")
            assert health["torque_on"] is True and health["sensor_error"] is None
            assert torque_registers(robot, d.cfg) == {1}
            assert "READY=1\nSTATUS=ready: sim mode" in said
            fake.script(Reply(label=CUBE[0]))
            status, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            assert status == 200 and ep["status"] == "done", ep
            assert ep["label"] == CUBE[0] and ep["press"]["contact"]
            assert gripper_open(robot)
    listener.cancel()
    systemd.close()


async def test_a_wrong_layout_found_after_a_degraded_start_keeps_torque_off_said_once(
        tmp_path, caplog):
    caplog.set_level(logging.INFO)
    async with SimRobot(QUICK_OBJECT, seed=14, cfg=base_config()) as robot:
        await robot.xela.stop()
        d = Daemon(robot, degraded_config(), tmp_path)
        d.wait_ready = False
        async with d:
            await wait_health(d, False)
            # The server that comes up sends 24 taxels a pad, not the configured 16.
            wrong = XelaServerEmulator(port=robot.xela.port, taxels=24)
            await wrong.start()
            try:
                health = await wait_until(
                    lambda: d.runtime.sensor_error and "layout" in d.runtime.sensor_error
                    and d.runtime.health(), 10, "the layout refused")
                await asyncio.sleep(1.0)  # long enough for any repetition to show
                status, health = await d.get("/healthz")
                print(f"late layout: {health['sensor_error']}")
                assert status == 503 and health["torque_on"] is False
                assert "configured 2 x XR1944 (16 taxels each)" in health["sensor_error"]
                assert "24 taxels" in health["sensor_error"]
                said = [r for r in caplog.records if "layout mismatch" in r.getMessage()]
                assert len(said) == 1 and said[0].levelno == logging.ERROR, \
                    [r.getMessage() for r in said]
                status, refused = await d.post("/v1/recognize", {"candidates": CUBE})
                assert status == 503 and "layout" in refused["error"]
                assert robot.dxl.torque_enables == 0
            finally:
                await wrong.stop()
        assert robot.dxl.torque_enables == 0


async def test_torque_failing_when_the_stream_arrives_is_what_health_names(tmp_path):
    systemd = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    systemd.bind(str(tmp_path / "notify.sock"))
    systemd.setblocking(False)
    said: list[str] = []
    listener = asyncio.create_task(listen(systemd, said))
    async with SimRobot(QUICK_OBJECT, seed=15, cfg=base_config()) as robot:
        await robot.xela.stop()
        d = Daemon(robot, degraded_config(), tmp_path)
        d.wait_ready = False
        d.notifier = Notifier(str(tmp_path / "notify.sock"))
        async with d:
            health = await wait_health(d, False)
            assert f"sensor server {robot.xela.url} unreachable" in health["sensor_error"]
            # The gripper unplugged while the daemon waits: torque-on fails on the stream.
            gripper = d.cfg.bus.gripper_id
            before = joints(robot, d.cfg), robot.dxl.true_position(gripper)
            robot.dxl.set_missing(gripper)
            try:
                await robot.xela.start()
                await wait_until(lambda: d.runtime.health().bus_error, 10,
                                 "the torque-on failure said")
                status, health = await d.get("/healthz")
                print(f"after the stream: sensor_error={health['sensor_error']!r} "
                      f"bus_error={health['bus_error']!r}")
                assert status == 503 and not health["ready"]
                assert health["sensor_error"] is None and health["sensor_fresh"]
                assert health["bus_error"].startswith("torque could not be turned on: ")
                assert f"motor {gripper}" in health["bus_error"]
                assert health["torque_on"] is False
                status, refused = await d.post("/v1/recognize", {"candidates": CUBE})
                assert status == 503 and "torque could not be turned on" in refused["error"]
                assert robot.xela.url not in refused["error"]
                assert (joints(robot, d.cfg), robot.dxl.true_position(gripper)) == before
                assert store_consistent(d.store.root) == []
                # systemctl status says it too, no longer the sensor server.
                statuses = [m for m in said if m.startswith("STATUS=")]
                assert statuses[-1] == f"STATUS=degraded: {health['bus_error']}", said
            finally:
                robot.dxl.set_missing(gripper, False)
    listener.cancel()
    systemd.close()


async def test_a_camera_failing_at_recognition_ends_camera_error_with_its_message(
        tmp_path, monkeypatch, capsys):
    still = tmp_path / "still.jpg"
    still.write_bytes(await asyncio.to_thread(sim_camera.render, QUICK_OBJECT))
    state = tmp_path / "state"
    async with FakeVLM(model="fake-vlm") as fake, \
            SimRobot(QUICK_OBJECT, seed=15, cfg=base_config()) as robot:
        d = Daemon(robot, fast_config(fake.base_url), state)
        command = f"cp {still} {{out}}"
        d.cfg = replace(d.cfg, camera=CameraConfig(kind="command", command=command))
        async with d:  # (the start took its photo with it)
            still.unlink()  # the camera breaks
            status, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            print(f"{ep['status']}: {ep.get('error')}")
            assert status == 200 and ep["status"] == "camera_error", ep
            assert f"camera command {command!r} failed (exit 1)" in ep["error"]
            assert str(still) in ep["error"]
            # The press itself worked and was analysed; the VLM was never asked.
            assert ep["press"]["contact"] and len(ep["topk"]) == 3
            assert fake.chat_requests == []
            assert [e["status"] for e in store_consistent(d.store.root)] == ["camera_error"]
    monkeypatch.setenv("VTZERO_STATE_DIR", str(state))
    capsys.readouterr()
    assert cli_main(["episodes", "--config", str(ROOT / "configs" / "sim.toml"), "list",
                     "--status", "camera_error"]) == 0
    listed = capsys.readouterr().out
    assert ep["id"] in listed and "camera_error" in listed and "camera command" in listed


@pytest.mark.asyncio
async def test_x_th_far_from_the_models_is_warned_at_start_and_each_press_ends_at_the_stall(
        tmp_path, caplog):
    """x_th = 0.2 (a typo for 0.002) on the emulated robot (its stainless cube): a warning at
    start, and each press ends within 3 s of closing, naming x_th and the peak reached."""
    cfg = fast_config()
    cfg = replace(cfg, press=replace(cfg.press, x_th=0.2),
                  runtime=replace(cfg.runtime, close_timeout_s=8.0))
    async with SimRobot("stainless_cube", seed=3, cfg=base_config()) as robot, \
            Daemon(robot, cfg, tmp_path) as d:
        assert d.runtime.model.x_th == 0.004  # the shipped model's class_x_th
        for _ in range(2):
            status, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            press = ep["press"]
            states = dict(press["states"])
            print(f"{states['opening'] - states['closing']:.2f} s: {ep['error']}")
            assert status == 200 and ep["status"] == "failed"
            assert press["result"] == "below_threshold"
            assert states["opening"] - states["closing"] < 3.0
            assert "x_th = 0.2" in ep["error"] and f"{press['peak_level']:.4f}" in ep["error"]
    warned = [r for r in caplog.records if r.levelno == logging.WARNING
              and "[press] x_th = 0.2 is 50 times the x_th = 0.004" in r.getMessage()]
    assert len(warned) == 1, [r.getMessage() for r in caplog.records]
