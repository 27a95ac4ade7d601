"""``running(daemon)``, the one start/stop glue of ``vt-edge run``, the tests' daemon and the
bench: a runtime that dies before it is ready is reported with its own error, at once, and
leaves the arm safe."""

from __future__ import annotations

import time
from dataclasses import replace

import pytest

from edge.app import assemble, running
from edge.sim.robot import SimRobot
from tests.support.daemon import QUICK_OBJECT, base_config, fast_config, gripper_open
from tests.support.fakes import FakeButton

pytestmark = pytest.mark.asyncio
# Far longer than the start takes: entering must end with the runtime's error, not this.
READY_WITHIN_S = 60.0


class FailingButton(FakeButton):
    """A button driver with a bug: its presses fail at once, so the runtime's button task
    dies before the runtime is ready (its warm-up comes after the tasks start)."""

    async def presses(self):
        raise RuntimeError("button bug")
        yield  # (an async generator, as the contract's)


async def test_a_runtime_dying_before_it_is_ready_raises_its_error_not_a_timeout(tmp_path):
    async with SimRobot(QUICK_OBJECT, seed=4, cfg=base_config()) as robot:
        cfg = robot.runtime_config(fast_config())
        cfg = replace(cfg, runtime=replace(cfg.runtime, state_dir=str(tmp_path)))
        with pytest.raises(ExceptionGroup) as err:
            async with assemble(cfg, button=FailingButton()) as daemon:
                t0 = time.monotonic()
                async with running(daemon, READY_WITHIN_S):
                    pytest.fail("entered although the runtime died")
        took_s = time.monotonic() - t0
        print(f"the runtime's error came {took_s:.2f} s after running() was entered")
        assert err.group_contains(RuntimeError, match="button bug")
        assert took_s < READY_WITHIN_S / 2 and not daemon.runtime.ready.is_set()
        assert gripper_open(robot)
        ids = (*cfg.bus.joint_ids, cfg.bus.gripper_id)
        assert {robot.dxl.get_register(i, "Torque Enable") for i in ids} == {0}
