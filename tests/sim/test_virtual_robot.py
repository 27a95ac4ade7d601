"""The virtual robot's bus is the daemon's bus with the simulator's executor: its exit closes
the bus as the daemon's shutdown does (torque off, watchdog disarmed, feed ended, port
released), all on the virtual clock."""

import asyncio
import functools

import numpy as np

from edge.core.errors import DeviceError
from edge.lab.record import CLOCK_START_S, sim_config
from edge.sim.virtual import VirtualClockLoop, VirtualRobot


def on_virtual_clock(coro):
    with asyncio.Runner(loop_factory=functools.partial(VirtualClockLoop, CLOCK_START_S)) as r:
        return r.run(coro)


def test_exit_turns_torque_off_and_ends_the_watchdog_feed():
    cfg = sim_config()
    ids = (*cfg.bus.joint_ids, cfg.bus.gripper_id)

    async def scenario():
        me = asyncio.current_task()
        async with VirtualRobot(cfg, "wood_cube", np.random.default_rng(0)) as robot:
            # As the recorder does: torque on starts the watchdog feed on the loop.
            await robot.bus.set_torque(True)
            await asyncio.sleep(3 * cfg.bus.watchdog_ms / 1000.0)
            armed = {i: robot.dxl.get_register(i, "Torque Enable") for i in ids}
            fed = [t.get_name() for t in asyncio.all_tasks() if t is not me]
        left = [t.get_name() for t in asyncio.all_tasks() if t is not me]
        torque = {i: robot.dxl.get_register(i, "Torque Enable") for i in ids}
        watchdog = {i: robot.dxl.get_register(i, "Bus Watchdog") for i in ids}
        try:
            await robot.bus.read_state()
        except DeviceError as exc:
            after = str(exc)
        else:
            after = "the bus still answers"
        return armed, fed, left, torque, watchdog, after

    armed, fed, left, torque, watchdog, after = on_virtual_clock(scenario())
    print(f"\ntasks while pressing {fed}, after exit {left}; torque after exit {torque}")
    assert set(armed.values()) == {1} and "dxl-watchdog-feed" in fed
    assert left == []
    assert set(torque.values()) == {0} and set(watchdog.values()) == {0}
    assert after.endswith("is not connected")
