"""`vt-edge calibrate threshold` on the emulated robot.

The two-gain test runs the procedure on the virtual-clock robot (edge/sim/virtual.py: the
real DynamixelBus, gripper and arm drivers over a loopback to the same motor emulator, the
same simulated world and pads), as the dataset recorder does: idle, probe and the presses
that check the result take ~1 s instead of ~40 s of wall time. The command itself is run as
`vt-edge` is, through edge.cli, against the real-time emulated robot (Dynamixel over a pty,
xela_server over a loopback WebSocket).
"""

from __future__ import annotations

import asyncio
import functools
import json
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from edge import cli
from edge.core import tomledit
from edge.core.config import load_config
from edge.core.errors import ConfigError, EdgeError, StaleSensorError
from edge.hw.contracts import Devices
from edge.hw.xela import parse_frame
from edge.lab.record import record_press, sim_config
from edge.ops import calibrate
from edge.sim.robot import SimRobot
from edge.sim.virtual import VirtualClockLoop, VirtualRobot
from edge.sim.world import robot_pads

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = "sponge_cube"
PRESSES = 3


def _calibrate_virtual(config: Path, out: Path, gain: float, obj: str = REFERENCE,
                       seed: int = 1, silence_after_s: float | None = None
                       ) -> calibrate.Proposal:
    """The procedure on the virtual-clock robot; ``silence_after_s``: the tactile stream
    stops that long after the gripper starts closing."""
    cfg = load_config(config)
    skin = replace(robot_pads(cfg.sim.seed), gain=gain)

    async def run() -> calibrate.Measurement:
        async with VirtualRobot(cfg, obj, np.random.default_rng(seed), skin_draw=skin) as r:
            if silence_after_s is not None:
                close = r.gripper.close

                async def close_then_silence(*args: float) -> None:
                    await close(*args)
                    asyncio.get_running_loop().call_later(
                        silence_after_s, lambda: setattr(r.tactile, "_closed", True))

                r.gripper.close = close_then_silence  # type: ignore[method-assign]
            await r.bus.set_torque(True)
            devices = Devices(tactile=r.tactile, gripper=r.gripper, arm=r.arm, bus=r.bus)
            try:
                return await calibrate.measure_threshold(cfg, prompt=None, devices=devices)
            finally:
                # Every way out leaves the gripper open.
                assert (await r.gripper.state()).width_m > cfg.press.open_width_m - 0.001

    # (the report, blocking, after the loop: as calibrate_threshold runs it off the loop)
    with asyncio.Runner(loop_factory=functools.partial(VirtualClockLoop, 100.0)) as runner:
        measured = runner.run(run())
    return calibrate.report(measured, cfg, config, out, None)


def _press(gain: float, x_th: float) -> tuple[float, float]:
    """Mean force (N per finger) at the threshold crossing and at its peak over ``PRESSES``
    presses of the reference through the daemon's press controller."""
    skin = replace(robot_pads(0), gain=gain)
    presses = [record_press(REFERENCE, np.random.default_rng(100 + i), cfg=sim_config(),
                            skin=skin, x_th=x_th) for i in range(PRESSES)]
    return (float(np.mean([p.force_at_cross_n for p in presses])),
            float(np.mean([p.peak_force_n for p in presses])))


def test_two_pad_gains_give_proportional_thresholds_that_stop_at_the_same_force(tmp_path):
    results = {}
    for gain in (1.0, 2.0):
        config = tmp_path / f"gain{gain}.toml"
        shutil.copy(ROOT / "configs" / "sim.toml", config)
        t0 = time.perf_counter()
        proposal = _calibrate_virtual(config, tmp_path / f"out{gain}", gain)
        wall = time.perf_counter() - t0
        assert load_config(config).press.x_th == proposal.x_th
        assert (tmp_path / f"out{gain}" / "threshold.png").read_bytes()[:4] == b"\x89PNG"
        at_cross, peak = _press(gain, proposal.x_th)
        results[gain] = (proposal, at_cross, peak)
        print(f"gain {gain}: x_th {proposal.x_th:.5f}, fragile {proposal.fragile:.5f}, "
              f"force at the crossing {at_cross:.4f} N, peak {peak:.4f} N "
              f"(calibration {wall:.2f} s wall)")
    (p1, cross1, peak1), (p2, cross2, peak2) = results[1.0], results[2.0]
    # Without calibration the same x_th stops the same object at another force on the
    # more sensitive pads: what the procedure corrects.
    uncal_cross, uncal_peak = _press(2.0, p1.x_th)
    print(f"gain 2.0 at the gain-1.0 x_th {p1.x_th:.5f}: force at the crossing "
          f"{uncal_cross:.4f} N, peak {uncal_peak:.4f} N")
    assert uncal_cross < 0.75 * cross1
    # The default gentle force reproduces today's threshold on the emulated XR1944.
    assert p1.x_th == pytest.approx(0.004, rel=0.15)
    assert p2.x_th / p1.x_th == pytest.approx(2.0, rel=0.1)
    assert p1.fragile == pytest.approx(calibrate.FRAGILE_RATIO * p1.x_th, abs=1e-5)
    assert cross2 == pytest.approx(cross1, rel=0.15)
    assert peak2 == pytest.approx(peak1, rel=0.15)


def test_an_object_too_stiff_to_resolve_is_refused_and_the_config_kept(tmp_path):
    config = tmp_path / "sim.toml"
    shutil.copy(ROOT / "configs" / "sim.toml", config)
    before = config.read_text()
    with pytest.raises(EdgeError, match="too stiff"):
        _calibrate_virtual(config, tmp_path / "out", 1.0, obj="rubber_cube")
    assert config.read_text() == before


async def _run_command(tmp_path: Path, *args: str, calibrated: bool = False,
                       pad_gain: float = 1.0) -> tuple[int, str, str, float]:
    """`vt-edge calibrate threshold ARGS` against the real-time emulated robot (its pads of
    ``[sim] pad_gain``): (exit status, config text before, after, the finger gap once the
    command returned)."""
    cfg = sim_config()
    cfg = replace(cfg, sim=replace(cfg.sim, pad_gain=pad_gain))
    config = tmp_path / "robot.toml"
    async with SimRobot(REFERENCE, seed=cfg.sim.seed, cfg=cfg, calibrated=calibrated) as robot:
        tomledit.update(ROOT / "configs" / "sim.toml", config, {
            "sensor": {"url": robot.xela.url, "stale_timeout_s": 0.25},
            "bus": {"port": robot.dxl.port}, "runtime": {"move_time_s": 0.2}})
        before = config.read_text()
        t0 = time.perf_counter()
        rc = await asyncio.to_thread(cli.main, [
            "calibrate", "threshold", "--config", str(config), "--out", str(tmp_path / "cal"),
            "--idle-s", "1.5", "--no-prompt", "--yes", *args])
        print(f"{time.perf_counter() - t0:.1f} s on the real-time emulated robot")
        gap = robot.world.gap_m
    return rc, before, config.read_text(), gap


def test_a_stream_that_stops_during_the_probe_opens_the_gripper(tmp_path):
    config = tmp_path / "sim.toml"
    shutil.copy(ROOT / "configs" / "sim.toml", config)
    before = config.read_text()
    # (the helper asserts the gripper is open after every way out)
    with pytest.raises(StaleSensorError, match="no tactile frame"):
        _calibrate_virtual(config, tmp_path / "out", 1.0, silence_after_s=1.0)
    assert config.read_text() == before


@pytest.mark.asyncio
async def test_the_command_writes_x_th_into_the_config_keeping_its_comments(tmp_path):
    rc, text, saved, gap = await _run_command(tmp_path)
    assert rc == 0
    assert "# The simulated objects are 16-34 mm wide" in text
    written = load_config(tmp_path / "robot.toml").press.x_th
    print(f"x_th written: {written}; finger gap after: {1e3 * gap:.1f} mm")
    # Only x_th changed: every comment and every other line as it was.
    changed = [(a, b) for a, b in zip(text.splitlines(), saved.splitlines(), strict=True)
               if a != b]
    assert len(changed) == 1 and changed[0][1].startswith("x_th = ")
    assert written == pytest.approx(0.004, rel=0.2) and written != 0.004
    assert (tmp_path / "cal" / "threshold.png").stat().st_size > 1000
    # The gripper was opened before the command returned (the pads released the object).
    assert gap > 0.030


@pytest.mark.asyncio
async def test_calibrated_newtons_set_the_gentle_force_in_newtons(tmp_path):
    """Pads twice as sensitive as the XR1944 whose xela_server sends `calibrated` forces:
    --force-n 0.37 (per finger, where 0.004 stops on the XR1944) gives twice today's
    threshold."""
    rc, _, _, _ = await _run_command(tmp_path, "--force-n", "0.37", calibrated=True,
                                     pad_gain=2.0)
    assert rc == 0
    written = load_config(tmp_path / "robot.toml").press.x_th
    data = json.loads((tmp_path / "cal" / "threshold.json").read_text())
    print(f"x_th at 0.37 N: {written}; at the crossing {data['at_x_th']}")
    assert data["at_x_th"]["newtons"] == pytest.approx(0.37, abs=0.02)
    assert written == pytest.approx(0.008, rel=0.2)


def test_answering_no_leaves_the_config_as_it_was(tmp_path):
    config = tmp_path / "sim.toml"
    shutil.copy(ROOT / "configs" / "sim.toml", config)
    before = config.read_text()
    asked = []
    cfg = load_config(config)

    async def run() -> calibrate.Measurement:
        async with VirtualRobot(cfg, REFERENCE, np.random.default_rng(1)) as r:
            await r.bus.set_torque(True)
            devices = Devices(tactile=r.tactile, gripper=r.gripper, arm=r.arm, bus=r.bus)
            return await calibrate.measure_threshold(cfg, prompt=None, devices=devices)

    with asyncio.Runner(loop_factory=functools.partial(VirtualClockLoop, 100.0)) as runner:
        measured = runner.run(run())
    calibrate.report(measured, cfg, config, tmp_path / "out",
                     lambda q: asked.append(q) or "n")
    assert config.read_text() == before
    assert len(asked) == 1 and "(now 0.004)" in asked[0] and str(config) in asked[0]


def test_pad_gain_out_of_range_is_refused_naming_the_field(tmp_path):
    config = tmp_path / "sim.toml"
    tomledit.update(ROOT / "configs" / "sim.toml", tmp_path / "ok.toml", {"sim": {"pad_gain": 2.0}})
    assert load_config(tmp_path / "ok.toml").sim.pad_gain == 2.0
    config.write_text((ROOT / "configs" / "sim.toml").read_text().replace(
        "seed = 0\n", "seed = 0\npad_gain = 0.0\n"))
    with pytest.raises(ConfigError, match=r"sim\.pad_gain"):
        load_config(config)


@pytest.mark.asyncio
async def test_force_n_without_calibrated_newtons_is_refused_naming_the_option(tmp_path,
                                                                              caplog):
    rc, text, saved, gap = await _run_command(tmp_path, "--force-n", "0.37")
    assert rc == 2 and saved == text and gap > 0.030
    assert any("--force-n" in r.getMessage() and "--force-ma" in r.getMessage()
               for r in caplog.records)


def test_the_client_reads_calibrated_newtons_only_when_asked():
    frame = (ROOT / "tests" / "fixtures" / "xela" / "v1.8_uSPa46_two_sensors.json").read_text()
    assert parse_frame(frame, 2, 24).newtons is None
    newtons = parse_frame(frame, 2, 24, newtons=True).newtons
    obj = json.loads(frame)
    assert newtons is not None and newtons.shape == (144,)
    assert newtons[0] == obj["1"]["calibrated"][0] and newtons[72] == obj["2"]["calibrated"][0]


@pytest.mark.asyncio
async def test_a_broken_stream_is_reconnected_and_its_error_kept():
    """A SensorError that is neither stale nor a layout (a bad frame) reconnects, as the
    sensor task does, instead of ending the reader."""
    from types import SimpleNamespace

    from edge.core.errors import SensorError

    class Source:
        connects = 0

        async def frames(self):
            self.connects += 1
            if self.connects == 1:
                raise SensorError("bad frame")
            for seq in range(3):
                yield SimpleNamespace(raw=np.zeros(96), recv_time=float(seq),
                                      sensor_time=float(seq), seq=seq, newtons=None)

    source = Source()
    stream = calibrate._Stream(source, 96, time.monotonic, 0.1)
    reader = asyncio.create_task(stream.run())
    try:
        await asyncio.wait_for(stream.wait_frames(3), 5.0)
    finally:
        reader.cancel()
    assert source.connects >= 2 and stream.ring.count >= 3
    assert isinstance(stream.error, SensorError) and "bad frame" in str(stream.error)


def test_a_gripper_that_cannot_open_leaves_the_arm_where_it_stands(tmp_path, monkeypatch):
    """Opening after the probe fails: torque goes off where the arm stands (no move to
    rest dragging the gripped object), as the press controller leaves it."""
    from edge.core.errors import DeviceError
    from edge.runtime import devices as devices_mod

    config = tmp_path / "sim.toml"
    shutil.copy(ROOT / "configs" / "sim.toml", config)
    cfg = load_config(config)
    moves, closes = [], []

    async def run() -> None:
        async with VirtualRobot(cfg, REFERENCE, np.random.default_rng(1)) as r:
            devices = Devices(tactile=r.tactile, gripper=r.gripper, arm=r.arm, bus=r.bus)
            opened, move_to, bus_close = r.gripper.open, r.arm.move_to, r.bus.close

            async def open_until_closed(*args: float) -> None:
                if r.gripper_closed:
                    raise DeviceError("gripper: no status packet")
                await opened(*args)

            async def close(*args: float) -> None:
                r.gripper_closed = True
                await closing(*args)

            async def move(pose: str, timeout_s: float) -> None:
                moves.append(pose)
                await move_to(pose, timeout_s)

            async def close_bus(safe_pose=None) -> None:
                closes.append(safe_pose)
                await bus_close(safe_pose)

            async def opened_devices(_cfg):
                return devices

            async def torque_on(d):
                await d.bus.set_torque(True)

            r.gripper_closed = False
            closing = r.gripper.close
            r.gripper.open, r.gripper.close = open_until_closed, close
            r.arm.move_to, r.bus.close = move, close_bus
            monkeypatch.setattr(devices_mod, "open_devices", opened_devices)
            monkeypatch.setattr(devices_mod, "enable_torque", torque_on)
            with pytest.raises(EdgeError, match="GRIPPER MAY STILL BE CLOSED"):
                await calibrate.measure_threshold(cfg, prompt=None)

    with asyncio.Runner(loop_factory=functools.partial(VirtualClockLoop, 100.0)) as runner:
        runner.run(run())
    print(f"moves {moves}, bus closes {closes}")
    assert moves == ["above", "lowered"] and closes and closes[0] is None
