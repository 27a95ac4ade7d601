"""The Dynamixel bus driver (Protocol 2.0 over ``dynamixel_sdk``), as lerobot has
``motors/dynamixel/``: :mod:`.bus` the bus the arm uses, :mod:`.executor` the owner its
operations run on, :mod:`.transactions` the SDK calls, :mod:`.bringup` finding, configuring
and arming the motors, :mod:`.stop` the stop's goal, :mod:`.port` the SDK's port handlers."""

from edge.hw.dynamixel.bringup import XM430_MODELS, MotorInfo
from edge.hw.dynamixel.bus import DynamixelBus
from edge.hw.dynamixel.executor import STOP_HANDOVER_MAX_S, Executor, ThreadExecutor
from edge.hw.dynamixel.port import (
    LATENCY_TIMER_DIR,
    LATENCY_TIMER_UDEV_RULE,
    BlockingPortHandler,
    CheckedPacketHandler,
    latency_timer_path,
    read_latency_timer,
)
from edge.hw.dynamixel.stop import STOP_STATE_MAX_AGE_S, STOP_STATE_SETTLE_S, StopRecord
from edge.hw.dynamixel.transactions import BusState, MotorState, SeenState

__all__ = [
    "LATENCY_TIMER_DIR",
    "LATENCY_TIMER_UDEV_RULE",
    "STOP_HANDOVER_MAX_S",
    "STOP_STATE_MAX_AGE_S",
    "STOP_STATE_SETTLE_S",
    "XM430_MODELS",
    "BlockingPortHandler",
    "BusState",
    "CheckedPacketHandler",
    "DynamixelBus",
    "Executor",
    "MotorInfo",
    "MotorState",
    "SeenState",
    "StopRecord",
    "ThreadExecutor",
    "latency_timer_path",
    "read_latency_timer",
]
