"""The Dynamixel bus of the arm: the real ``dynamixel_sdk`` (Protocol 2.0) behind one owner.

Every operation runs on the bus's :class:`~edge.hw.dynamixel.executor.Executor` (by default
the ``dxl-bus`` thread; the simulator's on its virtual clock), one at a time, stops first; no
SDK call ever runs on the event loop. What runs there: the protocol transactions
(:mod:`.transactions`), the bring-up and watchdog (:mod:`.bringup`) and the stop
(:mod:`.stop`). Handing a stop over, the event loop waits (at most ``STOP_HANDOVER_MAX_S``)
until the stop's packet is on the wire: the loop's thread sleeps, so the bus thread gets the
GIL and, on a busy host, the loop's core at once.

A motor that stops answering costs every operation that asks it a reply timeout, so what must
work while one is silent (opening the gripper, feeding the Bus Watchdog, clearing a trip,
torque off) asks each motor on its own. An I/O error on the port (an adapter unplugged, a
cable glitch) closes it; it is reopened with a capped backoff while :attr:`fault` says so,
and operations meanwhile wait a little for it (``PORT_BACK_WAIT_S``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import termios
import time
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import Any

import dynamixel_sdk as sdk

from edge.core.backoff import Backoff
from edge.core.config import BusConfig
from edge.core.errors import DeviceError, EdgeError, MotorError
from edge.core.tasks import cancel_and_wait
from edge.hw.control_table import XM430_W350
from edge.hw.dynamixel import bringup
from edge.hw.dynamixel.bringup import MotorInfo
from edge.hw.dynamixel.executor import Executor, ThreadExecutor
from edge.hw.dynamixel.port import LATENCY_TIMER_DIR, BlockingPortHandler
from edge.hw.dynamixel.stop import STOP_STATE_MAX_AGE_S, StopPacket, StopRecord, stop_goal
from edge.hw.dynamixel.transactions import (
    BUS_WATCHDOG,
    GOAL_POSITION,
    BusState,
    SeenState,
    Transactions,
)

_log = logging.getLogger(__name__)

# A motor that did not answer is asked again (by the watchdog feed) this often, alone and
# after the others: each ask of a silent motor costs its reply timeout.
SILENT_PROBE_S = 0.5
# After an I/O error on the port, the first reopen comes this late (a USB adapter takes
# about this long to come back after a glitch), the later ones twice as late each, at most
# PORT_REOPEN_CAP_S apart.
PORT_REOPEN_BASE_S = 0.25
PORT_REOPEN_CAP_S = 2.0
# How long an operation waits for a port being reopened before it fails: a glitch of a few
# milliseconds costs a press no more than this.
PORT_BACK_WAIT_S = 1.0
# How often the shutdown's reopening of a failed port tries again (within PORT_BACK_WAIT_S).
SHUTDOWN_REOPEN_RETRY_S = 0.05
# What a failing line raises inside the SDK: pyserial's SerialException (an OSError), and
# termios.error (not one) from the input flush before each packet on a line that is gone.
_PORT_ERRORS = (OSError, termios.error)


class DynamixelBus:
    """The Dynamixel bus of the arm: joints ``config.joint_ids``, gripper ``config.gripper_id``.

    Use ``async with DynamixelBus(config) as bus`` (connect, then close), or call
    :meth:`connect` and :meth:`close`. ``executor`` runs every operation (default a new
    :class:`ThreadExecutor`). ``port_handler_factory`` builds the SDK port handler (default
    :class:`BlockingPortHandler`; ``dynamixel_sdk.PortHandler`` is the stock one);
    ``exclusive=False`` skips the port device's lock, for a port that is no device (the
    simulator's in-process one).
    """

    def __init__(
        self,
        config: BusConfig,
        *,
        executor: Executor | None = None,
        port_handler_factory: Callable[[str], sdk.PortHandler] = BlockingPortHandler,
        latency_timer_dir: Path = LATENCY_TIMER_DIR,
        clock: Callable[[], float] = time.monotonic,
        exclusive: bool = True,
    ) -> None:
        self._config = config
        self._executor: Executor = executor if executor is not None else ThreadExecutor()
        # The clock of every time the bus reports (states, the stop); the event loop's.
        self._clock = clock
        # Called on the bus thread after each packet written to the port with (monotonic
        # time, first 8 bytes of the packet); for measurements (see BlockingPortHandler).
        self.on_write: Callable[[float, bytes], None] | None = None
        self._ids = (*config.joint_ids, config.gripper_id)
        self._port_handler_factory = port_handler_factory
        self._latency_timer_dir = latency_timer_dir
        self._exclusive = exclusive
        self._tx = Transactions(config.port, self._ids, clock)
        # The stop's packet per motor, built but for the goal (the stop only adds it).
        self._stop_packets = {i: StopPacket(i) for i in self._ids}
        # The exclusive flock on the port device held while connected (bringup.lock_port).
        self._lock_fd = -1
        self._accepting = False
        # When the last operation ended (the bus clock): a stop's in-flight wait, the feed.
        self._last_op_end = 0.0
        self._motors: dict[int, MotorInfo] = {}
        self._torque_on = False
        self._feed_task: asyncio.Task[None] | None = None
        self._reopen_task: asyncio.Task[None] | None = None
        # Set while the port is open (cleared, on the loop, once an I/O error closed it).
        self._port_up = asyncio.Event()
        # When the last stop's Goal Position packet went to the port (its write call,
        # monotonic), and what the stop did.
        self.last_stop_t = 0.0
        self.last_stop: StopRecord | None = None
        self.stops = 0
        # Stops that had to read Present Position first (no state fresh enough to trust).
        self.stop_fallbacks = 0
        # Why the bus is not fit to press, for /healthz. Per motor, what its last failed
        # feed or check said (written on the bus thread only; cleared by its next answer),
        # and that as one line.
        self._motor_errors: dict[int, MotorError] = {}
        self._motors_fault: str | None = None
        # When the feed last asked each motor with an error (see SILENT_PROBE_S).
        self._probed: dict[int, float] = {}
        # The port's I/O error, from the error until the port is open again.
        self._port_fault: str | None = None
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
        """What is wrong with the bus now (a motor that does not answer, the port's I/O
        error while it is reopened...), or None."""
        return self._torque_fault or self._port_fault or self._motors_fault

    @property
    def last_state(self) -> BusState | None:
        """The last sync read of every motor's state."""
        return self._tx.last_state

    @property
    def thread_id(self) -> int | None:
        """``threading.get_ident()`` of the bus thread (the only one calling the SDK)."""
        return self._executor.thread_id

    @property
    def native_thread_id(self) -> int | None:
        """The kernel's thread ID of the bus thread (for its scheduling policy and CPU)."""
        return self._executor.native_thread_id

    def seen(self, motor_id: int) -> SeenState | None:
        """The motor's position and velocity as last read (by any sync read), or None."""
        return self._tx.seen.get(motor_id)

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
        if self._accepting:
            raise DeviceError(f"Dynamixel bus on {self._config.port} is already connected")
        self._tx.read_only = not configure
        self._executor.start()
        self._accepting = True
        self._port_up.set()
        try:
            self._motors = await self._call("connect", self._connect_sync)
        except BaseException:
            await self._shutdown()
            raise
        return self._motors

    async def close(self, safe_pose: Callable[[], Awaitable[object]] | None = None) -> None:
        """Leave the arm safe and release the port.

        With torque on, ``safe_pose`` (e.g. ``lambda: arm.move_to("rest")``) runs first; a
        failing safe pose is logged and torque goes off where the arm is. The watchdog is
        disarmed and torque turned off on every motor in any case, since a torque-on that
        failed half way leaves some motors on.
        """
        if not self._accepting:
            return
        if self._tx.read_only:
            await self._shutdown()
            return
        try:
            if self._torque_on and safe_pose is not None:
                try:
                    await safe_pose()
                except Exception:
                    _log.exception("safe pose before torque off failed; "
                                   "turning torque off where the arm stands")
            await self._torque_off_at_shutdown()
        except DeviceError:
            _log.exception("turning torque off at shutdown failed")
        finally:
            await self._shutdown()

    async def _torque_off_at_shutdown(self) -> None:
        """Torque off; where the port failed (before it or during it), on a port reopened
        now (the reopening loop's backoff is not waited for)."""
        for last in (False, True):
            if self._port_fault is not None:
                await self._stop_reopen()
                # Tried often, for a moment: a line that glitched is back under its path a
                # moment later (a USB adapter re-enumerating; on a loaded host, even the
                # emulator's), and a single try at that moment would leave torque on.
                await self._reopen_port(Backoff(SHUTDOWN_REOPEN_RETRY_S, SHUTDOWN_REOPEN_RETRY_S),
                                        PORT_BACK_WAIT_S)
            try:
                await self.set_torque(False)
                return
            except DeviceError:
                if last or self._port_fault is None:
                    raise

    # ---------------------------------------------------------------- operations

    async def ping(self, motor_id: int) -> int:
        """Ping one motor; its model number, or :class:`MotorError` naming it."""
        return await self._call(f"ping {motor_id}", lambda: self._ping_sync(motor_id))

    async def scan(self) -> dict[int, int]:
        """Every motor that answers a broadcast ping: ID -> model number. Slow (the SDK
        waits out the replies of all 253 IDs: about 0.8 s at 1 Mbps)."""
        return await self._call("broadcast ping", lambda: bringup.scan(self._tx))

    async def read(self, motor_id: int, name: str) -> int:
        """One register of one motor (sign applied)."""
        reg = XM430_W350[name]
        return await self._call(f"read {name}", lambda: self._tx.read(motor_id, reg))

    async def write(self, motor_id: int, name: str, value: int) -> None:
        """One register of one motor, waiting for its status packet."""
        reg = XM430_W350[name]
        await self._call(f"write {name}", lambda: self._tx.write(motor_id, reg, value))

    async def read_state(self) -> BusState:
        """Present position, velocity and current of every motor in one sync read."""
        return await self._call("sync read state", self._tx.read_state)

    async def read_motor_state(self, motor_id: int) -> BusState:
        """Present position, velocity and current of one motor in a READ of its own (another
        motor that does not answer, which fails :meth:`read_state`, does not fail this)."""
        def op() -> BusState:
            state = self._tx.read_motor_state(motor_id)
            return BusState(self._clock(), {motor_id: state})

        return await self._call(f"read state of motor {motor_id}", op)

    async def sync_write(self, name: str, values: Mapping[int, int]) -> None:
        """One register on several motors in one SYNC WRITE packet (no status packets)."""
        reg = XM430_W350[name]
        items = dict(values)
        await self._call(f"sync write {name}", lambda: self._tx.sync_write(reg, items))

    async def write_goal_positions(self, goals: Mapping[int, int]) -> None:
        """Goal Position of several motors in one SYNC WRITE packet."""
        await self.sync_write(GOAL_POSITION.name, goals)

    async def stop(self, motor_id: int, goal_position: int) -> None:
        """Write Goal Position ahead of everything queued (one WRITE, status awaited)."""
        await self._call("stop", lambda: self._tx.write(motor_id, GOAL_POSITION, goal_position),
                         urgent=True)

    async def stop_ahead(self, motor_id: int, offset_raw: int,
                         max_age_s: float = STOP_STATE_MAX_AGE_S) -> StopRecord:
        """Ahead of everything queued, one WRITE of Goal Position = the motor's position
        extrapolated to the moment of the write + ``offset_raw`` (the squeeze, signed in the
        closing direction).

        The position is the last one read (:meth:`seen`) moved on by its velocity. A state
        older than ``max_age_s``, read before the motor's last goal write or within
        ``STOP_STATE_SETTLE_S`` of it, or missing, is not trusted: then Present Position is
        read first, as many times as :attr:`stop_fallbacks`
        says. Either way the goal lies past where the motor is, so a stop never backs off
        the squeeze.
        """
        return await self._submit_stop(motor_id, offset_raw, max_age_s)

    async def _submit_stop(self, motor_id: int, offset_raw: int,
                           max_age_s: float | None) -> StopRecord:
        t_submit = self._clock()
        busy = self._executor.busy  # a transaction on the wire at the hand-over

        def op() -> StopRecord:
            t_start = self._clock()
            in_flight = max(0.0, self._last_op_end - t_submit) if busy else 0.0
            goal, age, why = stop_goal(self._tx, motor_id, offset_raw, max_age_s)
            prepared = self._stop_packets.get(motor_id)
            packet = prepared.build(goal) if prepared is not None else None
            self._tx.write(motor_id, GOAL_POSITION, goal, packet)
            port = self._tx.port
            t_written = getattr(port, "last_write_t", 0.0) or self._clock()
            t_call = getattr(port, "write_call_t", 0.0) or t_written
            self.last_stop_t = t_call
            self.stops += 1
            if why is not None and max_age_s is not None:
                self.stop_fallbacks += 1
            record = StopRecord(goal, why is None, age, why, t_submit, t_start, t_call,
                                t_written, in_flight)
            self.last_stop = record
            return record

        return await self._call("stop", op, urgent=True)

    async def set_torque(self, enabled: bool) -> None:
        """Torque on (goals set to present positions first, then the Bus Watchdog armed and
        fed) or off (watchdog disarmed first)."""
        if enabled:
            await self._call("torque on", lambda: bringup.torque_on(self._tx, self._config))
            self._torque_on = True
            _log.info("torque on: motors %s, Bus Watchdog %d ms", ", ".join(map(str, self._ids)),
                      self._config.watchdog_ms)
            if self._feed_task is None:
                self._feed_task = asyncio.create_task(self._feed_watchdog(),
                                                      name="dxl-watchdog-feed")
        else:
            await self._stop_feed()
            self._torque_on = False
            await self._call("torque off", lambda: bringup.torque_off(self._tx))
            _log.info("torque off: motors %s", ", ".join(map(str, self._ids)))

    async def recover_watchdog(self) -> list[int]:
        """Before a press (and between tries to open the gripper), each motor on its own:
        clear a Bus Watchdog trip (write 0, hold the present position, re-arm), and check
        torque is still on (a motor that shut itself down raises :class:`MotorError` naming
        it, and :attr:`fault` keeps saying so). A motor that does not answer raises naming
        it, once every other motor is seen to.

        Returns the IDs that had tripped.
        """
        return await self._call("recover watchdog", self._recover_watchdog_sync)

    # ---------------------------------------------------------------- the asyncio side

    async def _call(self, label: str, fn: Callable[[], Any], *, urgent: bool = False) -> Any:
        if not self._accepting:
            raise DeviceError(f"Dynamixel bus on {self._config.port} is not connected")
        if not self._port_up.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._port_up.wait(), PORT_BACK_WAIT_S)

        def run() -> Any:
            try:
                if self._port_fault is not None:
                    raise DeviceError(f"Dynamixel bus on {self._config.port}: {label}: "
                                      f"{self._port_fault}")
                return fn()
            except EdgeError:
                raise
            except _PORT_ERRORS as e:
                self._port_failed(label, e)
                raise DeviceError(f"Dynamixel bus on {self._config.port}: {label}: "
                                  f"{_port_error(e)}") from e
            finally:
                self._last_op_end = self._clock()

        try:
            return await self._executor.submit(label, run, urgent)
        finally:
            if self._port_fault is not None and self._accepting and self._reopen_task is None:
                self._port_up.clear()
                self._reopen_task = asyncio.create_task(self._reopen(), name="dxl-port-reopen")

    async def _reopen(self) -> None:
        """The background reopening after a port error (see ``_call``)."""
        try:
            await self._reopen_port(Backoff(PORT_REOPEN_BASE_S, PORT_REOPEN_CAP_S))
        finally:
            self._reopen_task = None

    async def _reopen_port(self, backoff: Backoff, give_up_s: float = math.inf) -> None:
        """Reopen the port until the motors answer on it again, waiting ``backoff`` before
        each try; the last try's :class:`DeviceError` once ``give_up_s`` have passed."""
        t_failed = self._clock()
        while True:
            await asyncio.sleep(backoff.next_s())
            try:
                await self._executor.submit("reopen port", self._reopen_sync)
            except DeviceError as exc:
                if self._clock() - t_failed >= give_up_s:
                    raise
                _log.log(logging.WARNING if backoff.failures == 1 else logging.DEBUG,
                         "reopening the Dynamixel port failed (again in %.2f s): %s",
                         backoff.delay_s, exc)
                continue
            self._port_up.set()
            _log.info("Dynamixel port %s is back %.2f s after its error", self._config.port,
                      self._clock() - t_failed)
            return

    async def _feed_watchdog(self) -> None:
        # Feeding from the loop, not the bus thread: a stalled event loop stops the feed, so
        # the watchdog catches a dead host as well as a dead process. Each motor is fed on
        # its own, only where nothing else it answered reached it lately: a sync read of all
        # would fail as a whole at one silent motor and starve every other.
        interval_s = self._config.watchdog_ms / 1000.0 / 4
        while True:
            await asyncio.sleep(interval_s)
            if not self._feed_due(interval_s):
                continue
            try:
                await self._call("feed watchdog", lambda: self._feed_sync(interval_s))
            except DeviceError as exc:  # the port is down: the reopening says so
                _log.debug("Bus Watchdog feed: %s", exc)

    def _feed_due(self, interval_s: float) -> list[int]:
        """The motors the feed asks now: those that answered nothing for ``interval_s``,
        then those with an error, each every ``SILENT_PROBE_S``."""
        now = self._clock()
        errors, heard = self._motor_errors, self._tx.heard
        due = [i for i in self._ids
               if i not in errors and now - heard.get(i, -math.inf) >= interval_s]
        return due + [i for i in self._ids if i in errors
                      and now - self._probed.get(i, -math.inf) >= SILENT_PROBE_S]

    async def _stop_feed(self) -> None:
        task, self._feed_task = self._feed_task, None
        if task is not None:
            await cancel_and_wait(task)

    async def _stop_reopen(self) -> None:
        task, self._reopen_task = self._reopen_task, None
        if task is not None:
            await cancel_and_wait(task)

    async def _shutdown(self) -> None:
        await self._stop_feed()
        await self._stop_reopen()
        self._accepting = False
        await self._executor.stop(self._close_port)
        self._torque_on = False

    # ---------------------------------------------------------------- on the executor

    def _connect_sync(self) -> dict[int, MotorInfo]:
        if self._exclusive:
            self._lock_fd = bringup.lock_port(self._config.port)
        self._open_port()
        if self._tx.read_only:
            return {}
        return bringup.configure(self._tx, self._config)

    def _open_port(self) -> None:
        port = bringup.open_port(self._config, self._port_handler_factory,
                                 self._latency_timer_dir)
        self._tx.port = port
        if isinstance(port, BlockingPortHandler):
            port.on_write = self._written

    def _written(self, t: float, head: bytes) -> None:
        self._executor.on_wire()
        if self.on_write is not None:
            self.on_write(t, head)

    def _ping_sync(self, motor_id: int) -> int:
        model, why = bringup.ping_once(self._tx, motor_id)
        if model is None:
            raise bringup.no_answer(self._config, [motor_id], why)
        return model

    def _recover_watchdog_sync(self) -> list[int]:
        units = bringup.watchdog_units(self._config) if self._torque_on else None
        check = bringup.check_motors(self._tx, torque_expected=self._torque_on,
                                     rearm_units=units, suspect=self._suspect())
        for motor_id in self._ids:
            self._motor_answered(motor_id, check.errors.get(motor_id))
        if check.torque_fault is not None:
            motor_id, self._torque_fault = check.torque_fault
            raise MotorError(self._torque_fault, motor_id)
        if check.errors:
            raise next(iter(check.errors.values()))
        return check.tripped

    def _feed_sync(self, interval_s: float) -> None:
        due = self._feed_due(interval_s)
        suspect = self._suspect()
        for motor_id in sorted(due, key=lambda i: i in suspect):
            if motor_id in self._motor_errors:
                self._probed[motor_id] = self._clock()
            try:
                # Once: a silent motor's second try would starve the others longer.
                self._tx.read(motor_id, BUS_WATCHDOG, attempts=1)
            except MotorError as exc:
                self._motor_answered(motor_id, exc)
            else:
                self._motor_answered(motor_id, None)

    def _suspect(self) -> set[int]:
        """Motors whose last error was a lost reply (no answer, or a garbled one)."""
        return {i for i, e in self._motor_errors.items() if e.transient}

    def _motor_answered(self, motor_id: int, error: MotorError | None) -> None:
        """Keep what the last feed or check of ``motor_id`` found (None: it answered)."""
        errors = self._motor_errors
        if error is None:
            if errors.pop(motor_id, None) is None:
                return
            _log.info("motor %d answers again", motor_id)
        else:
            if motor_id not in errors:
                _log.warning("motor %d: %s", motor_id, error)
            errors[motor_id] = error
        self._motors_fault = "; ".join(str(errors[i]) for i in sorted(errors)) or None

    def _port_failed(self, label: str, exc: Exception) -> None:
        """After an I/O error inside a transaction: the SDK leaves its port handler marked
        in use (every later call would answer "Port is in use!"), so the handler is closed
        and dropped; :meth:`_reopen` opens a new one, and :attr:`fault` says why
        meanwhile."""
        self._close_port()
        self._port_fault = (f"Dynamixel port {self._config.port} failed ({label}: "
                            f"{_port_error(exc)}); reopening it")
        _log.error("%s", self._port_fault)

    def _reopen_sync(self) -> None:
        """Open the port again and check the line: back once any motor answers a ping."""
        self._close_port()
        try:
            if self._exclusive:
                self._lock_fd = bringup.lock_port(self._config.port)
            self._open_port()
            answered = [i for i in self._ids if bringup.ping_once(self._tx, i)[0] is not None]
        except _PORT_ERRORS as exc:
            self._close_port()
            if isinstance(exc, DeviceError):  # (it names the port)
                raise
            raise DeviceError(f"Dynamixel port {self._config.port}: {_port_error(exc)}") from exc
        if not answered:
            self._close_port()
            raise DeviceError(f"no motor answers on {self._config.port} (check the bus's "
                              "power and cabling)")
        self._port_fault = None

    def _close_port(self) -> None:
        port, self._tx.port = self._tx.port, None
        if port is not None and port.is_open:
            with contextlib.suppress(OSError):
                port.closePort()
        lock_fd, self._lock_fd = self._lock_fd, -1
        if lock_fd >= 0:
            os.close(lock_fd)


def _port_error(exc: Exception) -> str:
    """An I/O error as a person reads it (termios.error's text is its bare tuple)."""
    if isinstance(exc, termios.error) and len(exc.args) == 2:
        return f"[Errno {exc.args[0]}] {exc.args[1]}"
    return str(exc)
