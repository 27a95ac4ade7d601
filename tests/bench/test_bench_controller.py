"""The bench's one press controller (``assemble(..., controller_factory=BenchController)``),
switched between presses among the compared ways of checking the threshold, on the fakes of
the press controller's own tests."""

from __future__ import annotations

import asyncio
import contextlib

import pytest

from edge.bench.controllers import TICK_PERIOD_S, BenchController
from edge.bench.settings import CONTROLLERS
from edge.core import preprocess
from edge.core.errors import BusyError
from edge.runtime.press import PressController
from edge.runtime.ring import FrameRing
from tests.runtime.test_press import Pads, config
from tests.support.fakes import FakeArm, FakeGripper
from tests.support.waits import wait_until

pytestmark = pytest.mark.asyncio


async def test_each_compared_controller_presses_and_stops_with_the_one_controller():
    cfg = config()
    ring = FrameRing(96, 20000)
    gripper = FakeGripper(object_width_m=0.005, start_width_m=0.01)
    ctl = BenchController(cfg, gripper, FakeArm(cfg.poses, start="rest"), ring)
    pads = Pads(ring, gripper)
    pads.controller = ctl  # as the sensor task: ctl.check with every frame
    task = asyncio.create_task(pads.run())
    try:
        await asyncio.sleep(preprocess.DEFAULT_WINDOW.before_s)
        assert set(TICK_PERIOD_S) == set(CONTROLLERS)
        for name in CONTROLLERS:
            ctl.use(name)
            # Per frame: the production check itself, nothing added on the frame's path.
            # Ticked: the frame's call only keeps the frame, so a stop proves the tick's check.
            per_frame = TICK_PERIOD_S[name] is None
            assert (ctl.check.__func__ is PressController.check) == per_frame, name
            pressing = asyncio.create_task(ctl.run())
            await wait_until(lambda: ctl.state == "closing", 5.0, "closing",
                             interval_s=0.001)
            with pytest.raises(BusyError, match="between presses"):
                ctl.use("per_frame")
            outcome = await pressing
            print(f"{name}: {outcome.result}, stop latency "
                  f"{1e3 * (outcome.stop_latency_s or float('nan')):.2f} ms")
            assert outcome.result == "ok", (name, outcome.message)
            assert outcome.t_stop is not None and f"stop_now {cfg.press.stop_squeeze_raw}" \
                in gripper.calls
            assert ctl.outcomes.get_nowait() is outcome and ctl.outcomes.empty()
            gripper.calls.clear()
        ctl.use("per_frame")  # back from a ticked one: the production check again
        assert ctl.check.__func__ is PressController.check
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    # No ticker is left behind by a ticked press.
    assert not [t for t in asyncio.all_tasks() if t.get_name().startswith("bench-")]
