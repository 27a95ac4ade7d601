"""Bringing the bus up and keeping it fit to press: the port lock, finding and configuring
every motor, torque on and off with the Bus Watchdog, and the checks before each press.

Everything here runs on the bus's owner, over :class:`Transactions`.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path

import dynamixel_sdk as sdk

from edge import SERVICE_NAME
from edge.core.config import BusConfig
from edge.core.errors import BusInUseError, DeviceError, MotorError
from edge.hw.control_table import (
    BUS_WATCHDOG_UNIT_S,
    DRIVE_MODE_REVERSE,
    DRIVE_MODE_TIME_BASED_PROFILE,
    MODE_CURRENT_BASED_POSITION,
    MODE_POSITION,
    describe_hardware_error,
)
from edge.hw.dynamixel.port import (
    LATENCY_TIMER_UDEV_RULE,
    BlockingPortHandler,
    latency_timer_path,
    read_latency_timer,
)
from edge.hw.dynamixel.transactions import (
    BUS_WATCHDOG,
    CURRENT_LIMIT,
    DRIVE_MODE,
    FIRMWARE_VERSION,
    GOAL_CURRENT,
    GOAL_POSITION,
    HARDWARE_ERROR_STATUS,
    OPERATING_MODE,
    PRESENT_POSITION,
    READ_ATTEMPTS,
    RETURN_DELAY_TIME,
    STATUS_RETURN_LEVEL,
    TORQUE_ENABLE,
    Transactions,
)

_log = logging.getLogger(__name__)

# Models the driver is written for; others get a warning (their tables may differ).
XM430_MODELS = {1020: "XM430-W350", 1030: "XM430-W210"}


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


def lock_port(port: str) -> int:
    """The exclusive flock on the port device, on a descriptor of its own (returned).

    One bus, one owner: two processes talking on one half-duplex bus garble each other's
    replies and turn each other's motors off. The lock is an flock on the port device itself
    (what pyserial's exclusive=True takes), taken before the port is opened: opening a tty
    flushes its input, which would eat the replies of the process that owns it. The kernel
    drops it when this process dies.
    """
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
    return fd


def open_port(cfg: BusConfig, factory: Callable[[str], sdk.PortHandler],
              latency_timer_dir: Path) -> sdk.PortHandler:
    """The port handler, open at ``cfg.baudrate``, its latency timer checked."""
    port = factory(cfg.port)
    try:
        # setBaudRate opens the port (the SDK's openPort is setBaudRate of its default).
        opened = port.setBaudRate(cfg.baudrate)
    except OSError as exc:
        raise DeviceError(f"cannot open Dynamixel port {cfg.port}: {exc}") from exc
    if not opened:
        raise DeviceError(f"Dynamixel port {cfg.port}: baud rate {cfg.baudrate} is not one "
                          "the SDK supports")
    _check_latency_timer(cfg.port, port, latency_timer_dir)
    return port


def configure(tx: Transactions, cfg: BusConfig) -> dict[int, MotorInfo]:
    """Find every motor (a missing one raises naming it) and configure it; torque off."""
    models: dict[int, int] = {}
    missing: list[tuple[int, str]] = []
    for motor_id in tx.ids:
        model, why = ping_once(tx, motor_id)
        if model is None:
            missing.append((motor_id, why))
        else:
            models[motor_id] = model
    if missing:
        raise no_answer(cfg, [i for i, _ in missing], missing[0][1])

    infos = {}
    for motor_id in tx.ids:
        infos[motor_id] = _configure_motor(tx, motor_id, models[motor_id],
                                           motor_id == cfg.gripper_id)

    gripper = infos[cfg.gripper_id]
    if cfg.gripper_goal_current > gripper.current_limit:
        raise MotorError(
            f"motor {cfg.gripper_id}: gripper_goal_current {cfg.gripper_goal_current} "
            f"exceeds the motor's Current Limit {gripper.current_limit}", cfg.gripper_id)
    tx.write(cfg.gripper_id, GOAL_CURRENT, cfg.gripper_goal_current)
    _log.info("Dynamixel bus on %s at %d bps: motors %s ready (torque off)",
              cfg.port, cfg.baudrate, ", ".join(map(str, tx.ids)))
    return infos


def _configure_motor(tx: Transactions, motor_id: int, model: int,
                     is_gripper: bool) -> MotorInfo:
    if model not in XM430_MODELS:
        _log.warning("motor %d: model number %d is not an XM430 (%s); its control table "
                     "may differ", motor_id, model, ", ".join(map(str, XM430_MODELS)))
    firmware = tx.read(motor_id, FIRMWARE_VERSION)
    _ensure_status_return_level(tx, motor_id)
    # A watchdog trip left by an earlier run refuses goal writes until cleared; then torque
    # off, since the EEPROM registers below are writable only with torque off.
    tx.write(motor_id, BUS_WATCHDOG, 0)
    tx.write(motor_id, TORQUE_ENABLE, 0)

    drive = tx.read(motor_id, DRIVE_MODE)
    # The direction bit is the arm's business: keep it as found, never assume it. Joints
    # move on time-based profiles, the gripper on a velocity (its closing speed).
    want = drive & ~DRIVE_MODE_TIME_BASED_PROFILE
    if not is_gripper:
        want |= DRIVE_MODE_TIME_BASED_PROFILE
    if want != drive:
        tx.write(motor_id, DRIVE_MODE, want)
    mode = tx.read(motor_id, OPERATING_MODE)
    want_mode = MODE_CURRENT_BASED_POSITION if is_gripper else MODE_POSITION
    if mode != want_mode:
        tx.write(motor_id, OPERATING_MODE, want_mode)
    if tx.read(motor_id, RETURN_DELAY_TIME) != 0:
        tx.write(motor_id, RETURN_DELAY_TIME, 0)
    current_limit = tx.read(motor_id, CURRENT_LIMIT)
    _log.info("motor %d: %s firmware %d, drive mode %d (%s direction, %s profile), "
              "operating mode %d -> %d", motor_id, XM430_MODELS.get(model, model), firmware,
              want, "reverse" if want & DRIVE_MODE_REVERSE else "normal",
              "time-based" if want & DRIVE_MODE_TIME_BASED_PROFILE else "velocity-based",
              mode, want_mode)
    return MotorInfo(motor_id, model, firmware, want, want_mode, current_limit)


def _ensure_status_return_level(tx: Transactions, motor_id: int) -> None:
    # Below 2 a motor answers writes with silence, which would read as timeouts.
    level = tx.read(motor_id, STATUS_RETURN_LEVEL)
    if level == 2:
        return
    _log.warning("motor %d: Status Return Level %d; setting 2", motor_id, level)
    result = tx.ph.write1ByteTxOnly(tx.port, motor_id, STATUS_RETURN_LEVEL.address, 2)
    tx.check(motor_id, "write Status Return Level = 2", result, 0)
    if tx.read(motor_id, STATUS_RETURN_LEVEL) != 2:
        raise MotorError(f"motor {motor_id}: Status Return Level does not stay at 2",
                         motor_id)


def _check_latency_timer(port_name: str, port: sdk.PortHandler, timer_dir: Path) -> None:
    path = latency_timer_path(port_name, timer_dir)
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
            "(`vt-edge install-udev --install` installs it)", port_name, value,
            value, path, LATENCY_TIMER_UDEV_RULE)


def ping_once(tx: Transactions, motor_id: int) -> tuple[int | None, str]:
    """(model number, "") or (None, why there was no answer)."""
    for _ in range(READ_ATTEMPTS):  # one lost reply is not a missing motor
        model, result, error = tx.ph.ping(tx.port, motor_id)
        if result == sdk.COMM_SUCCESS:
            tx.check(motor_id, "ping", result, error)
            return model, ""
        tx.port.clearPort()
    return None, tx.ph.getTxRxResult(result)


def no_answer(cfg: BusConfig, ids: list[int], why: str) -> MotorError:
    return MotorError(
        f"motor {', '.join(map(str, ids))} did not answer a ping on {cfg.port} at "
        f"{cfg.baudrate} bps: {why} (check power, cabling, ID and baud rate)", ids[0])


def scan(tx: Transactions) -> dict[int, int]:
    found, _ = tx.ph.broadcastPing(tx.port)
    tx.port.clearPort()
    return {motor_id: model for motor_id, (model, _firmware) in sorted(found.items())}


def watchdog_units(cfg: BusConfig) -> int:
    """The Bus Watchdog register value for ``cfg.watchdog_ms``."""
    return round(cfg.watchdog_ms / 1000.0 / BUS_WATCHDOG_UNIT_S)


def torque_on(tx: Transactions, cfg: BusConfig) -> None:
    state = tx.read_state()
    # Torque on holds wherever the goal says: make that where each motor stands.
    tx.sync_write(GOAL_POSITION, {i: s.position for i, s in state.motors.items()})
    for motor_id in tx.ids:
        tx.write(motor_id, TORQUE_ENABLE, 1)
    units = watchdog_units(cfg)
    for motor_id in tx.ids:
        tx.write(motor_id, BUS_WATCHDOG, units)


def torque_off(tx: Transactions) -> None:
    # Try every motor even if one fails: as many as possible end up limp.
    first: MotorError | None = None
    for motor_id in tx.ids:
        try:
            tx.write(motor_id, BUS_WATCHDOG, 0)
            tx.write(motor_id, TORQUE_ENABLE, 0)
        except MotorError as exc:
            _log.error("torque off: %s", exc)
            first = first or exc
    if first is not None:
        raise first


@dataclass
class MotorCheck:
    """What :func:`check_motors` found: ``tripped`` the motors whose Bus Watchdog had tripped
    (cleared now), ``torque_fault`` (motor, why) for the first motor with torque off where
    torque should be on, ``errors`` each motor that did not answer or refused, by ID."""

    tripped: list[int]
    torque_fault: tuple[int, str] | None
    errors: dict[int, MotorError]


def check_motors(tx: Transactions, *, torque_expected: bool, rearm_units: int | None,
                 suspect: Collection[int] = ()) -> MotorCheck:
    """Before every press and between tries to open the gripper: each motor on its own (a
    sync read fails as a whole at one silent motor, and a silent joint must not keep the
    gripper's trip from being cleared), its Torque Enable, Hardware Error Status and Bus
    Watchdog in one READ. A tripped motor is cleared (write 0), holds its present position
    and is re-armed with ``rearm_units`` (None: torque is off, left disarmed).

    ``suspect``: motors that did not answer lately, asked last and once: each try waits
    out the reply's timeout while no other motor hears anything.
    """
    tripped: list[int] = []
    fault: tuple[int, str] | None = None
    errors: dict[int, MotorError] = {}
    for motor_id in sorted(tx.ids, key=lambda i: i in suspect):
        try:
            values = tx.read_span(motor_id, (TORQUE_ENABLE, HARDWARE_ERROR_STATUS, BUS_WATCHDOG),
                                  1 if motor_id in suspect else READ_ATTEMPTS)
            if values[BUS_WATCHDOG] == -1:
                tx.write(motor_id, BUS_WATCHDOG, 0)
                tx.write(motor_id, GOAL_POSITION, tx.read(motor_id, PRESENT_POSITION))
                if rearm_units is not None:
                    tx.write(motor_id, BUS_WATCHDOG, rearm_units)
                tripped.append(motor_id)
        except MotorError as exc:
            errors[motor_id] = exc
            continue
        if torque_expected and not values[TORQUE_ENABLE] and fault is None:
            fault = motor_id, _torque_off_why(tx, motor_id, values[HARDWARE_ERROR_STATUS])
    if tripped:
        _log.warning("Bus Watchdog had tripped on motors %s; cleared, holding position",
                     tripped)
    return MotorCheck(tripped, fault, errors)


def _torque_off_why(tx: Transactions, motor_id: int, status: int) -> str:
    """Why a motor found with torque off has it off.

    A motor that shut itself down (overload, overheating...) has torque off: any goal is
    ignored, so a press would close nothing and open nothing. (While its alert is on, every
    read of it raises with the Hardware Error Status instead.)
    """
    if status:
        return (f"motor {motor_id}: torque is off (Hardware Error Status 0x{status:02x}: "
                f"{describe_hardware_error(status)}): the motor shut itself down; remove "
                "the cause, power-cycle or reboot it, then restart the daemon")
    # A motor that shuts itself down keeps its alert until it is rebooted; with none,
    # torque was turned off from the bus (a second program on it: the port lock keeps
    # out only programs that take it) or the motor lost power.
    return (f"motor {motor_id}: torque is off with no hardware error: not a shutdown of the "
            f"motor; another program on {tx.port_name} turned it off (one bus, one owner: "
            "stop it), or the motor was power-cycled or rebooted; then restart the daemon")


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
