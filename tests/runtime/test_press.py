"""The press controller alone, on fakes of the gripper, the arm and the pads (no emulator):
every state transition and every way a press ends."""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import replace

import numpy as np
import pytest

from edge.core import preprocess
from edge.core.config import Config
from edge.core.errors import DeviceError, StaleSensorError
from edge.runtime.press import OPEN_TRIES, RECORD_MARGIN_S, PressController, PressOutcome
from edge.runtime.ring import FrameRing
from tests.support.fakes import FakeArm, FakeGripper

pytestmark = pytest.mark.asyncio

FRAME_PERIOD_S = 0.002
# Counts added to the 16 z channels of a pad while the gripper squeezes: a norm of 600
# counts, level 0.0092: over x_th (0.004), far under the abort level (0.1).
SQUEEZE_COUNTS = 150
BASE = np.full(96, 32768, dtype=np.uint16)
Z = np.arange(2, 96, 3)[:16]
FULL_PRESS = ["above", "lowered", "tare", "closing", "holding", "opening", "returning", "idle"]


def config(**runtime) -> Config:
    cfg = Config()
    # Opening to 8 mm and closing at 2 cm/s per finger: contact with a 5 mm object 0.15 s
    # into closing.
    return replace(cfg, press=replace(cfg.press, tare_s=0.05, dt_stopping_s=0.05,
                                      open_width_m=0.008, close_speed_mps=0.04),
                   runtime=replace(cfg.runtime, **{"close_timeout_s": 0.3, **runtime}))


class Pads:
    """The pads in front of the fake gripper: a frame every 2 ms, loaded while the gripper
    squeezes (``extra`` counts more on demand), fed to the controller as the sensor task
    does."""

    def __init__(self, ring: FrameRing, gripper: FakeGripper) -> None:
        self.ring, self.gripper = ring, gripper
        self.controller: PressController | None = None
        self.extra = 0
        self.running = True
        self.seq = 0

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            if self.running:
                raw = BASE.copy()
                if (await self.gripper.state()).squeeze_ma > 0:
                    raw[Z] += SQUEEZE_COUNTS + self.extra
                now = loop.time()
                self.seq += 1
                self.ring.push(raw, now, now, self.seq)
                if self.controller is not None:
                    await self.controller.check(raw, now)
            await asyncio.sleep(FRAME_PERIOD_S)


@contextlib.asynccontextmanager
async def rig(cfg: Config | None = None, object_width_m: float | None = 0.005):
    cfg = cfg or config()
    ring = FrameRing(96, 20000)
    gripper = FakeGripper(object_width_m=object_width_m, start_width_m=0.01)
    arm = FakeArm(cfg.poses, start="rest")
    pads = Pads(ring, gripper)
    states: list[str] = []
    outcomes: list[PressOutcome] = []
    ctl = PressController(cfg, gripper, arm, ring, on_state=states.append,
                          on_outcome=outcomes.append)
    pads.controller = ctl
    task = asyncio.create_task(pads.run())
    await asyncio.sleep(0.05)
    try:
        yield ctl, gripper, arm, pads, states, outcomes
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def opened(gripper: FakeGripper, cfg: Config) -> bool:
    return gripper.calls[-1].startswith(f"open {cfg.press.open_width_m} ")


async def test_a_press_goes_through_every_state_and_stops_on_the_threshold():
    cfg = config()
    async with rig(cfg) as (ctl, gripper, arm, _, states, outcomes):
        await asyncio.sleep(preprocess.DEFAULT_WINDOW.before_s)  # frames before the press
        outcome = await ctl.run()
    assert outcome.result == "ok" and outcome.contact, outcome.message
    assert states == FULL_PRESS and [s for s, _ in outcome.states] == FULL_PRESS
    assert arm.history == ["above", "lowered", "above"]
    # Opened before anything moved, closed at half the gap speed per finger, stopped with
    # the configured squeeze, opened again.
    assert gripper.calls[0].startswith("open ")
    assert gripper.calls[1].startswith(f"close {cfg.press.close_speed_mps / 2} ")
    assert f"stop_now {cfg.press.stop_squeeze_raw}" in gripper.calls
    assert opened(gripper, cfg)
    assert cfg.press.x_th < outcome.level_at_cross < cfg.press.abort_factor * cfg.press.x_th
    assert outcome.t_cross is not None and outcome.t_stop >= outcome.t_cross
    assert outcome.stop_latency_s is not None and outcome.stop_latency_s < 0.05
    # The recording covers the model's window around the stop.
    win = outcome.window
    assert win.recv_time[0] <= outcome.t_stop - preprocess.DEFAULT_WINDOW.before_s
    assert win.recv_time[-1] >= outcome.t_stop + preprocess.DEFAULT_WINDOW.after_s
    assert outcomes == [outcome] and ctl.state == "idle" and not ctl.armed


async def test_no_contact_within_the_close_timeout_opens_and_returns():
    cfg = config(close_timeout_s=0.15)
    async with rig(cfg, object_width_m=None) as (ctl, gripper, arm, _, states, _o):
        outcome = await ctl.run()
    assert outcome.result == "no_contact"
    assert "for 0.15 s of closing" in outcome.message
    assert "holding" not in states and states[-3:] == ["opening", "returning", "idle"]
    assert not any(c.startswith("stop_now") for c in gripper.calls) and opened(gripper, cfg)
    assert arm.history == ["above", "lowered", "above"] and outcome.window is None


async def test_a_force_far_past_the_threshold_aborts_and_opens():
    cfg = config()
    async with rig(cfg) as (ctl, gripper, _a, pads, states, _o):
        task = asyncio.create_task(ctl.run())
        while ctl.state != "holding":  # noqa: ASYNC110
            await asyncio.sleep(0.001)
        pads.extra = 4000  # the object gives way under the held squeeze
        outcome = await task
    assert outcome.result == "aborted" and "force far past the threshold" in outcome.message
    assert states[-3:] == ["opening", "returning", "idle"] and opened(gripper, cfg)


async def test_a_stream_gone_stale_while_closing_opens_and_fails_the_press():
    cfg = config(close_timeout_s=2.0)
    async with rig(cfg, object_width_m=None) as (ctl, gripper, arm, pads, _s, _o):
        task = asyncio.create_task(ctl.run())
        while ctl.state != "closing":  # noqa: ASYNC110
            await asyncio.sleep(0.001)
        pads.running = False
        ctl.sensor_stale(StaleSensorError("no frame for 0.1 s"))
        outcome = await task
    assert outcome.result == "stale" and "went stale during the press" in outcome.message
    assert opened(gripper, cfg) and arm.history[-1] == "above"


async def test_a_stale_stream_refuses_the_press_before_anything_moves():
    async with rig() as (ctl, gripper, arm, pads, states, _o):
        pads.running = False
        await asyncio.sleep(0.15)  # older than FRESH_FRAME_S
        outcome = await ctl.run()
    assert outcome.result == "stale" and "not pressing" in outcome.message
    assert gripper.calls == [] and arm.history == [] and states == ["idle"]


async def test_a_frame_held_back_past_the_fresh_limit_delays_the_press_instead_of_failing_it():
    async with rig() as (ctl, gripper, arm, pads, states, _o):
        await asyncio.sleep(preprocess.DEFAULT_WINDOW.before_s)
        pads.running = False
        await asyncio.sleep(0.15)  # older than FRESH_FRAME_S: a host that held frames back
        ctl.sensor_stale(StaleSensorError("no fresh frame for 0.1 s"))  # the sensor task's
        press = asyncio.create_task(ctl.run())
        await asyncio.sleep(0.1)
        assert gripper.calls == [] and arm.history == []  # nothing moves on old data
        pads.running = True
        ctl.sensor_fresh()  # the sensor task, on the frame that ends it
        outcome = await press
    assert outcome.result == "ok" and states == FULL_PRESS, outcome.message


async def test_an_abort_request_while_closing_opens():
    cfg = config(close_timeout_s=2.0)
    async with rig(cfg, object_width_m=None) as (ctl, gripper, arm, _p, _s, _o):
        assert ctl.request_abort() is False  # idle: nothing to abort
        task = asyncio.create_task(ctl.run())
        while ctl.state != "closing":  # noqa: ASYNC110
            await asyncio.sleep(0.001)
        assert ctl.request_abort() is True
        outcome = await task
    assert (outcome.result, outcome.message) == ("aborted", "aborted on request")
    assert opened(gripper, cfg) and arm.history == ["above", "lowered", "above"]


async def test_a_failed_stop_aborts_and_opens():
    cfg = config()
    async with rig(cfg) as (ctl, gripper, _a, _p, _s, _o):
        async def refuse(squeeze_raw: int):
            raise DeviceError("motor 15: no status packet")

        gripper.stop_now = refuse
        outcome = await ctl.run()
    assert outcome.result == "error"
    assert outcome.message.startswith("the stop at the threshold failed (motor 15")
    assert outcome.t_stop is None and opened(gripper, cfg)


async def test_checked_is_resolved_by_the_motor_check_before_anything_moves():
    # The photo waits for it (the recognition): it must come after the check, and before
    # the press's moves, which the photo does not need to wait out.
    seen = []
    async with rig() as (ctl, gripper, arm, _p, _s, _o):
        checked = asyncio.get_running_loop().create_future()
        arm.history.clear()

        async def recover():
            seen.append(("recover", checked.done()))

        def on_state(state: str) -> None:
            if state == "above":
                seen.append(("above", checked.done(), list(gripper.calls), list(arm.history)))

        ctl.recover, ctl.on_state = recover, on_state
        outcome = await ctl.run(None, checked)
    assert outcome.result == "ok"
    assert seen == [("recover", False), ("above", True, [], [])]


async def test_a_gripper_that_cannot_open_leaves_the_arm_where_it_stands():
    cfg = config()
    recoveries = []

    async def recover():
        recoveries.append(1)

    async with rig(cfg) as (ctl, gripper, arm, _, states, _o):
        ctl.recover = recover
        real_open = gripper.open
        calls = {"n": 0}

        async def open_once_then_fail(width_m: float, current_cap_ma: float) -> None:
            calls["n"] += 1
            if calls["n"] > 1:  # the first opening (before the press) works
                raise DeviceError("motor 15: no status packet")
            await real_open(width_m, current_cap_ma)

        gripper.open = open_once_then_fail
        outcome = await ctl.run()
    assert outcome.result == "error"
    assert f"GRIPPER MAY STILL BE CLOSED: opening failed {OPEN_TRIES} times" in outcome.message
    assert outcome.message.endswith("arm left where it stands: free the object by hand")
    assert arm.history == ["above", "lowered"]  # never lifted with the object held
    assert "returning" not in states and calls["n"] == 1 + OPEN_TRIES
    assert len(recoveries) == 1 + OPEN_TRIES  # before the press, and after each failure


async def test_an_arm_that_fails_to_lower_opens_and_returns():
    cfg = config()
    async with rig(cfg) as (ctl, gripper, arm, _, states, _o):
        arm.history.clear()
        real_move = arm.move_to

        async def fail_lowered(pose: str, timeout_s: float = 5.0) -> None:
            if pose == "lowered":
                raise DeviceError("joint 12: did not reach 'lowered'")
            await real_move(pose, timeout_s)

        arm.move_to = fail_lowered
        outcome = await ctl.run()
    assert outcome.result == "error" and "joint 12" in outcome.message
    assert states == ["above", "lowered", "opening", "returning", "idle"]
    assert opened(gripper, cfg) and arm.history == ["above", "above"]


async def test_the_recording_covers_the_window_the_controller_is_given():
    wide = preprocess.WindowSpec(before_s=0.4, after_s=0.9)
    async with rig() as (ctl, _g, _a, _p, _s, _o):
        ctl.window = wide
        outcome = await ctl.run()
    assert outcome.window.recv_time[-1] >= outcome.t_stop + wide.after_s


async def test_the_window_is_handed_over_at_the_crops_last_sample_then_the_margin_recorded():
    spec = preprocess.DEFAULT_WINDOW
    async with rig() as (ctl, _g, _a, _p, _s, _o):
        await asyncio.sleep(spec.before_s)
        window_ready: asyncio.Future[PressOutcome] = asyncio.get_running_loop().create_future()
        press = asyncio.create_task(ctl.run(window_ready))
        handed = await window_ready
        t_handed = asyncio.get_running_loop().time()
        # What the analysis takes at that moment: the crop's frames, through the first frame
        # at or past its last sample, and no further; the press has not ended.
        early = handed.window
        last_sample = handed.t_stop + spec.last_sample_s
        assert early.recv_time[-1] >= last_sample > early.recv_time[-2]
        print(f"handed over {1e3 * (t_handed - last_sample):.1f} ms after the crop's last "
              "sample")
        assert t_handed - last_sample < 0.1 and not press.done()
        outcome = await press
    # Then the recording's margin: the window stored with the press reaches further, to
    # (within a frame or a late one of) the margin's end, not past it.
    end = outcome.t_stop + spec.after_s + RECORD_MARGIN_S
    assert outcome is handed and end - 0.05 < outcome.window.recv_time[-1] <= end
    assert len(outcome.window.raw) > len(early.raw)


@pytest.mark.parametrize("at", ["above", "lowered", "tare"])
async def test_an_abort_request_before_closing_stops_the_press_there(at):
    cfg = config()
    async with rig(cfg) as (ctl, gripper, arm, _p, states, _o):
        answers = []

        def on_state(state: str) -> None:
            states.append(state)
            if state == at:  # asked the moment the press gets there
                answers.append(ctl.request_abort())

        ctl.on_state = on_state
        outcome = await ctl.run()
    assert answers == [True]
    assert (outcome.result, outcome.message) == ("aborted", "aborted on request")
    assert "closing" not in states and not any(c.startswith("close") for c in gripper.calls)
    assert opened(gripper, cfg) and arm.history[-1] == "above"
