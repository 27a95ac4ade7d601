"""The protocol transactions of the bus: what runs on its owner, one SDK call sequence each.

Every SDK failure becomes :class:`MotorError` with the motor ID and the SDK's own message
(``getTxRxResult`` / ``getRxPacketError``). Reads and single-register writes are tried twice
before a timeout or a bad reply is an error. Every state read is remembered per motor
(:class:`SeenState`) for the stop to extrapolate from, and every answer per motor
(``heard``) for the Bus Watchdog's feed.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import TypeVar

import dynamixel_sdk as sdk

from edge.core.errors import DeviceError, MotorError
from edge.hw.control_table import (
    RAW_PER_S_PER_VELOCITY_UNIT,
    XM430_W350,
    Register,
    describe_hardware_error,
)
from edge.hw.dynamixel.port import CheckedPacketHandler

# Reads and single-register writes are tried this often before a timeout or a bad reply
# is an error.
READ_ATTEMPTS = 2
_TRANSIENT = (sdk.COMM_RX_TIMEOUT, sdk.COMM_RX_CORRUPT)
_R = TypeVar("_R")
# Protocol 2.0 status error number (not a bit field): "Data Range Error".
ERR_DATA_RANGE = 4
# Before a retry: how long late replies to the failed attempt are waited for and dropped.
LATE_REPLY_DRAIN_S = 0.05

_T = XM430_W350
MODEL_NUMBER = _T["Model Number"]
FIRMWARE_VERSION = _T["Firmware Version"]
RETURN_DELAY_TIME = _T["Return Delay Time"]
DRIVE_MODE = _T["Drive Mode"]
OPERATING_MODE = _T["Operating Mode"]
CURRENT_LIMIT = _T["Current Limit"]
TORQUE_ENABLE = _T["Torque Enable"]
STATUS_RETURN_LEVEL = _T["Status Return Level"]
HARDWARE_ERROR_STATUS = _T["Hardware Error Status"]
BUS_WATCHDOG = _T["Bus Watchdog"]
GOAL_CURRENT = _T["Goal Current"]
PROFILE_ACCELERATION = _T["Profile Acceleration"]
PROFILE_VELOCITY = _T["Profile Velocity"]
GOAL_POSITION = _T["Goal Position"]
MOVING = _T["Moving"]
PRESENT_CURRENT = _T["Present Current"]
PRESENT_VELOCITY = _T["Present Velocity"]
PRESENT_POSITION = _T["Present Position"]
# One sync read covers Present Current (126), Present Velocity (128), Present Position (132).
_STATE_START = PRESENT_CURRENT.address
_STATE_LENGTH = PRESENT_POSITION.end - _STATE_START


@dataclass(frozen=True)
class MotorState:
    """Present values of one motor, raw units (position counts, 0.229 rev/min, 2.69 mA)."""

    position: int
    velocity: int
    current: int


@dataclass(frozen=True)
class BusState:
    """One sync read of all motors; ``t`` is the bus clock (monotonic) when it completed."""

    t: float
    motors: Mapping[int, MotorState]


@dataclass(frozen=True)
class SeenState:
    """A motor's position and velocity as last read; ``t`` is when the read's instruction
    went out (the motor sampled no earlier: extrapolating from ``t`` never falls short)."""

    t: float
    position: int
    velocity_raw_s: float


class Transactions:
    """The SDK calls of one bus on an open port (``port``, set by the bring-up); called on
    the bus's owner only."""

    def __init__(self, port_name: str, ids: tuple[int, ...], clock: Callable[[], float]) -> None:
        self.port_name = port_name
        self.ids = ids
        self.clock = clock
        self.ph = CheckedPacketHandler()
        self.port: sdk.PortHandler | None = None
        # Opened with connect(configure=False): nothing is ever written to a motor.
        self.read_only = False
        self.last_state: BusState | None = None
        # Per motor: the state last read, and when its last Goal Position write completed.
        self.seen: dict[int, SeenState] = {}
        self.goal_t: dict[int, float] = {}
        # Per motor: when it last answered a packet (it heard the bus then: its Bus Watchdog
        # started counting again).
        self.heard: dict[int, float] = {}

    def refuse_if_read_only(self, what: str) -> None:
        if self.read_only:
            raise DeviceError(f"Dynamixel bus on {self.port_name} is open read-only: "
                              f"{what} refused")

    def check(self, motor_id: int, what: str, result: int, error: int) -> None:
        if result != sdk.COMM_SUCCESS:
            raise MotorError(f"motor {motor_id}: {what}: {self.ph.getTxRxResult(result)}",
                             motor_id, transient=result in _TRANSIENT)
        self.heard[motor_id] = self.clock()
        if error:
            message = self.ph.getRxPacketError(error)
            if error & sdk.ERRBIT_ALERT:
                other = error & ~sdk.ERRBIT_ALERT
                if other:
                    message += " " + self.ph.getRxPacketError(other)
                message += f" Hardware Error Status: {self._hardware_error_detail(motor_id)}"
            elif error & ~sdk.ERRBIT_ALERT == ERR_DATA_RANGE and self._watchdog_tripped(motor_id):
                # A tripped Bus Watchdog refuses every goal with a range error: say why.
                message += (" (its Bus Watchdog has tripped: the host was silent on the bus"
                            " longer than the watchdog allows)")
            raise MotorError(f"motor {motor_id}: {what}: {message}", motor_id)

    @contextlib.contextmanager
    def expect(self, params: int) -> Iterator[None]:
        """Status packets carry ``params`` parameters until the block ends."""
        self.ph.expect_params = params
        try:
            yield
        finally:
            self.ph.expect_params = None

    def settle(self, result: int) -> None:
        """The transaction read every status packet it caused (``result`` COMM_SUCCESS):
        nothing is left on the input (CheckedPacketHandler.settled)."""
        if result == sdk.COMM_SUCCESS:
            self.ph.settled = True

    def drain_late_replies(self) -> None:
        # Replies that come after the SDK gave up must not be read as the retry's answer (a
        # same-size status would pass for it): let them arrive, then drop them.
        time.sleep(LATE_REPLY_DRAIN_S)
        self.port.clearPort()

    def _hardware_error_detail(self, motor_id: int) -> str:
        with self.expect(HARDWARE_ERROR_STATUS.size):
            status, result, _ = self.ph.read1ByteTxRx(self.port, motor_id,
                                                      HARDWARE_ERROR_STATUS.address)
        if result != sdk.COMM_SUCCESS:
            return "unreadable"
        return f"0x{status:02x} ({describe_hardware_error(status)})"

    def _watchdog_tripped(self, motor_id: int) -> bool:
        with self.expect(BUS_WATCHDOG.size):
            value, result, _ = self.ph.read1ByteTxRx(self.port, motor_id, BUS_WATCHDOG.address)
        return result == sdk.COMM_SUCCESS and BUS_WATCHDOG.from_unsigned(value) == -1

    def read(self, motor_id: int, reg: Register, attempts: int = READ_ATTEMPTS) -> int:
        """One register of one motor; ``attempts`` 1 for a motor that may be silent (each
        try waits out the reply's timeout while every other motor hears nothing)."""
        return self.read_span(motor_id, (reg,), attempts)[reg]

    def read_span(self, motor_id: int, regs: tuple[Register, ...],
                  attempts: int = READ_ATTEMPTS) -> dict[Register, int]:
        """Several registers of one motor in one READ (from the first one's address to the
        last one's end)."""
        start = min(r.address for r in regs)
        length = max(r.end for r in regs) - start
        what = f"read {regs[0].name}" if len(regs) == 1 else f"read {regs[0].name}..{regs[-1].name}"
        with self.expect(length):
            for _ in range(attempts - 1):
                # A lost or garbled reply is retried once: reads have no side effect.
                data, result, error = self.ph.readTxRx(self.port, motor_id, start, length)
                if result not in _TRANSIENT:
                    break
                self.drain_late_replies()
            else:
                data, result, error = self.ph.readTxRx(self.port, motor_id, start, length)
        self.settle(result)
        self.check(motor_id, what, result, error)
        return {r: r.decode(bytes(data[r.address - start:r.end - start])) for r in regs}

    def read_motor_state(self, motor_id: int) -> MotorState:
        """One motor's present state in a READ of its own: a silent other motor, which fails
        a sync read of them all, does not fail this."""
        t_sent = self.clock()  # the motor samples after this: see SeenState
        values = self.read_span(motor_id, (PRESENT_CURRENT, PRESENT_VELOCITY, PRESENT_POSITION))
        state = MotorState(position=values[PRESENT_POSITION], velocity=values[PRESENT_VELOCITY],
                           current=values[PRESENT_CURRENT])
        self.seen[motor_id] = SeenState(t_sent, state.position,
                                        state.velocity * RAW_PER_S_PER_VELOCITY_UNIT)
        return state

    def write(self, motor_id: int, reg: Register, value: int,
              packet: bytes | None = None) -> None:
        """``packet``: this write's instruction packet built ahead (the stop's: stop.StopPacket),
        sent as it is instead of the SDK building it."""
        self.refuse_if_read_only(f"motor {motor_id}: write {reg.name}")
        if packet is None:
            write = {1: self.ph.write1ByteTxRx, 2: self.ph.write2ByteTxRx,
                     4: self.ph.write4ByteTxRx}[reg.size]

            def send() -> tuple[int, int]:
                return write(self.port, motor_id, reg.address, reg.to_unsigned(value))
        else:
            def send() -> tuple[int, int]:
                _, result, error = self.ph.txRxPacket(self.port, packet)
                return result, error
        with self.expect(0):
            for _ in range(READ_ATTEMPTS - 1):
                # A lost or garbled status packet is written again once: every register
                # written here takes an absolute value, so a second delivery changes nothing.
                result, error = send()
                if result not in _TRANSIENT:
                    break
                self.drain_late_replies()
            else:
                result, error = send()
        self.settle(result)
        if reg is GOAL_POSITION:
            # A new goal changes the motion: states read before it say nothing about it now.
            self.goal_t[motor_id] = self.clock()
        self.check(motor_id, f"write {reg.name} = {value}", result, error)

    def sync_write(self, reg: Register, values: Mapping[int, int]) -> None:
        self.refuse_if_read_only(f"sync write {reg.name}")
        param: list[int] = []
        for motor_id, value in values.items():
            param += [motor_id, *reg.encode(value)]
        result = self.ph.syncWriteTxOnly(self.port, reg.address, reg.size, param, len(param))
        now = self.clock()
        if reg is GOAL_POSITION:
            self.goal_t.update(dict.fromkeys(values, now))
        if result != sdk.COMM_SUCCESS:
            first = next(iter(values), None)
            raise MotorError(f"motors {sorted(values)}: sync write {reg.name}: "
                             f"{self.ph.getTxRxResult(result)}", first)
        # (No status packets: each motor named in the packet heard it.)
        self.heard.update(dict.fromkeys(values, now))

    def read_state(self) -> BusState:
        return self._sync_read(self._read_state_once)

    def _sync_read(self, read: Callable[[], _R]) -> _R:
        # A lost or garbled reply is retried once: a sync read has no side effect.
        for _ in range(READ_ATTEMPTS - 1):
            try:
                return read()
            except MotorError as exc:
                if not exc.transient:
                    raise
                self.drain_late_replies()
        return read()

    def _read_state_once(self) -> BusState:
        # The SDK's SYNC READ transmit, then its per-motor receive, so that a failure names
        # its motor and the error byte (e.g. a hardware alert) is checked, which
        # GroupSyncRead.rxPacket drops.
        t_sent = self.clock()  # the motors sample after this: see SeenState
        result = self.ph.syncReadTx(self.port, _STATE_START, _STATE_LENGTH, list(self.ids),
                                    len(self.ids), False)
        if result != sdk.COMM_SUCCESS:
            raise MotorError(f"motors {list(self.ids)}: sync read of present state: "
                             f"{self.ph.getTxRxResult(result)}", self.ids[0])
        motors = {}
        for motor_id in self.ids:
            with self.expect(_STATE_LENGTH):
                data, result, error = self.ph.readRx(self.port, motor_id, _STATE_LENGTH)
            self.check(motor_id, "sync read of present state", result, error)
            motors[motor_id] = MotorState(
                position=_field(PRESENT_POSITION, data),
                velocity=_field(PRESENT_VELOCITY, data),
                current=_field(PRESENT_CURRENT, data),
            )
        self.settle(sdk.COMM_SUCCESS)
        state = BusState(self.clock(), motors)
        self.last_state = state
        for motor_id, m in motors.items():
            self.seen[motor_id] = SeenState(t_sent, m.position,
                                            m.velocity * RAW_PER_S_PER_VELOCITY_UNIT)
        return state

    def sync_read_register(self, reg: Register) -> dict[int, int]:
        """One register of every motor in one SYNC READ (one round trip, not one each)."""
        return self._sync_read(lambda: self._sync_read_register_once(reg))

    def _sync_read_register_once(self, reg: Register) -> dict[int, int]:
        result = self.ph.syncReadTx(self.port, reg.address, reg.size, list(self.ids),
                                    len(self.ids), False)
        if result != sdk.COMM_SUCCESS:
            raise MotorError(f"motors {list(self.ids)}: sync read of {reg.name}: "
                             f"{self.ph.getTxRxResult(result)}", self.ids[0])
        values = {}
        for motor_id in self.ids:
            with self.expect(reg.size):
                data, result, error = self.ph.readRx(self.port, motor_id, reg.size)
            self.check(motor_id, f"sync read of {reg.name}", result, error)
            values[motor_id] = reg.decode(bytes(data))
        return values


def _field(reg: Register, data: list[int]) -> int:
    start = reg.address - _STATE_START
    return reg.decode(bytes(data[start:start + reg.size]))
