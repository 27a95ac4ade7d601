"""The arm and gripper over the Dynamixel bus (contracts in :mod:`edge.hw.contracts`).

Positions are raw Dynamixel counts (4096 per turn) unless a name says metres. The gripper's
width follows the current ROBOTIS description of the OpenMANIPULATOR-X:
``width_m = raw * 1.7626621790e-5 - 0.036099321`` with the default Drive Mode (closing
toward decreasing raw). With Drive Mode bit 0 (reverse) the driver mirrors the raw value
(``4096 - raw``) before that formula, so closing is toward increasing raw: an assumption to
check on an arm that really runs reversed.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping

from edge.core.errors import DeviceTimeoutError
from edge.hw.contracts import (
    DEFAULT_MOVE_TIMEOUT_S,
    GripperState,
    GripperStop,
    JointPose,
    named_pose,
)
from edge.hw.control_table import CURRENT_MA_PER_UNIT, RAW_PER_REV, RAW_PER_S_PER_VELOCITY_UNIT
from edge.hw.dynamixel import DynamixelBus

GRIPPER_M_PER_RAW = 1.7626621790e-5
GRIPPER_OFFSET_M = 0.036099321
# The OpenMANIPULATOR-X gripper joint range (ROBOTIS description).
GRIPPER_OPEN_WIDTH_M = 0.019
# Joint ("width") speed when opening.
GRIPPER_OPEN_SPEED_MPS = 0.02
GRIPPER_CLOSED_WIDTH_M = -0.010

DEFAULT_GRIPPER_TIMEOUT_S = 3.0


def gripper_width_m(raw: float, reverse: bool = False) -> float:
    """Gripper width in metres from the gripper motor's raw position."""
    if reverse:
        raw = RAW_PER_REV - raw
    return raw * GRIPPER_M_PER_RAW - GRIPPER_OFFSET_M


def gripper_raw(width_m: float, reverse: bool = False) -> int:
    """The gripper motor's raw position for a width in metres (inverse of the above)."""
    raw = round((width_m + GRIPPER_OFFSET_M) / GRIPPER_M_PER_RAW)
    return RAW_PER_REV - raw if reverse else raw


class DynamixelGripper:
    """The gripper motor (current-based position) on a connected :class:`DynamixelBus`."""

    def __init__(
        self,
        bus: DynamixelBus,
        *,
        closed_width_m: float = GRIPPER_CLOSED_WIDTH_M,
        open_speed_mps: float = GRIPPER_OPEN_SPEED_MPS,
        tolerance_raw: int = 15,
        timeout_s: float = DEFAULT_GRIPPER_TIMEOUT_S,
        poll_interval_s: float = 0.01,
    ) -> None:
        self._bus = bus
        self._id = bus.config.gripper_id
        self._closed_width_m = closed_width_m
        self._open_speed_mps = open_speed_mps
        self._tolerance_raw = tolerance_raw
        self._timeout_s = timeout_s
        self._poll_interval_s = poll_interval_s

    @property
    def _reverse(self) -> bool:
        return self._bus.motors[self._id].reverse

    @property
    def closing_sign(self) -> int:
        """+1 if closing increases the raw position (reverse Drive Mode), else -1."""
        return 1 if self._reverse else -1

    async def open(self, width_m: float, current_cap_ma: float) -> None:
        # The gripper's own ID only, every read and write: opening is every press's way out,
        # and must work while another motor does not answer.
        goal = gripper_raw(width_m, self._reverse)
        # Not checked against the Current Limit as close() does: opening is every press's
        # way out, and a cap the motor refuses comes back as a MotorError the caller retries,
        # where a ValueError would skip the retries.
        cap = round(current_cap_ma / CURRENT_MA_PER_UNIT)
        await self._bus.write(self._id, "Goal Current", cap)
        await self._bus.write(self._id, "Profile Velocity", _velocity_units(self._open_speed_mps))
        await self._bus.write(self._id, "Goal Position", goal)
        deadline = asyncio.get_running_loop().time() + self._timeout_s
        while True:
            state = await self._bus.read_motor_state(self._id)
            if abs(state.motors[self._id].position - goal) <= self._tolerance_raw:
                return
            if asyncio.get_running_loop().time() > deadline:
                raise DeviceTimeoutError(
                    f"gripper (motor {self._id}) not open within {self._timeout_s} s: at "
                    f"{state.motors[self._id].position}, goal {goal}")
            await asyncio.sleep(self._poll_interval_s)

    async def close(self, speed_mps: float, current_cap_ma: float) -> None:
        cap = round(current_cap_ma / CURRENT_MA_PER_UNIT)
        limit = self._bus.motors[self._id].current_limit
        if not 1 <= cap <= limit:
            raise ValueError(f"current_cap_ma {current_cap_ma} is {cap} units; the gripper "
                             f"takes 1..{limit} (Current Limit, 2.69 mA each)")
        await self._bus.write(self._id, "Goal Current", cap)
        await self._bus.write(self._id, "Profile Velocity", _velocity_units(speed_mps))
        await self._bus.write(self._id, "Goal Position",
                              gripper_raw(self._closed_width_m, self._reverse))

    async def stop_now(self, squeeze_raw: int) -> GripperStop:
        # One WRITE: the goal is extrapolated from the gripper's last state read (the press
        # reads it after every second frame while closing); without a fresh one the bus
        # reads first.
        record = await self._bus.stop_ahead(self._id, self.closing_sign * squeeze_raw)
        # The bus stamps the stop when its packet leaves for the port (the write call), on
        # the bus thread: later than any time taken here before the await, earlier than one
        # taken after.
        return GripperStop(record.goal, record.t_write_call)

    async def state(self) -> GripperState:
        bus_state = await self._bus.read_motor_state(self._id)
        motor = bus_state.motors[self._id]
        # Closing draws current of the closing direction's sign.
        squeeze = motor.current * self.closing_sign * CURRENT_MA_PER_UNIT
        return GripperState(bus_state.t, gripper_width_m(motor.position, self._reverse),
                            squeeze, motor.position)


def _velocity_units(speed_mps: float) -> int:
    """Profile Velocity units (0.229 rev/min) for a gripper width speed in m/s (at least 1:
    0 would mean "as fast as possible")."""
    if speed_mps <= 0:
        raise ValueError(f"gripper speed must be > 0 m/s, got {speed_mps}")
    return max(1, round(speed_mps / GRIPPER_M_PER_RAW / RAW_PER_S_PER_VELOCITY_UNIT))


class DynamixelArm:
    """The four joints (position mode, time-based profile) on a connected bus."""

    def __init__(
        self,
        bus: DynamixelBus,
        poses: Mapping[str, JointPose],
        *,
        move_time_s: float = 2.0,
        accel_time_s: float = 0.4,
        tolerance_raw: int = 15,
        poll_interval_s: float = 0.02,
    ) -> None:
        self._bus = bus
        self._joint_ids = tuple(bus.config.joint_ids)
        for name, pose in poses.items():
            if len(pose) != len(self._joint_ids):
                raise ValueError(f"arm pose {name!r} has {len(pose)} joints, the arm has "
                                 f"{len(self._joint_ids)}")
        self._poses = dict(poses)
        self._move_time_ms = round(move_time_s * 1000)
        self._accel_time_ms = round(accel_time_s * 1000)
        self._tolerance_raw = tolerance_raw
        self._poll_interval_s = poll_interval_s

    @property
    def poses(self) -> Mapping[str, JointPose]:
        return self._poses

    async def move_to(self, pose: str, timeout_s: float = DEFAULT_MOVE_TIMEOUT_S) -> None:
        goals = dict(zip(self._joint_ids, named_pose(self._poses, pose), strict=True))
        # Every joint answers before any is sent anywhere: with one silent, the others would
        # go and leave the arm bent between two poses.
        await self._bus.read_state()
        await self._bus.sync_write("Profile Acceleration",
                                   dict.fromkeys(self._joint_ids, self._accel_time_ms))
        await self._bus.sync_write("Profile Velocity",
                                   dict.fromkeys(self._joint_ids, self._move_time_ms))
        await self._bus.write_goal_positions(goals)
        deadline = asyncio.get_running_loop().time() + timeout_s
        while True:
            state = await self._bus.read_state()
            off = {i: state.motors[i].position for i in self._joint_ids
                   if abs(state.motors[i].position - goals[i]) > self._tolerance_raw}
            if not off:
                return
            if asyncio.get_running_loop().time() > deadline:
                detail = ", ".join(f"joint {i} at {p} (goal {goals[i]})" for i, p in off.items())
                raise DeviceTimeoutError(f"arm did not reach pose {pose!r} within "
                                         f"{timeout_s} s: {detail}")
            await asyncio.sleep(self._poll_interval_s)

    async def joints(self) -> JointPose:
        state = await self._bus.read_state()
        a, b, c, d = (state.motors[i].position for i in self._joint_ids)
        return (a, b, c, d)
