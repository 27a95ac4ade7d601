"""The stop at the threshold: one WRITE from the gripper's last state, never backing off.

200 presses on mixed objects through the real stop path (``DynamixelGripper.stop_now`` ->
``DynamixelBus.stop_ahead`` -> the bus thread -> the SDK -> the pty) against the real
emulator, whose contact physics is the simulator's (``SimWorld``). Each press starts with the
fingers a little short of the object (placed there behind the bus's back, so no press waits
for a long approach), closes at the configured speed while a task reads the gripper after
every second frame as the press controller's trace does, and stops on the first simulated
tactile frame over ``x_th``. The emulator checks every stop: its goal must lie past the motor's true
position when the packet arrives. Figures are printed (``-s``).
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import time

import numpy as np
import pytest

from edge.core.config import BusConfig, Config
from edge.core.preprocess import UNITS_SCALE
from edge.hw.arm import DynamixelGripper, gripper_raw
from edge.hw.dynamixel import DynamixelBus
from edge.runtime.press import GRIPPER_TRACE_FRAMES
from edge.sim.dxl_emulator import DxlEmulator
from edge.sim.world import CLOSED_WIDTH_M, SimWorld

PRESSES = 200
OBJECTS = ("stainless_cube", "gelatin_soft", "sponge_cube", "tofu_firm", "rubber_ball",
           "marshmallow", "wood_cube", "grape")
FRAME_PERIOD_S = 1 / 125.0
# Where each press starts: this much gap short of the object.
APPROACH_GAP_M = (0.0003, 0.001)
# The threshold for fragile objects and the shipped one.
THRESHOLDS = (0.003, 0.004)
OPEN_GAP_M = 0.036
PRESS_TIMEOUT_S = 2.0
# The emulator shares this process's GIL with the bus thread and the test's loop; a short
# switch interval keeps it answering when the packet arrives, as a motor does (the bench's
# emulated robot runs in a process of its own with the same setting).
# What that cannot help is a host too busy to run the emulator's thread: it then reads a
# packet milliseconds after it was written, and the motor it models moves on meanwhile
# (~0.3 counts per ms), which a real one does not: the packet reaches a real motor within
# about this long of its write call (one USB transfer, 16 bytes at 1 Mbps). A stop the
# emulator read later than that is also judged where the motor was by then.
WIRE_S = 0.001
EMULATOR_SWITCH_INTERVAL_S = 0.0002


def _raw_for_gap(gap_m: float) -> int:
    return gripper_raw(gap_m / 2 + CLOSED_WIDTH_M)


OPEN_RAW = _raw_for_gap(OPEN_GAP_M)


@pytest.mark.slow
@pytest.mark.asyncio
async def test_200_stops_never_back_off_the_squeeze():
    cfg = Config()
    press = cfg.press
    world = SimWorld(OBJECTS[0], seed=3, gripper_id=cfg.bus.gripper_id)
    gid = cfg.bus.gripper_id
    rng = np.random.default_rng(7)
    switch = sys.getswitchinterval()
    sys.setswitchinterval(EMULATOR_SWITCH_INTERVAL_S)
    emu = DxlEmulator((*cfg.bus.joint_ids, gid), load=world.load,
                      initial_positions={gid: OPEN_RAW}).start()
    world.sync = lambda: emu.true_position(gid)  # frames see the fingers where they are
    records, crossed, t_start = [], 0, time.monotonic()
    try:
        async with DynamixelBus(BusConfig(port=emu.port, watchdog_ms=300)) as bus:
            await bus.set_torque(True)
            gripper = DynamixelGripper(bus)
            for i in range(PRESSES):
                obj = OBJECTS[i % len(OBJECTS)]
                x_th = THRESHOLDS[i % len(THRESHOLDS)]
                # Fingers wide open before the new object is placed (it must never feel
                # the last press's gap), then just short of it.
                for raw in (OPEN_RAW, None):
                    if raw is None:
                        world.place(obj)
                        raw = _raw_for_gap(world.instance.width_m + rng.uniform(*APPROACH_GAP_M))
                    emu.set_register(gid, "Present Position", raw)
                    world.load(gid, raw, time.monotonic())
                tare = world.frame(time.monotonic()).astype(np.float64)
                await bus.read_state()  # a state from before closing: never extrapolated
                await gripper.close(press.close_speed_mps / 2,
                                    cfg.bus.gripper_goal_current * 2.69)
                due = asyncio.Event()
                trace = asyncio.create_task(_trace(gripper, due))
                try:
                    stop, hit = await _close_until_over(world, gripper, tare, x_th,
                                                        press.stop_squeeze_raw, due)
                finally:
                    trace.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await trace
                crossed += hit
                records.append(bus.last_stop)
                assert stop.goal_raw == bus.last_stop.goal
            fallbacks, stops = bus.stop_fallbacks, bus.stops
    finally:
        emu.stop()
        sys.setswitchinterval(switch)
    elapsed = time.monotonic() - t_start
    checks = list(emu.stop_checks)
    ahead = np.array([c.ahead_raw for c in checks])
    fast = [r for r in records if r.fast]
    ages = np.array([r.state_age_s for r in fast]) * 1e3
    latency = np.array([r.t_write_call - r.t_submit for r in records]) * 1e3
    parts = {k: np.array(v) * 1e3 for k, v in {
        "in flight": [r.in_flight_s for r in records],
        "hand-over": [r.t_start - r.t_submit - r.in_flight_s for r in records],
        "write": [r.t_write_call - r.t_start for r in fast]}.items()}
    late = np.array([c.t - r.t_write_call for c, r in zip(checks, records, strict=True)]) * 1e3
    worst = np.argsort(ahead)[:3]
    print("\nclosest stops: " + "; ".join(
        f"{ahead[i]:.2f} counts past, packet read by the emulator {late[i]:.2f} ms after it "
        f"was written, state {1e3 * (records[i].state_age_s or 0):.1f} ms old" for i in worst)
        + f"; emulator lateness p50 {np.median(late):.3f} max {late.max():.2f} ms")
    print("\n" + ", ".join(f"{k} p50 {np.median(v):.3f} max {v.max():.3f} ms"
                           for k, v in parts.items()))
    print(f"\n{PRESSES} presses on {len(OBJECTS)} objects in {elapsed:.1f} s ({crossed} over "
          f"x_th, the rest stopped at the timeout): {len(checks)} stops seen by the emulator, "
          f"{emu.stops_behind} behind the true position; goal past it by min "
          f"{ahead.min():.2f} / p50 {np.median(ahead):.2f} counts (squeeze "
          f"{press.stop_squeeze_raw}); one WRITE from a state {np.median(ages):.1f} ms old "
          f"(p50, max {ages.max():.1f}) in {len(fast)}, read first in {fallbacks} "
          f"({[r.fallback for r in records if not r.fast][:3]}); hand-over to packet written "
          f"p50 {np.median(latency):.3f} ms, max {latency.max():.3f} ms")
    # Where the motor was when a real one would have had the packet.
    excess = np.maximum(late / 1e3 - WIRE_S, 0.0)
    ahead_at_wire = ahead + np.abs([c.velocity_raw_s for c in checks]) * excess
    print(f"\nread by the emulator more than {WIRE_S * 1e3:g} ms after the write: "
          f"{int((excess > 0).sum())} stops; behind at the emulator's reading "
          f"{emu.stops_behind}, behind {WIRE_S * 1e3:g} ms after the write "
          f"{int((ahead_at_wire < 0).sum())}")
    assert stops == PRESSES and len(checks) == PRESSES
    assert (ahead_at_wire >= 0).all()
    # The emulator finds a stop behind only where it read it late.
    assert all(late[i] > WIRE_S * 1e3 for i in np.flatnonzero(ahead < 0))
    # The trace keeps a state fresh: a read before the stop is the exception.
    assert fallbacks <= PRESSES // 20
    assert crossed >= PRESSES * 0.9


async def _trace(gripper: DynamixelGripper, due: asyncio.Event) -> None:
    """What the press controller's trace does while closing: read the gripper when cued."""
    while True:
        await due.wait()
        due.clear()
        await gripper.state()


async def _close_until_over(world: SimWorld, gripper: DynamixelGripper, tare: np.ndarray,
                            x_th: float, squeeze: int, due: asyncio.Event):
    """Frames at 125 Hz until the norm crosses ``x_th`` (or the timeout), then the stop;
    the stop and whether the threshold was crossed. The trace is cued after every
    GRIPPER_TRACE_FRAMES frames checked, as the press controller does."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + PRESS_TIMEOUT_S
    t_next = loop.time()
    checked = 0
    while loop.time() < deadline:
        t_next += FRAME_PERIOD_S
        await asyncio.sleep(max(0.0, t_next - loop.time()))
        raw = world.frame(time.monotonic())
        if np.linalg.norm(raw - tare) / UNITS_SCALE > x_th:
            return await gripper.stop_now(squeeze), True
        checked += 1
        if checked % GRIPPER_TRACE_FRAMES == 0:
            due.set()
    return await gripper.stop_now(squeeze), False
