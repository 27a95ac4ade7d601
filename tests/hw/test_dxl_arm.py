"""Arm and gripper: the width formula, the fakes, and the Dynamixel implementations on the
emulator (their conformance to the contracts: tests/hw/test_contracts.py)."""

from __future__ import annotations

import time

import pytest

from edge.core.config import BusConfig
from edge.core.errors import DeviceTimeoutError
from edge.hw.arm import DynamixelArm, gripper_raw, gripper_width_m
from edge.hw.contracts import GripperStop
from edge.hw.dynamixel import DynamixelBus
from edge.sim.dxl_emulator import DxlEmulator
from tests.support.fakes import FakeArm, FakeGripper

POSES = {"home": (2048, 2048, 2048, 2048), "above": (2048, 1800, 2300, 2048)}


def test_width_formula_and_its_inverse():
    assert gripper_width_m(2048) == pytest.approx(0.0, abs=1e-6)
    assert gripper_width_m(3126) == pytest.approx(0.019, abs=2e-5)
    for width in (-0.010, 0.0, 0.005, 0.019):
        assert gripper_width_m(gripper_raw(width)) == pytest.approx(width, abs=1e-5)
        assert gripper_width_m(gripper_raw(width, True), True) == pytest.approx(width, abs=1e-5)
    # Reversed, closing is toward increasing raw.
    assert gripper_raw(-0.010, True) > gripper_raw(0.019, True)


@pytest.mark.asyncio
async def test_fake_gripper_closes_onto_the_object_and_stops():
    now = [0.0]
    gripper = FakeGripper(object_width_m=0.005, clock=lambda: now[0])
    await gripper.close(speed_mps=0.01, current_cap_ma=300)
    now[0] = 1.0
    state = await gripper.state()
    assert state.width_m == pytest.approx(0.009) and state.squeeze_ma == 0
    now[0] = 3.0
    state = await gripper.state()
    assert state.width_m == pytest.approx(0.005) and state.squeeze_ma == 300
    stop = await gripper.stop_now(2)
    assert stop == GripperStop(gripper_raw(0.005) - 2, 3.0)  # past present, closing = down
    await gripper.open(0.015, 538)
    assert (await gripper.state()).width_m == pytest.approx(0.015)
    assert gripper.calls == ["close 0.01 300", "stop_now 2", "open 0.015 538"]


@pytest.mark.asyncio
async def test_fake_arm_records_moves_and_fails_on_demand():
    arm = FakeArm(POSES)
    await arm.move_to("above")
    assert await arm.joints() == POSES["above"] and arm.history == ["above"]
    arm.fail_next = DeviceTimeoutError("stuck")
    with pytest.raises(DeviceTimeoutError):
        await arm.move_to("home")
    with pytest.raises(ValueError, match="known: above, home"):
        await arm.move_to("nowhere")


@pytest.mark.asyncio
async def test_dynamixel_arm_moves_on_a_time_based_profile():
    with DxlEmulator() as emu:
        async with DynamixelBus(BusConfig(port=emu.port)) as bus:
            await bus.set_torque(True)
            arm = DynamixelArm(bus, POSES, move_time_s=0.3, accel_time_s=0.1, tolerance_raw=2)
            t0 = time.monotonic()
            await arm.move_to("above", timeout_s=3.0)
            took = time.monotonic() - t0
            print(f"\nmove_to('above') on a 0.3 s profile took {took * 1e3:.0f} ms")
            assert 0.2 < took < 2.0
            joints = await arm.joints()
            assert all(abs(j - g) <= 2 for j, g in zip(joints, POSES["above"], strict=True))
            assert emu.get_register(12, "Profile Velocity") == 300
            slow = DynamixelArm(bus, POSES, move_time_s=5.0)
            with pytest.raises(DeviceTimeoutError, match="joint 12 at"):
                await slow.move_to("home", timeout_s=0.1)
