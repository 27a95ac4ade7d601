"""The Dynamixel bus driver: the real ``dynamixel_sdk`` (Protocol 2.0) behind one owner thread.

The SDK is blocking and not thread-safe, so exactly one thread (``dxl-bus``) ever calls it.
The asyncio side submits operations and awaits futures that the thread resolves with
``loop.call_soon_threadsafe``; no SDK call ever runs on the event loop. The thread sleeps in
``select()`` on an eventfd that every submission writes to. Operations run one at a time in
submission order, except stops: they go to an urgent queue the thread empties before taking
anything else, so a stop waits at most for the one transaction already on the wire (the bus
is half duplex: a transaction in flight cannot be interrupted without colliding with the
replies).

The stop (:meth:`DynamixelBus.stop_ahead`) is one WRITE of Goal Position: the goal comes from
the motor's last state read (position and velocity, stamped when the read went out),
extrapolated to the moment of the write, plus the squeeze. Only a state too old, or one read
before the motor's last goal, makes it read Present Position first (counted in
:attr:`DynamixelBus.stop_fallbacks`). Handing a stop to the bus thread, the event loop waits
(at most ``STOP_HANDOVER_MAX_S``) until the stop's packet is on the wire: the loop's thread
sleeps, so the bus thread gets the GIL and, on a busy host, the loop's core at once.

The SDK waits for status packets by spinning in pure Python, which holds the GIL and delays
the event loop by up to the interpreter's switch interval (5 ms). :class:`BlockingPortHandler`
replaces the spin: its reads wait in ``select()`` (GIL released) for the bytes or the SDK's own
packet deadline. ``tests/hw/test_dxl_bus.py`` measures the difference.

Every SDK failure becomes :class:`MotorError` with the motor ID and the SDK's own message
(``getTxRxResult`` / ``getRxPacketError``).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import errno
import fcntl
import logging
import math
import os
import select
import threading
import time
from collections.abc import Awaitable, Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import dynamixel_sdk as sdk

from edge import SERVICE_NAME
from edge.core.config import BusConfig
from edge.core.errors import BusInUseError, DeviceError, EdgeError, MotorError
from edge.hw.control_table import (
    BUS_WATCHDOG_UNIT_S,
    DRIVE_MODE_REVERSE,
    DRIVE_MODE_TIME_BASED_PROFILE,
    MODE_CURRENT_BASED_POSITION,
    MODE_POSITION,
    RAW_PER_S_PER_VELOCITY_UNIT,
    XM430_W350,
    Register,
    describe_hardware_error,
)

_log = logging.getLogger(__name__)

LATENCY_TIMER_DIR = Path("/sys/bus/usb-serial/devices")
LATENCY_TIMER_UDEV_RULE = (
    'ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", ATTR{latency_timer}="1"'
)
# What the SDK's packet timeouts assume (dynamixel_sdk.port_handler.LATENCY_TIMER).
SDK_LATENCY_TIMER_MS = 16.0
# Reads and single-register writes are tried this often before a timeout or a bad reply
# is an error.
READ_ATTEMPTS = 2
_TRANSIENT = (sdk.COMM_RX_TIMEOUT, sdk.COMM_RX_CORRUPT)
# Protocol 2.0 status error number (not a bit field): "Data Range Error".
ERR_DATA_RANGE = 4
# Before a retry: how long late replies to the failed attempt are waited for and dropped.
LATE_REPLY_DRAIN_S = 0.05
# Past the SDK's packet deadline, so the SDK's own timeout check fires after our wait.
_READ_DEADLINE_SLACK_S = 0.0002
THREAD_JOIN_TIMEOUT_S = 2.0
# The stop's goal is extrapolated from a state read no older than this. The press reads the
# gripper after every second tactile frame while closing (16 ms at 125 Hz, 20 ms at
# 100 Hz: edge.daemon.press.GRIPPER_TRACE_FRAMES); 50 ms rides out one late or lost read.
# At a constant velocity the estimate is then off by less than one count: 0.5 for Present
# Position's resolution, 0.4 for Present Velocity's (0.5 of its 15.6 raw/s unit over 50 ms),
# inside the default 2-count squeeze. What a state cannot show is a change of velocity
# after it was read: slowing down (contact, stall) only puts the goal further in the
# closing direction (more squeeze, capped by Goal Current); speeding up happens as a motion
# starts, hence STOP_STATE_SETTLE_S.
STOP_STATE_MAX_AGE_S = 0.05
# A state read sooner than this after the motor's last goal write may show it still
# accelerating (a real XM430 takes a few ms to reach its profile velocity): not used.
STOP_STATE_SETTLE_S = 0.01
# How long the event loop waits, when it hands a stop over, for the stop's packet to be on
# the wire (normally the hand-over plus any transaction already in flight: tens of
# microseconds to a millisecond). Past it the loop goes on and the stop still goes out.
STOP_HANDOVER_MAX_S = 0.003
# What a person stops to free the bus when the daemon holds it (edge.daemon.systemd.UNIT_NAME).
# Models the driver is written for; others get a warning (their tables may differ).
XM430_MODELS = {1020: "XM430-W350", 1030: "XM430-W210"}

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
# Status packet offsets (dynamixel_sdk.protocol2_packet_handler).
_PKT_ID, _PKT_LENGTH_L, _PKT_LENGTH_H = 4, 5, 6
# One sync read covers Present Current (126), Present Velocity (128), Present Position (132).
_STATE_START = PRESENT_CURRENT.address
_STATE_LENGTH = PRESENT_POSITION.end - _STATE_START


def latency_timer_path(port: str, timer_dir: Path = LATENCY_TIMER_DIR) -> Path:
    """Where the kernel shows the USB latency timer of serial ``port`` (by-id links
    followed)."""
    return timer_dir / Path(os.path.realpath(port)).name / "latency_timer"


def read_latency_timer(path: Path) -> int | None:
    """The latency timer in ms; None when there is none (not a USB serial adapter). Raises
    OSError or ValueError when it cannot be read."""
    try:
        return int(path.read_text().strip())
    except FileNotFoundError:
        return None


class BlockingPortHandler(sdk.PortHandler):
    """A ``PortHandler`` whose reads block in ``select()`` instead of spinning.

    The SDK's receive loop calls ``readPort`` until the packet is complete or
    ``isPacketTimeout()``; the stock handler returns at once (pyserial timeout 0), so the loop
    spins holding the GIL. Here ``readPort`` first waits, GIL released, until a byte is
    readable or the SDK's packet deadline passes, then returns what is there. The SDK's
    deadlines stay its own; ``latency_timer_ms`` replaces its hard-coded 16 ms in them once the
    driver has read the adapter's real latency timer.
    """

    def __init__(self, port_name: str) -> None:
        super().__init__(port_name)
        self.latency_timer_ms = SDK_LATENCY_TIMER_MS
        # Monotonic time of the last write call (the packet goes to the kernel from here:
        # the stop latency ends here), and when that call returned (later by the system
        # call, and by any wait of this thread for a CPU or the GIL after it).
        self.write_call_t = 0.0
        self.last_write_t = 0.0
        # Called on the bus thread after each write with (its time, the packet's first 8
        # bytes: header, ID, length, instruction): a benchmark's probe.
        self.on_write: Callable[[float, bytes], None] | None = None

    def writePort(self, packet) -> int:
        self.write_call_t = time.monotonic()
        written = super().writePort(packet)
        self.last_write_t = time.monotonic()
        if self.on_write is not None:
            self.on_write(self.last_write_t, bytes(packet[:8]))
        return written

    def setPacketTimeout(self, packet_length: int) -> None:
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = (self.tx_time_per_byte * packet_length
                               + self.latency_timer_ms * 2.0 + 2.0)

    def readPort(self, length: int) -> bytes:
        if length <= 0:
            return b""
        remaining_s = (self.packet_timeout - self.getTimeSinceStart()) / 1000.0
        if remaining_s > 0:
            select.select([self.ser.fileno()], [], [], remaining_s + _READ_DEADLINE_SLACK_S)
        return self.ser.read(length)


class CheckedPacketHandler(sdk.Protocol2PacketHandler):
    """The SDK's Protocol 2.0 packet handler, refusing status packets of the wrong size.

    The SDK takes the first status packet from the right ID as the answer. A motor that
    answers an instruction after the SDK gave up on it (a timeout) leaves that late packet
    on the wire while the next instruction waits for its own: a 10-byte sync-read status
    would be read as the 4-byte Present Position a stop is computed from. With
    ``expect_params`` set (by the bus thread, around each call), a status packet with a
    different number of parameters is skipped as stale and reading goes on until the
    packet deadline.
    """

    expect_params: int | None = None
    stale_skipped = 0

    def rxPacket(self, port, fast_option):
        while True:
            packet, result = super().rxPacket(port, fast_option)
            if result != sdk.COMM_SUCCESS or self.expect_params is None:
                return packet, result
            # Status LENGTH = instruction + error + parameters + CRC (2).
            params = sdk.DXL_MAKEWORD(packet[_PKT_LENGTH_L], packet[_PKT_LENGTH_H]) - 4
            if params == self.expect_params:
                return packet, result
            self.stale_skipped += 1
            _log.warning("skipped a late status packet from motor %d (%d parameters, "
                         "expected %d): the answer to an instruction that timed out",
                         packet[_PKT_ID], params, self.expect_params)


@dataclass(frozen=True)
class MotorInfo:
    """What ``connect()`` found (and set) on one motor."""

    motor_id: int
    model_number: int
    firmware: int
    drive_mode: int
    operating_mode: int
    current_limit: int

    @property
    def reverse(self) -> bool:
        """Drive Mode bit 0: positions count the other way round."""
        return bool(self.drive_mode & DRIVE_MODE_REVERSE)

    @property
    def time_based_profile(self) -> bool:
        """Drive Mode bit 2: Profile Velocity/Acceleration are times in ms."""
        return bool(self.drive_mode & DRIVE_MODE_TIME_BASED_PROFILE)


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


@dataclass(frozen=True)
class StopRecord:
    """What one stop did, and when (the bus clock).

    ``t_submit``: the stop handed to the bus (event loop); ``t_start``: the bus thread began
    it; ``t_write_call``: its Goal Position packet's write call (the packet goes to the
    kernel from here: the stop's time); ``t_written``: that call returned. ``in_flight_s``:
    how long a transaction already on the wire at the hand-over still took. ``fast``: one
    WRITE from a state ``state_age_s`` old; else ``fallback`` says why it read first.
    """

    goal: int
    fast: bool
    state_age_s: float | None
    fallback: str | None
    t_submit: float
    t_start: float
    t_write_call: float
    t_written: float
    in_flight_s: float


class _Op:
    """One operation for the bus thread, and the future its caller awaits."""

    __slots__ = ("abandoned", "fn", "future", "label", "loop", "must_run", "on_wire")

    def __init__(self, label: str, fn: Callable[[], Any], loop: asyncio.AbstractEventLoop,
                 future: asyncio.Future[Any], must_run: bool) -> None:
        self.label, self.fn, self.loop, self.future = label, fn, loop, future
        self.must_run = must_run
        self.abandoned = False
        # Set once the operation's first packet is written (or it ended): what a caller
        # handing over a stop waits for.
        self.on_wire = threading.Event()

    def on_done(self, future: asyncio.Future[Any]) -> None:
        # Runs on the loop: a caller that gave up on a queued read needs no bus time. A stop
        # is sent even then.
        if future.cancelled() and not self.must_run:
            self.abandoned = True

    def settle(self, value: Any, exc: BaseException | None) -> None:
        try:
            self.loop.call_soon_threadsafe(_settle, self.future, value, exc)
        except RuntimeError:
            pass  # the loop is closed: nobody is waiting any more


def _settle(future: asyncio.Future[Any], value: Any, exc: BaseException | None) -> None:
    if future.done():
        return
    if exc is not None:
        future.set_exception(exc)
    else:
        future.set_result(value)


class DynamixelBus:
    """The Dynamixel bus of the arm: joints ``config.joint_ids``, gripper ``config.gripper_id``.

    Use ``async with DynamixelBus(config) as bus`` (connect, then close), or call
    :meth:`connect` and :meth:`close`. ``port_handler_factory`` builds the SDK port handler
    (default :class:`BlockingPortHandler`; ``dynamixel_sdk.PortHandler`` is the stock one).
    """

    def __init__(
        self,
        config: BusConfig,
        *,
        port_handler_factory: Callable[[str], sdk.PortHandler] = BlockingPortHandler,
        latency_timer_dir: Path = LATENCY_TIMER_DIR,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._config = config
        # The clock of every time the bus reports (states, the stop); the event loop's.
        self._clock = clock
        # Called on the bus thread after each packet written to the port with (monotonic
        # time, first 8 bytes of the packet); for measurements (see BlockingPortHandler).
        self.on_write: Callable[[float, bytes], None] | None = None
        self._ids = (*config.joint_ids, config.gripper_id)
        self._port_handler_factory = port_handler_factory
        self._latency_timer_dir = latency_timer_dir
        self._ph = CheckedPacketHandler()
        self._port: sdk.PortHandler | None = None
        # The exclusive flock on the port device held while connected (see _connect_owned).
        self._lock_fd = -1
        self._lock = threading.Lock()
        self._urgent: collections.deque[_Op] = collections.deque()
        self._normal: collections.deque[_Op] = collections.deque()
        self._accepting = False
        self._thread_exit = False
        self._thread: threading.Thread | None = None
        # Written by every submission; the bus thread sleeps in select() on it.
        self._wake_fd = -1
        # The operation on the bus thread now, and when the last one ended (monotonic).
        self._running: _Op | None = None
        self._last_op_end = 0.0
        self._motors: dict[int, MotorInfo] = {}
        self._torque_on = False
        # Opened with connect(configure=False): nothing is ever written to a motor.
        self._read_only = False
        self._feed_task: asyncio.Task[None] | None = None
        self._last_traffic = 0.0
        self.last_state: BusState | None = None
        # When the last stop's Goal Position packet went to the port (its write call,
        # monotonic), and what the stop did.
        self.last_stop_t = 0.0
        self.last_stop: StopRecord | None = None
        self.stops = 0
        # Stops that had to read Present Position first (no state fresh enough to trust).
        self.stop_fallbacks = 0
        # Per motor: the state last read, and when its last Goal Position write completed.
        self._seen: dict[int, SeenState] = {}
        self._goal_t: dict[int, float] = {}
        # Why the bus is not fit to press, for /healthz: the last failed watchdog feed
        # (cleared by the next good one).
        self._feed_fault: str | None = None
        # A motor found with torque off before a press (it shut itself down): until restart.
        self._torque_fault: str | None = None

    # ---------------------------------------------------------------- properties

    @property
    def ids(self) -> tuple[int, ...]:
        return self._ids

    @property
    def config(self) -> BusConfig:
        return self._config

    @property
    def motors(self) -> Mapping[int, MotorInfo]:
        """What :meth:`connect` found, by motor ID."""
        return self._motors

    @property
    def torque_on(self) -> bool:
        return self._torque_on

    @property
    def fault(self) -> str | None:
        """What is wrong with the bus now (a motor that does not answer...), or None."""
        return self._torque_fault or self._feed_fault

    @property
    def thread_id(self) -> int | None:
        """``threading.get_ident()`` of the bus thread (the only one calling the SDK)."""
        return self._thread.ident if self._thread is not None else None

    @property
    def native_thread_id(self) -> int | None:
        """The kernel's thread ID of the bus thread (for its scheduling policy and CPU)."""
        return self._thread.native_id if self._thread is not None else None

    def seen(self, motor_id: int) -> SeenState | None:
        """The motor's position and velocity as last read (by any sync read), or None."""
        return self._seen.get(motor_id)

    # ---------------------------------------------------------------- lifecycle

    async def __aenter__(self) -> DynamixelBus:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def connect(self, *, configure: bool = True) -> Mapping[int, MotorInfo]:
        """Open the port, find every motor and configure it; torque stays off.

        Pings every ID (a missing one raises :class:`MotorError` naming it), reads model and
        firmware, reads Drive Mode and keeps its direction bit as found (joints get the
        time-based profile bit, the gripper the velocity-based one), sets Operating Mode (3
        for joints, 5 for the gripper) and Return Delay Time 0 with torque off, sets the
        gripper's Goal Current, and checks the USB latency timer.

        ``configure=False`` (``vt-edge doctor``) only opens the port and checks the latency
        timer: the bus is then read-only (:meth:`ping`, :meth:`read`); every write is refused
        and :meth:`close` leaves the motors as they were.
        """
        if self._thread is not None:
            raise DeviceError(f"Dynamixel bus on {self._config.port} is already connected")
        self._read_only = not configure
        self._thread_exit = False
        self._accepting = True
        self._wake_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self._thread = threading.Thread(target=self._run, name="dxl-bus", daemon=True)
        self._thread.start()
        try:
            self._motors = await self._call("connect", self._connect_owned)
        except BaseException:
            await self._shutdown_thread()
            raise
        return self._motors

    async def close(self, safe_pose: Callable[[], Awaitable[object]] | None = None) -> None:
        """Leave the arm safe and release the port.

        With torque on, ``safe_pose`` (e.g. ``lambda: arm.move_to("rest")``) runs first; a
        failing safe pose is logged and torque goes off where the arm is. The watchdog is
        disarmed and torque turned off on every motor in any case, since a torque-on that
        failed half way leaves some motors on.
        """
        if self._thread is None:
            return
        if self._read_only:
            await self._shutdown_thread()
            return
        try:
            if self._torque_on and safe_pose is not None:
                try:
                    await safe_pose()
                except Exception:
                    _log.exception("safe pose before torque off failed; "
                                   "turning torque off where the arm stands")
            await self.set_torque(False)
        except DeviceError:
            _log.exception("turning torque off at shutdown failed")
        finally:
            await self._shutdown_thread()

    # ---------------------------------------------------------------- operations

    async def ping(self, motor_id: int) -> int:
        """Ping one motor; its model number, or :class:`MotorError` naming it."""
        return await self._call(f"ping {motor_id}", lambda: self._ping_sync(motor_id))

    async def scan(self) -> dict[int, int]:
        """Every motor that answers a broadcast ping: ID -> model number. Slow (the SDK
        waits out the replies of all 253 IDs: about 0.8 s at 1 Mbps)."""
        return await self._call("broadcast ping", self._scan_sync)

    async def read(self, motor_id: int, name: str) -> int:
        """One register of one motor (sign applied)."""
        reg = _T[name]
        return await self._call(f"read {name}", lambda: self._read(motor_id, reg))

    async def write(self, motor_id: int, name: str, value: int) -> None:
        """One register of one motor, waiting for its status packet."""
        reg = _T[name]
        await self._call(f"write {name}", lambda: self._write(motor_id, reg, value))

    async def read_state(self) -> BusState:
        """Present position, velocity and current of every motor in one sync read."""
        return await self._call("sync read state", self._read_state_sync)

    async def sync_write(self, name: str, values: Mapping[int, int]) -> None:
        """One register on several motors in one SYNC WRITE packet (no status packets)."""
        reg = _T[name]
        items = dict(values)
        await self._call(f"sync write {name}", lambda: self._sync_write(reg, items))

    async def write_goal_positions(self, goals: Mapping[int, int]) -> None:
        """Goal Position of several motors in one SYNC WRITE packet."""
        await self.sync_write(GOAL_POSITION.name, goals)

    async def stop(self, motor_id: int, goal_position: int) -> None:
        """Write Goal Position ahead of everything queued (one WRITE, status awaited)."""
        await self._call("stop", lambda: self._write(motor_id, GOAL_POSITION, goal_position),
                         urgent=True)

    async def stop_past_present(self, motor_id: int, offset_raw: int) -> int:
        """Ahead of everything queued: read Present Position, write Goal Position =
        present + ``offset_raw``; returns the goal written (the fallback of
        :meth:`stop_ahead`)."""
        record = await self._submit_stop(motor_id, offset_raw, None)
        return record.goal

    async def stop_ahead(self, motor_id: int, offset_raw: int,
                         max_age_s: float = STOP_STATE_MAX_AGE_S) -> StopRecord:
        """Ahead of everything queued, one WRITE of Goal Position = the motor's position
        extrapolated to the moment of the write + ``offset_raw`` (the squeeze, signed in the
        closing direction).

        The position is the last one read (:meth:`seen`) moved on by its velocity. A state
        older than ``max_age_s``, read before the motor's last goal write or within
        ``STOP_STATE_SETTLE_S`` of it, or missing, is not trusted: then Present Position is
        read first (:meth:`stop_past_present`), as many times as :attr:`stop_fallbacks`
        says. Either way the goal lies past where the motor is, so a stop never backs off
        the squeeze.
        """
        return await self._submit_stop(motor_id, offset_raw, max_age_s)

    async def _submit_stop(self, motor_id: int, offset_raw: int,
                           max_age_s: float | None) -> StopRecord:
        t_submit = self._clock()
        busy = self._running  # a transaction on the wire at the hand-over

        def op() -> StopRecord:
            t_start = self._clock()
            in_flight = max(0.0, self._last_op_end - t_submit) if busy is not None else 0.0
            goal, age, why = self._stop_goal(motor_id, offset_raw, max_age_s)
            self._write(motor_id, GOAL_POSITION, goal)
            t_written = getattr(self._port, "last_write_t", 0.0) or self._clock()
            t_call = getattr(self._port, "write_call_t", 0.0) or t_written
            self.last_stop_t = t_call
            self.stops += 1
            if why is not None and max_age_s is not None:
                self.stop_fallbacks += 1
            record = StopRecord(goal, why is None, age, why, t_submit, t_start, t_call,
                                t_written, in_flight)
            self.last_stop = record
            return record

        return await self._call("stop", op, urgent=True)

    def _stop_goal(self, motor_id: int, offset_raw: int,
                   max_age_s: float | None) -> tuple[int, float | None, str | None]:
        """(goal, age of the state used, why the state was not used) on the bus thread."""
        now = self._clock()
        seen = self._seen.get(motor_id)
        goal_t = self._goal_t.get(motor_id, -math.inf)
        if max_age_s is None:
            why = "asked to read"
        elif seen is None:
            why = "no state read yet"
        elif now - seen.t > max_age_s:
            why = f"state {1e3 * (now - seen.t):.0f} ms old"
        elif seen.t < goal_t + STOP_STATE_SETTLE_S:
            why = "state read before the motor's last goal had settled"
        else:
            estimate = seen.position + seen.velocity_raw_s * (now - seen.t)
            return round(estimate) + offset_raw, now - seen.t, None
        return self._read(motor_id, PRESENT_POSITION) + offset_raw, None, why

    async def set_torque(self, enabled: bool) -> None:
        """Torque on (goals set to present positions first, then the Bus Watchdog armed and
        fed) or off (watchdog disarmed first)."""
        if enabled:
            await self._call("torque on", self._torque_on_sync)
            self._torque_on = True
            if self._feed_task is None:
                self._feed_task = asyncio.create_task(self._feed_watchdog(),
                                                      name="dxl-watchdog-feed")
        else:
            await self._stop_feed()
            self._torque_on = False
            await self._call("torque off", self._torque_off_sync)

    async def recover_watchdog(self) -> list[int]:
        """Before a press: check every motor still has torque on (a motor that shut itself
        down raises :class:`MotorError` naming it, and :attr:`fault` keeps saying so), then
        clear Bus Watchdog trips: write 0, hold the present position, re-arm.

        Returns the IDs that had tripped.
        """
        return await self._call("recover watchdog", self._recover_watchdog_sync)

    # ---------------------------------------------------------------- the asyncio side

    async def _call(self, label: str, fn: Callable[[], Any], *, urgent: bool = False) -> Any:
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Any] = loop.create_future()
        op = _Op(label, fn, loop, future, must_run=urgent)
        future.add_done_callback(op.on_done)
        with self._lock:
            if not self._accepting:
                raise DeviceError(f"Dynamixel bus on {self._config.port} is not connected")
            (self._urgent if urgent else self._normal).append(op)
        os.eventfd_write(self._wake_fd, 1)
        if urgent:
            # Sleeping here hands the bus thread the GIL (and, on a busy host, this core)
            # at once; going on would leave it waiting until the loop next blocks, up to
            # the interpreter's 5 ms switch interval under load. Bounded: a stop behind a
            # transaction that hangs does not hold up the loop.
            op.on_wire.wait(STOP_HANDOVER_MAX_S)
        return await future

    async def _feed_watchdog(self) -> None:
        # Feeding from the loop, not the bus thread: a stalled event loop stops the feed, so
        # the watchdog catches a dead host as well as a dead process. Any traffic counts.
        interval_s = self._config.watchdog_ms / 1000.0 / 4
        failing = False
        while True:
            await asyncio.sleep(interval_s)
            if self._clock() - self._last_traffic < interval_s:
                continue
            try:
                await self.read_state()
            except DeviceError as exc:
                if not failing:
                    _log.warning("Bus Watchdog feed failed: %s", exc)
                failing = True
                self._feed_fault = str(exc)
            else:
                if failing:
                    _log.info("Bus Watchdog feed works again")
                failing = False
                self._feed_fault = None

    async def _stop_feed(self) -> None:
        task, self._feed_task = self._feed_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _shutdown_thread(self) -> None:
        await self._stop_feed()
        thread = self._thread
        if thread is None:
            return
        with self._lock:
            self._accepting = False
            self._thread_exit = True
        os.eventfd_write(self._wake_fd, 1)
        await asyncio.to_thread(thread.join, THREAD_JOIN_TIMEOUT_S)
        if thread.is_alive():
            _log.error("Dynamixel bus thread did not stop within %.1f s", THREAD_JOIN_TIMEOUT_S)
        else:
            os.close(self._wake_fd)
            self._wake_fd = -1
        self._thread = None
        self._torque_on = False

    # ---------------------------------------------------------------- the bus thread

    def _next_op(self) -> _Op | None:
        """The next operation (stops first), sleeping in select() until there is one; None
        when the thread is to end."""
        while True:
            with self._lock:
                if self._urgent:
                    return self._urgent.popleft()
                if self._normal:
                    return self._normal.popleft()
                if self._thread_exit:
                    return None
            # A submission after the check above has written the eventfd: select returns.
            select.select([self._wake_fd], [], [])
            with contextlib.suppress(BlockingIOError):
                os.eventfd_read(self._wake_fd)

    def _run(self) -> None:
        try:
            while (op := self._next_op()) is not None:
                if op.abandoned:
                    op.on_wire.set()
                    continue
                value, exc = None, None
                self._running = op
                try:
                    value = op.fn()
                except EdgeError as e:
                    exc = e
                except OSError as e:  # pyserial's SerialException among them
                    exc = DeviceError(f"Dynamixel bus on {self._config.port}: {op.label}: {e}")
                    exc.__cause__ = e
                except Exception as e:
                    _log.exception("unexpected error in bus operation %s", op.label)
                    exc = e
                finally:
                    self._running = None
                    op.on_wire.set()
                self._last_op_end = self._last_traffic = self._clock()
                op.settle(value, exc)
        finally:
            self._close_port()

    def _close_port(self) -> None:
        port, self._port = self._port, None
        if port is not None and port.is_open:
            with contextlib.suppress(OSError):
                port.closePort()
        lock_fd, self._lock_fd = self._lock_fd, -1
        if lock_fd >= 0:
            os.close(lock_fd)

    def _check(self, motor_id: int, what: str, result: int, error: int) -> None:
        if result != sdk.COMM_SUCCESS:
            raise MotorError(f"motor {motor_id}: {what}: {self._ph.getTxRxResult(result)}",
                             motor_id, transient=result in _TRANSIENT)
        if error:
            message = self._ph.getRxPacketError(error)
            if error & sdk.ERRBIT_ALERT:
                other = error & ~sdk.ERRBIT_ALERT
                if other:
                    message += " " + self._ph.getRxPacketError(other)
                message += f" Hardware Error Status: {self._hardware_error_detail(motor_id)}"
            elif error & ~sdk.ERRBIT_ALERT == ERR_DATA_RANGE and self._watchdog_tripped(motor_id):
                # A tripped Bus Watchdog refuses every goal with a range error: say why.
                message += (" (its Bus Watchdog has tripped: the host was silent on the bus"
                            " longer than the watchdog allows)")
            raise MotorError(f"motor {motor_id}: {what}: {message}", motor_id)

    @contextlib.contextmanager
    def _expect(self, params: int) -> Iterator[None]:
        """Status packets carry ``params`` parameters until the block ends (bus thread)."""
        self._ph.expect_params = params
        try:
            yield
        finally:
            self._ph.expect_params = None

    def _drain_late_replies(self) -> None:
        # Replies that come after the SDK gave up must not be read as the retry's answer (a
        # same-size status would pass for it): let them arrive, then drop them.
        time.sleep(LATE_REPLY_DRAIN_S)
        self._port.clearPort()

    def _hardware_error_detail(self, motor_id: int) -> str:
        with self._expect(HARDWARE_ERROR_STATUS.size):
            status, result, _ = self._ph.read1ByteTxRx(self._port, motor_id,
                                                       HARDWARE_ERROR_STATUS.address)
        if result != sdk.COMM_SUCCESS:
            return "unreadable"
        return f"0x{status:02x} ({describe_hardware_error(status)})"

    def _watchdog_tripped(self, motor_id: int) -> bool:
        with self._expect(BUS_WATCHDOG.size):
            value, result, _ = self._ph.read1ByteTxRx(self._port, motor_id, BUS_WATCHDOG.address)
        return result == sdk.COMM_SUCCESS and BUS_WATCHDOG.from_unsigned(value) == -1

    def _read(self, motor_id: int, reg: Register) -> int:
        read = {1: self._ph.read1ByteTxRx, 2: self._ph.read2ByteTxRx,
                4: self._ph.read4ByteTxRx}[reg.size]
        with self._expect(reg.size):
            for _ in range(READ_ATTEMPTS - 1):
                # A lost or garbled reply is retried once: reads have no side effect.
                raw, result, error = read(self._port, motor_id, reg.address)
                if result not in _TRANSIENT:
                    break
                self._drain_late_replies()
            else:
                raw, result, error = read(self._port, motor_id, reg.address)
        self._check(motor_id, f"read {reg.name}", result, error)
        return reg.from_unsigned(raw)

    def _write(self, motor_id: int, reg: Register, value: int) -> None:
        self._refuse_if_read_only(f"motor {motor_id}: write {reg.name}")
        write = {1: self._ph.write1ByteTxRx, 2: self._ph.write2ByteTxRx,
                 4: self._ph.write4ByteTxRx}[reg.size]
        with self._expect(0):
            for _ in range(READ_ATTEMPTS - 1):
                # A lost or garbled status packet is written again once: every register
                # written here takes an absolute value, so a second delivery changes nothing.
                result, error = write(self._port, motor_id, reg.address, reg.to_unsigned(value))
                if result not in _TRANSIENT:
                    break
                self._drain_late_replies()
            else:
                result, error = write(self._port, motor_id, reg.address,
                                      reg.to_unsigned(value))
        if reg is GOAL_POSITION:
            # A new goal changes the motion: states read before it say nothing about it now.
            self._goal_t[motor_id] = self._clock()
        self._check(motor_id, f"write {reg.name} = {value}", result, error)

    def _sync_write(self, reg: Register, values: Mapping[int, int]) -> None:
        self._refuse_if_read_only(f"sync write {reg.name}")
        param: list[int] = []
        for motor_id, value in values.items():
            param += [motor_id, *reg.encode(value)]
        result = self._ph.syncWriteTxOnly(self._port, reg.address, reg.size, param, len(param))
        if reg is GOAL_POSITION:
            now = self._clock()
            self._goal_t.update(dict.fromkeys(values, now))
        if result != sdk.COMM_SUCCESS:
            first = next(iter(values), None)
            raise MotorError(f"motors {sorted(values)}: sync write {reg.name}: "
                             f"{self._ph.getTxRxResult(result)}", first)

    def _read_state_sync(self) -> BusState:
        # A lost or garbled reply is retried once: a sync read has no side effect.
        for _ in range(READ_ATTEMPTS - 1):
            try:
                return self._read_state_once()
            except MotorError as exc:
                if not exc.transient:
                    raise
                self._drain_late_replies()
        return self._read_state_once()

    def _read_state_once(self) -> BusState:
        # The SDK's SYNC READ transmit, then its per-motor receive, so that a failure names
        # its motor and the error byte (e.g. a hardware alert) is checked, which
        # GroupSyncRead.rxPacket drops.
        t_sent = self._clock()  # the motors sample after this: see SeenState
        result = self._ph.syncReadTx(self._port, _STATE_START, _STATE_LENGTH, list(self._ids),
                                     len(self._ids), False)
        if result != sdk.COMM_SUCCESS:
            raise MotorError(f"motors {list(self._ids)}: sync read of present state: "
                             f"{self._ph.getTxRxResult(result)}", self._ids[0])
        motors = {}
        for motor_id in self._ids:
            with self._expect(_STATE_LENGTH):
                data, result, error = self._ph.readRx(self._port, motor_id, _STATE_LENGTH)
            self._check(motor_id, "sync read of present state", result, error)
            motors[motor_id] = MotorState(
                position=_field(PRESENT_POSITION, data),
                velocity=_field(PRESENT_VELOCITY, data),
                current=_field(PRESENT_CURRENT, data),
            )
        state = BusState(self._clock(), motors)
        self.last_state = state
        for motor_id, m in motors.items():
            self._seen[motor_id] = SeenState(t_sent, m.position,
                                             m.velocity * RAW_PER_S_PER_VELOCITY_UNIT)
        return state

    def _written(self, t: float, head: bytes) -> None:
        op = self._running
        if op is not None:
            op.on_wire.set()
        if self.on_write is not None:
            self.on_write(t, head)

    def _connect_owned(self) -> dict[int, MotorInfo]:
        # One bus, one owner: two processes talking on one half-duplex bus garble each
        # other's replies and turn each other's motors off. The lock is an flock on the port
        # device itself (what pyserial's exclusive=True takes), on a descriptor of its own so
        # it is taken before the port is opened: opening a tty flushes its input, which would
        # eat the replies of the process that owns it. The kernel drops it when this process
        # dies.
        port = self._config.port
        try:
            fd = os.open(port, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
        except OSError as exc:
            raise DeviceError(f"cannot open Dynamixel port {port}: {exc}") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = _lock_holder(fd)
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise DeviceError(f"cannot lock Dynamixel port {port}: {exc}") from exc
            raise BusInUseError(
                f"Dynamixel port {port} is in use by {holder or 'another process'}: one bus, "
                f"one owner; stop it first (the daemon: systemctl stop {SERVICE_NAME}), then "
                "run this again") from None
        self._lock_fd = fd
        return self._connect_sync()

    def _connect_sync(self) -> dict[int, MotorInfo]:
        cfg = self._config
        port = self._port_handler_factory(cfg.port)
        try:
            # setBaudRate opens the port (the SDK's openPort is setBaudRate of its default).
            opened = port.setBaudRate(cfg.baudrate)
        except OSError as exc:
            raise DeviceError(f"cannot open Dynamixel port {cfg.port}: {exc}") from exc
        if not opened:
            raise DeviceError(f"Dynamixel port {cfg.port}: baud rate {cfg.baudrate} is not one "
                              "the SDK supports")
        self._port = port
        if isinstance(port, BlockingPortHandler):
            port.on_write = self._written
        self._check_latency_timer(port)
        if self._read_only:
            return {}

        models: dict[int, int] = {}
        missing: list[tuple[int, str]] = []
        for motor_id in self._ids:
            model, why = self._ping_once(motor_id)
            if model is None:
                missing.append((motor_id, why))
            else:
                models[motor_id] = model
        if missing:
            raise self._no_answer([i for i, _ in missing], missing[0][1])

        infos = {}
        for motor_id in self._ids:
            infos[motor_id] = self._configure_motor(motor_id, models[motor_id])

        gripper = infos[cfg.gripper_id]
        if cfg.gripper_goal_current > gripper.current_limit:
            raise MotorError(
                f"motor {cfg.gripper_id}: gripper_goal_current {cfg.gripper_goal_current} "
                f"exceeds the motor's Current Limit {gripper.current_limit}", cfg.gripper_id)
        self._write(cfg.gripper_id, GOAL_CURRENT, cfg.gripper_goal_current)
        _log.info("Dynamixel bus on %s at %d bps: motors %s ready (torque off)",
                  cfg.port, cfg.baudrate, ", ".join(map(str, self._ids)))
        return infos

    def _configure_motor(self, motor_id: int, model: int) -> MotorInfo:
        is_gripper = motor_id == self._config.gripper_id
        if model not in XM430_MODELS:
            _log.warning("motor %d: model number %d is not an XM430 (%s); its control table "
                         "may differ", motor_id, model, ", ".join(map(str, XM430_MODELS)))
        firmware = self._read(motor_id, FIRMWARE_VERSION)
        self._ensure_status_return_level(motor_id)
        # A watchdog trip left by an earlier run refuses goal writes until cleared; then torque
        # off, since the EEPROM registers below are writable only with torque off.
        self._write(motor_id, BUS_WATCHDOG, 0)
        self._write(motor_id, TORQUE_ENABLE, 0)

        drive = self._read(motor_id, DRIVE_MODE)
        # The direction bit is the arm's business: keep it as found, never assume it. Joints
        # move on time-based profiles, the gripper on a velocity (its closing speed).
        want = drive & ~DRIVE_MODE_TIME_BASED_PROFILE
        if not is_gripper:
            want |= DRIVE_MODE_TIME_BASED_PROFILE
        if want != drive:
            self._write(motor_id, DRIVE_MODE, want)
        mode = self._read(motor_id, OPERATING_MODE)
        want_mode = MODE_CURRENT_BASED_POSITION if is_gripper else MODE_POSITION
        if mode != want_mode:
            self._write(motor_id, OPERATING_MODE, want_mode)
        if self._read(motor_id, RETURN_DELAY_TIME) != 0:
            self._write(motor_id, RETURN_DELAY_TIME, 0)
        current_limit = self._read(motor_id, CURRENT_LIMIT)
        _log.info("motor %d: %s firmware %d, drive mode %d (%s direction, %s profile), "
                  "operating mode %d -> %d", motor_id, XM430_MODELS.get(model, model), firmware,
                  want, "reverse" if want & DRIVE_MODE_REVERSE else "normal",
                  "time-based" if want & DRIVE_MODE_TIME_BASED_PROFILE else "velocity-based",
                  mode, want_mode)
        return MotorInfo(motor_id, model, firmware, want, want_mode, current_limit)

    def _ensure_status_return_level(self, motor_id: int) -> None:
        # Below 2 a motor answers writes with silence, which would read as timeouts.
        level = self._read(motor_id, STATUS_RETURN_LEVEL)
        if level == 2:
            return
        _log.warning("motor %d: Status Return Level %d; setting 2", motor_id, level)
        result = self._ph.write1ByteTxOnly(self._port, motor_id, STATUS_RETURN_LEVEL.address, 2)
        self._check(motor_id, "write Status Return Level = 2", result, 0)
        if self._read(motor_id, STATUS_RETURN_LEVEL) != 2:
            raise MotorError(f"motor {motor_id}: Status Return Level does not stay at 2",
                             motor_id)

    def _check_latency_timer(self, port: sdk.PortHandler) -> None:
        path = latency_timer_path(self._config.port, self._latency_timer_dir)
        try:
            value = read_latency_timer(path)
        except (OSError, ValueError) as exc:
            _log.warning("cannot read the USB latency timer %s: %s", path, exc)
            return
        if value is None:
            _log.debug("no USB latency timer at %s (not a USB serial adapter)", path)
            return
        if isinstance(port, BlockingPortHandler):
            port.latency_timer_ms = float(value)
        if value != 1:
            _log.warning(
                "%s: USB latency timer is %d ms, which adds up to %d ms to every reply; set it "
                "to 1 now with `echo 1 | sudo tee %s`, and for good with the udev rule %s "
                "(`vt-edge install-udev --install` installs it)", self._config.port, value,
                value, path, LATENCY_TIMER_UDEV_RULE)

    def _refuse_if_read_only(self, what: str) -> None:
        if self._read_only:
            raise DeviceError(f"Dynamixel bus on {self._config.port} is open read-only: "
                              f"{what} refused")

    def _ping_once(self, motor_id: int) -> tuple[int | None, str]:
        """(model number, "") or (None, why there was no answer)."""
        for _ in range(READ_ATTEMPTS):  # one lost reply is not a missing motor
            model, result, error = self._ph.ping(self._port, motor_id)
            if result == sdk.COMM_SUCCESS:
                self._check(motor_id, "ping", result, error)
                return model, ""
            self._port.clearPort()
        return None, self._ph.getTxRxResult(result)

    def _no_answer(self, ids: list[int], why: str) -> MotorError:
        cfg = self._config
        return MotorError(
            f"motor {', '.join(map(str, ids))} did not answer a ping on {cfg.port} at "
            f"{cfg.baudrate} bps: {why} (check power, cabling, ID and baud rate)", ids[0])

    def _ping_sync(self, motor_id: int) -> int:
        model, why = self._ping_once(motor_id)
        if model is None:
            raise self._no_answer([motor_id], why)
        return model

    def _scan_sync(self) -> dict[int, int]:
        found, _ = self._ph.broadcastPing(self._port)
        self._port.clearPort()
        return {motor_id: model for motor_id, (model, _firmware) in sorted(found.items())}

    def _torque_on_sync(self) -> None:
        state = self._read_state_sync()
        # Torque on holds wherever the goal says: make that where each motor stands.
        self._sync_write(GOAL_POSITION, {i: s.position for i, s in state.motors.items()})
        for motor_id in self._ids:
            self._write(motor_id, TORQUE_ENABLE, 1)
        units = round(self._config.watchdog_ms / 1000.0 / BUS_WATCHDOG_UNIT_S)
        for motor_id in self._ids:
            self._write(motor_id, BUS_WATCHDOG, units)

    def _torque_off_sync(self) -> None:
        # Try every motor even if one fails: as many as possible end up limp.
        first: MotorError | None = None
        for motor_id in self._ids:
            try:
                self._write(motor_id, BUS_WATCHDOG, 0)
                self._write(motor_id, TORQUE_ENABLE, 0)
            except MotorError as exc:
                _log.error("torque off: %s", exc)
                first = first or exc
        if first is not None:
            raise first

    def _sync_read_register(self, reg: Register) -> dict[int, int]:
        """One register of every motor in one SYNC READ (one round trip, not one each)."""
        result = self._ph.syncReadTx(self._port, reg.address, reg.size, list(self._ids),
                                     len(self._ids), False)
        if result != sdk.COMM_SUCCESS:
            raise MotorError(f"motors {list(self._ids)}: sync read of {reg.name}: "
                             f"{self._ph.getTxRxResult(result)}", self._ids[0])
        values = {}
        for motor_id in self._ids:
            with self._expect(reg.size):
                data, result, error = self._ph.readRx(self._port, motor_id, reg.size)
            self._check(motor_id, f"sync read of {reg.name}", result, error)
            values[motor_id] = reg.decode(bytes(data))
        return values

    def _recover_watchdog_sync(self) -> list[int]:
        if self._torque_on:
            self._check_torque_sync()
        # Before every press: one sync read (the common case: nothing tripped).
        watchdogs = self._sync_read_register(BUS_WATCHDOG)
        tripped = [i for i in self._ids if watchdogs[i] == -1]
        units = round(self._config.watchdog_ms / 1000.0 / BUS_WATCHDOG_UNIT_S)
        for motor_id in tripped:
            self._write(motor_id, BUS_WATCHDOG, 0)
            self._write(motor_id, GOAL_POSITION, self._read(motor_id, PRESENT_POSITION))
            if self._torque_on:
                self._write(motor_id, BUS_WATCHDOG, units)
        if tripped:
            _log.warning("Bus Watchdog had tripped on motors %s; cleared, holding position",
                         tripped)
        return tripped


    def _check_torque_sync(self) -> None:
        # A motor that shut itself down (overload, overheating...) has torque off: any goal
        # is ignored, so a press would close nothing and open nothing. Refuse it by name.
        # While the alert is on, the read itself raises with the Hardware Error Status.
        # One SYNC READ for all motors: this runs before every press.
        torque = self._sync_read_register(TORQUE_ENABLE)
        for motor_id in self._ids:
            if torque[motor_id]:
                continue
            status = self._read(motor_id, HARDWARE_ERROR_STATUS)
            if status:
                self._torque_fault = (
                    f"motor {motor_id}: torque is off (Hardware Error Status 0x{status:02x}: "
                    f"{describe_hardware_error(status)}): the motor shut itself down; remove "
                    "the cause, power-cycle or reboot it, then restart the daemon")
            else:
                # A motor that shuts itself down keeps its alert until it is rebooted; with
                # none, torque was turned off from the bus (a second program on it: the port
                # lock keeps out only programs that take it) or the motor lost power.
                self._torque_fault = (
                    f"motor {motor_id}: torque is off with no hardware error: not a shutdown "
                    "of the motor; another program on "
                    f"{self._config.port} turned it off (one bus, one owner: stop it), or the "
                    "motor was power-cycled or rebooted; then restart the daemon")
            raise MotorError(self._torque_fault, motor_id)


def _lock_holder(fd: int) -> str | None:
    """"pid N (its command line)" of the process holding an flock on ``fd``'s file, from
    /proc/locks; None where that cannot be told."""
    st = os.fstat(fd)
    inode = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    try:
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        fields = line.split()
        if len(fields) > 5 and fields[1] == "FLOCK" and fields[5] == inode:
            pid = fields[4]
            try:
                argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
                command = " ".join(a.decode(errors="replace") for a in argv if a)
            except OSError:
                return f"pid {pid}"
            return f"pid {pid} ({command[:120]})"
    return None


def _field(reg: Register, data: list[int]) -> int:
    start = reg.address - _STATE_START
    return reg.decode(bytes(data[start:start + reg.size]))
