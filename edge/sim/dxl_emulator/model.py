"""The emulated motors of a Dynamixel Protocol 2.0 bus of XM430-W350s: the device model.

:meth:`DxlEmulator.start` serves them on a pty pair (:mod:`.pty`; ``emulator.port``, e.g.
``/dev/pts/7``), so the real ``dynamixel_sdk.PortHandler(emulator.port)`` talks to them byte
for byte; :meth:`DxlEmulator.transact` takes instruction packets in-process (the recorder's
virtual bus). Packets (:mod:`.codec`): header ``FF FF FD 00``, CRC-16 (poly 0x8005), byte
stuffing both ways, status packets, Return Delay Time, Status Return Level, broadcast rules
(no status for broadcast writes). Instructions: PING (unicast and broadcast), READ, WRITE,
REG_WRITE, ACTION, REBOOT, SYNC READ, FAST SYNC READ, SYNC WRITE, BULK READ, BULK WRITE.

Each motor has the XM430 control table in memory with the EEPROM/RAM rules (EEPROM writes
answer the Access error while torque is on), the static and dependent write limits, and a
motion model stepped on a fixed simulated step (1 ms) of ``time.monotonic``:

- profile motion to Goal Position, velocity-based or time-based per Drive Mode bit 2, as a
  trapezoid re-planned from rest at every goal write (a real motor blends from its present
  velocity; the emulator does not);
- current-based position (Operating Mode 5): the motor cannot advance toward its goal in the
  closing direction while the external load is at least Goal Current (raw * 2.69 mA); the
  profile pauses while it is stalled;
- the Bus Watchdog: while torque is on and the watchdog is armed, an interval without any
  instruction packet longer than its period stops the motion, the register reads -1 and goal
  writes (Goal PWM/Current/Velocity/Position) answer the Data Range error until 0 is written.

Physics hook: ``load(motor_id, position_raw, t) -> mA`` gives the external load current at the
motion model's time ``t``, opposing the closing direction (decreasing position with the default
Drive Mode, increasing position with Drive Mode bit 0 set; positive = resists closing). Present
Current reports it (capped at Goal Current in current-based position mode, at Current Limit
otherwise), with the motor's sign convention: a motor pushing toward decreasing position draws
negative current.
``true_position(motor_id)`` reads the true position (raw, float) from any thread.

Modelling gaps: no wire time (10 us/byte at 1 Mbps), no velocity/PWM/current operating-mode
dynamics (goals are stored, nothing moves), Baud Rate changes are stored but ignored, and
Torque Enable = 1 sets Goal Position to the present position (the driver writes it before
torque on anyway, so it never depends on this).

The stop check: a Goal Position write that reaches a motor in current-based position mode
while it is closing (its profile heads in the closing direction) and sets a goal short of
the one it was closing to is a stop. For each, the emulator records in ``stop_checks`` how
far the goal lies past the motor's true position at the instant the packet arrived, in the
closing direction, and counts in ``stops_behind`` every stop whose goal lay behind it: a
stop that backed off the squeeze.

Fault switches: ``set_missing`` (a motor that does not answer at all), ``corrupt_crc`` (replies
with a wrong CRC), ``set_hardware_error`` (Hardware Error Status bits, the alert bit in every
status packet and torque off, as a real shutdown does), and the line's (:mod:`.pty`):
``unplug`` / ``plug`` (the adapter, its path gone then back), ``serial_error_once`` (an I/O
error inside the next transaction, then a working line). Torque changes are logged (INFO).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from edge.hw.control_table import (
    BUS_WATCHDOG_UNIT_S,
    CURRENT_MA_PER_UNIT,
    DRIVE_MODE_REVERSE,
    DRIVE_MODE_TIME_BASED_PROFILE,
    MODE_CURRENT_BASED_POSITION,
    MODE_EXTENDED_POSITION,
    MODE_POSITION,
    OPERATING_MODES,
    RAW_PER_S2_PER_ACCELERATION_UNIT,
    RAW_PER_S_PER_VELOCITY_UNIT,
    RETURN_DELAY_UNIT_S,
    XM430_W350,
    Area,
    Register,
)
from edge.sim.dxl_emulator.codec import (
    BROADCAST_ID,
    ERR_ACCESS,
    ERR_ALERT,
    ERR_CRC,
    ERR_DATA_LENGTH,
    ERR_DATA_LIMIT,
    ERR_DATA_RANGE,
    ERR_INSTRUCTION,
    ERR_RESULT_FAIL,
    HEADER,
    INST_ACTION,
    INST_BULK_READ,
    INST_BULK_WRITE,
    INST_FAST_SYNC_READ,
    INST_PING,
    INST_READ,
    INST_REBOOT,
    INST_REG_WRITE,
    INST_STATUS,
    INST_SYNC_READ,
    INST_SYNC_WRITE,
    INST_WRITE,
    Instruction,
    crc16,
    encode_packet,
    parse_packet,
)
from edge.sim.dxl_emulator.pty import PtyTransport

_log = logging.getLogger(__name__)

LoadFn = Callable[[int, float, float], float]

# Firmware of the XM430s on our arm.
DEFAULT_FIRMWARE = 48
# Hardware no-load speed of the XM430-W350 at 12 V is about 46 rev/min (200 velocity units):
# a Profile Velocity of 0 ("infinite") still moves at most this fast.
_MAX_VELOCITY_UNITS = 200

_TABLE = XM430_W350
_GOALS = frozenset({"Goal PWM", "Goal Current", "Goal Velocity", "Goal Position"})


@dataclass(frozen=True)
class StopCheck:
    """One stop as the emulator took it: ``ahead_raw`` is how far the goal lay past the
    true position in the closing direction when the packet arrived (< 0: behind it), and
    ``velocity_raw_s`` the motor's velocity then."""

    t: float
    motor_id: int
    goal: int
    true_position: float
    ahead_raw: float
    velocity_raw_s: float


@dataclass(frozen=True)
class Received:
    """One instruction as the emulator took it off the wire (for tests to check ordering)."""

    t: float
    motor_id: int
    instruction: int
    params: bytes


class _Profile:
    """A trapezoidal move from ``start`` to ``goal`` beginning at ``t0``."""

    __slots__ = ("dist", "duration", "goal", "sign", "start", "t0", "t_acc", "v")

    def __init__(self, start: float, goal: float, t0: float, duration: float,
                 t_acc: float) -> None:
        self.start, self.goal, self.t0 = start, goal, t0
        self.dist = abs(goal - start)
        self.sign = 1.0 if goal >= start else -1.0
        self.duration = duration
        self.t_acc = min(t_acc, duration / 2)
        cruise = duration - self.t_acc
        self.v = self.dist / cruise if cruise > 0 else 0.0

    @classmethod
    def velocity_based(cls, start: float, goal: float, t0: float, v: float,
                       a: float) -> _Profile:
        dist = abs(goal - start)
        if dist == 0 or v <= 0:
            return cls(start, goal, t0, 0.0, 0.0)
        t_acc = v / a if math.isfinite(a) else 0.0
        if v * t_acc > dist:  # never reaches v: a triangle
            t_acc = math.sqrt(dist / a)
            v = a * t_acc
        return cls(start, goal, t0, dist / v + t_acc, t_acc)

    def position(self, t: float) -> float:
        tau = t - self.t0
        if tau <= 0:
            return self.start
        if tau >= self.duration:
            return self.goal
        v, ta = self.v, self.t_acc
        if tau < ta:
            x = 0.5 * v / ta * tau * tau
        elif tau <= self.duration - ta:
            x = 0.5 * v * ta + v * (tau - ta)
        else:
            r = self.duration - tau
            x = self.dist - 0.5 * v / ta * r * r
        return self.start + self.sign * x

    def done(self, t: float) -> bool:
        return t - self.t0 >= self.duration


class _Motor:
    """Control table memory and physical state of one emulated motor."""

    def __init__(self, motor_id: int, position: float, firmware: int) -> None:
        self.mem = bytearray(_TABLE.size)
        for reg in _TABLE.values():
            self.mem[reg.address:reg.end] = reg.encode(reg.default)
        self.id = motor_id
        self.put("ID", motor_id)
        self.put("Firmware Version", firmware)
        # An OpenMANIPULATOR-X ships with its motors at 1 Mbps.
        self.put("Baud Rate", 3)
        self.put("Goal Position", round(position))
        self.pos = float(position)
        self.vel = 0.0
        self.load_ma = 0.0
        self.profile: _Profile | None = None
        self.stalled = False
        self.watchdog_last = 0.0
        self.pending: tuple[int, bytes] | None = None  # REG_WRITE waiting for ACTION
        self.missing = False
        self.corrupt_left = 0  # replies still to corrupt; -1 forever
        self.load_failed = False

    def get(self, name: str) -> int:
        reg = _TABLE[name]
        return reg.decode(self.mem[reg.address:reg.end])

    def put(self, name: str, value: int) -> None:
        reg = _TABLE[name]
        self.mem[reg.address:reg.end] = reg.encode(value)

    @property
    def torque_on(self) -> bool:
        return self.mem[64] == 1

    @property
    def closing_sign(self) -> float:
        return 1.0 if self.mem[10] & DRIVE_MODE_REVERSE else -1.0

    @property
    def watchdog_tripped(self) -> bool:
        return self.mem[98] == 0xFF

    @property
    def return_delay_s(self) -> float:
        return self.mem[9] * RETURN_DELAY_UNIT_S


class DxlEmulator:
    """XM430-W350 motors on a Protocol 2.0 bus behind a pty, served by one thread.

    ``ids``: the motors on the bus (OpenMANIPULATOR-X: joints 11-14, gripper 15).
    ``load``: optional physics hook, see the module docstring; called for every motor with
    torque on, from the emulator's thread (and from ``true_position`` callers) with the
    emulator's lock held. It must be quick, and must not take a lock that another thread
    holds while calling into the emulator (a physics thread calling ``true_position`` under
    its own lock would deadlock against a ``load`` that takes that lock).
    ``reply_latency_s``: added once before the status packets of every instruction (a USB
    adapter's latency timer, a slow bus); settable while running.
    ``initial_positions``: raw positions at power-up (default 2048, the centre).
    """

    def __init__(
        self,
        ids: Iterable[int] = (11, 12, 13, 14, 15),
        *,
        load: LoadFn | None = None,
        reply_latency_s: float = 0.0,
        step_s: float = 0.001,
        initial_positions: Mapping[int, float] | None = None,
        firmware: int = DEFAULT_FIRMWARE,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        positions = dict(initial_positions or {})
        self._motors = {i: _Motor(i, positions.get(i, 2048.0), firmware) for i in ids}
        self._load = load
        self.reply_latency_s = reply_latency_s
        self._step_s = step_s
        self.clock = clock
        self._lock = threading.RLock()
        self._sim_t = clock()
        self.received: collections.deque[Received] = collections.deque(maxlen=10_000)
        self.stop_checks: collections.deque[StopCheck] = collections.deque(maxlen=10_000)
        self.stops_behind = 0
        # Torque Enable = 1 writes that took effect, on any motor: the history a start that
        # must never power the arm is checked against.
        self.torque_enables = 0
        self.port = ""
        self._pty = PtyTransport(self)

    # ---------------------------------------------------------------- lifecycle

    def start(self) -> DxlEmulator:
        """Serve the motors on a pty (:attr:`port`) from a thread of their own."""
        if self._pty.serving:
            raise RuntimeError("emulator already started")
        with self._lock:
            self._sim_t = self.clock()
            for motor in self._motors.values():
                motor.watchdog_last = self._sim_t
        self.port = self._pty.start()
        _log.debug("Dynamixel emulator serving %s, motors %s", self.port, sorted(self._motors))
        return self

    def stop(self) -> None:
        self._pty.stop()

    @property
    def plugged(self) -> bool:
        """Whether the emulated adapter is plugged in (its port's path exists)."""
        return self._pty.plugged

    def unplug(self) -> None:
        """Pull the emulated adapter out: the client's line fails, the port's path is gone.
        The motors keep their power: with torque on, their Bus Watchdogs trip."""
        self._pty.unplug()

    def plug(self) -> None:
        """Plug the emulated adapter back in, under the same path."""
        self._pty.plug()

    def serial_error_once(self) -> None:
        """Fail the line inside the next transaction (its client reads an I/O error while it
        waits for the reply), then serve a working one under the same path at once."""
        self._pty.serial_error_once()

    def __enter__(self) -> DxlEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---------------------------------------------------------------- test and physics API

    def true_position(self, motor_id: int) -> float:
        """The motor's true position (raw counts), advanced to now."""
        with self._lock:
            self._advance(self.clock())
            return self._motors[motor_id].pos

    def transact(self, data: bytes) -> bytes:
        """The in-process transport of the dataset recorder's virtual bus: execute the
        instruction packets in ``data`` at the clock's present time and return their status
        packets at once (the recorder models the wire's timing itself). Not while the pty
        thread serves."""
        if self._pty.serving:
            raise RuntimeError("transact() is for an emulator without its pty thread")
        now = self.clock()
        buf = bytearray(data)
        out = bytearray()
        self.advance(now)
        while (ins := parse_packet(buf)) is not None:
            for _motor_id, _delay_s, packet in self.execute(ins, now):
                out += packet
        return bytes(out)

    def advance(self, now: float) -> None:
        """Step the motion model (and the watchdogs) to ``now``."""
        with self._lock:
            self._advance(now)

    def execute(self, ins: Instruction, now: float) -> list[tuple[int, float, bytes]]:
        """Take one instruction off the wire at ``now`` (the model advanced to it): the
        status packets it is answered with, in bus order, each as (motor ID, that motor's
        Return Delay Time, packet)."""
        self.received.append(Received(now, ins.motor_id, ins.instruction, ins.params))
        with self._lock:
            return [(m.id, m.return_delay_s, packet) for m, packet in self._handle(ins, now)]

    def get_register(self, motor_id: int, name: str) -> int:
        """A register as the motor would answer it now (bypasses the bus)."""
        with self._lock:
            self._advance(self.clock())
            motor = self._motors[motor_id]
            self._refresh(motor)
            return motor.get(name)

    @staticmethod
    def _trip(m: _Motor) -> None:
        # Torque stays on, the motor holds where it is, goal writes are refused.
        m.mem[98] = 0xFF
        m.profile = None
        m.vel = 0.0
        m.put("Goal Position", round(m.pos))
        _log.info("emulated motor %d: Bus Watchdog tripped", m.id)

    def pause_watchdogs(self, seconds: float) -> None:
        """Let ``seconds`` not count towards any Bus Watchdog: time the transport could not
        see the wire (its thread did not run)."""
        with self._lock:
            for m in self._motors.values():
                m.watchdog_last += seconds

    def trip_watchdog(self, motor_id: int) -> None:
        """Trip the motor's Bus Watchdog now, as a host silent past it would: the motor
        stops where it is, and every read still answers."""
        with self._lock:
            self._advance(self.clock())
            self._trip(self._motors[motor_id])

    def set_register(self, motor_id: int, name: str, value: int) -> None:
        """Set a register behind the bus's back (no access rules), e.g. Return Delay Time 0.

        ``Present Position`` moves the motor there (and its Goal Position with it).
        """
        with self._lock:
            self._advance(self.clock())
            motor = self._motors[motor_id]
            if name == "Present Position":
                motor.pos = float(value)
                motor.profile = None
                motor.put("Goal Position", value)
                return
            reg = _TABLE[name]
            motor.mem[reg.address:reg.end] = reg.encode(value)
            self._after_write(motor, reg, value, self._sim_t)

    @property
    def ids(self) -> tuple[int, ...]:
        """The motors on the bus, by ID."""
        with self._lock:
            return tuple(sorted(self._motors))

    def missing(self, motor_id: int) -> bool:
        """Whether the motor is switched silent (:meth:`set_missing`)."""
        with self._lock:
            return self._motors[motor_id].missing

    def set_missing(self, motor_id: int, missing: bool = True) -> None:
        """A missing motor hears nothing and answers nothing (unplugged, wrong ID or baud)."""
        with self._lock:
            self._motors[motor_id].missing = missing

    def corrupt_crc(self, motor_id: int, count: int = 1) -> None:
        """Send the next ``count`` status packets of this motor with a wrong CRC (-1: all;
        0: stop)."""
        with self._lock:
            self._motors[motor_id].corrupt_left = count

    def set_hardware_error(self, motor_id: int, bits: int) -> None:
        """Raise Hardware Error Status bits (0 clears): the motor shuts down (torque off) and
        every status packet carries the alert bit until cleared."""
        with self._lock:
            self._advance(self.clock())
            motor = self._motors[motor_id]
            motor.put("Hardware Error Status", bits)
            if bits:
                _log.info("emulated motor %d: hardware error 0x%02x, torque off", motor_id,
                          bits)
                motor.put("Torque Enable", 0)
                motor.profile = None
                motor.vel = 0.0

    # ---------------------------------------------------------------- motion model

    def _advance(self, now: float) -> None:
        dt = self._step_s
        while self._sim_t + dt <= now:
            self._sim_t += dt
            for motor in self._motors.values():
                self._step(motor, self._sim_t, dt)

    def _step(self, m: _Motor, t: float, dt: float) -> None:
        if not m.torque_on:
            m.vel = 0.0
            return
        wd = m.mem[98]
        if 0 < wd <= 127 and t - m.watchdog_last > wd * BUS_WATCHDOG_UNIT_S:
            self._trip(m)
            return
        profile = m.profile
        if profile is None:
            m.vel = 0.0
            return
        desired = profile.position(t)
        if (m.mem[11] == MODE_CURRENT_BASED_POSITION and self._load is not None
                and (desired - m.pos) * m.closing_sign > 0):
            load = self._call_load(m, t)
            cap_ma = abs(m.get("Goal Current")) * CURRENT_MA_PER_UNIT
            if load >= cap_ma:
                # Stalled on the object: the profile waits, the motor pushes at the cap.
                profile.t0 += dt
                m.stalled = True
                m.vel = 0.0
                return
        m.stalled = False
        m.vel = (desired - m.pos) / dt
        m.pos = desired
        if profile.done(t):
            m.profile = None
            m.vel = 0.0

    def _call_load(self, m: _Motor, t: float) -> float:
        if self._load is None:
            return 0.0
        try:
            load = float(self._load(m.id, m.pos, t))
        except Exception:
            if not m.load_failed:
                _log.exception("load hook failed for motor %d; using 0 mA", m.id)
                m.load_failed = True
            return 0.0
        m.load_ma = load
        return load

    def _start_profile(self, m: _Motor, goal: int, t: float) -> None:
        pv = m.get("Profile Velocity")
        pa = m.get("Profile Acceleration")
        limit_units = m.get("Velocity Limit") or _MAX_VELOCITY_UNITS
        v_max = min(limit_units, _MAX_VELOCITY_UNITS) * RAW_PER_S_PER_VELOCITY_UNIT
        if m.mem[10] & DRIVE_MODE_TIME_BASED_PROFILE and pv > 0:
            m.profile = _Profile(m.pos, goal, t, pv / 1000.0, pa / 1000.0)
        else:
            v = min(pv * RAW_PER_S_PER_VELOCITY_UNIT, v_max) if pv > 0 else v_max
            a = pa * RAW_PER_S2_PER_ACCELERATION_UNIT if pa > 0 else math.inf
            m.profile = _Profile.velocity_based(m.pos, goal, t, v, a)

    def _refresh(self, m: _Motor) -> None:
        """Copy the physical state into the Present registers before a read."""
        profile = m.profile
        if m.torque_on and self._load is not None:
            load = self._call_load(m, self._sim_t)
            # The motor's current cannot exceed its cap: Goal Current in current-based
            # position mode (a stall overshoots the cap by at most one step of load), the
            # Current Limit otherwise.
            limit_ma = m.get("Current Limit") * CURRENT_MA_PER_UNIT
            if m.mem[11] == MODE_CURRENT_BASED_POSITION:
                limit_ma = min(limit_ma, abs(m.get("Goal Current")) * CURRENT_MA_PER_UNIT)
            current_ma = m.closing_sign * max(-limit_ma, min(limit_ma, load))
        else:
            current_ma = 0.0
        moving = profile is not None and not m.stalled
        m.put("Present Position", round(m.pos))
        m.put("Present Velocity", round(m.vel / RAW_PER_S_PER_VELOCITY_UNIT))
        m.put("Present Current", round(current_ma / CURRENT_MA_PER_UNIT))
        m.put("Moving", int(moving))
        in_position = not moving and abs(m.get("Goal Position") - m.pos) <= 1
        m.put("Moving Status", (0x02 if profile is not None else 0) | int(in_position))
        desired = profile.position(self._sim_t) if profile is not None else m.pos
        m.put("Position Trajectory", round(desired))
        m.put("Realtime Tick", int(self._sim_t * 1000) % 32768)

    # ---------------------------------------------------------------- control table writes

    def _check_write(self, m: _Motor, address: int, data: bytes) -> int:
        """The error a WRITE of ``data`` at ``address`` answers, 0 if it is accepted."""
        regs = _TABLE.covering(address, len(data))
        if regs is None:
            return ERR_ACCESS
        for reg in regs:
            value = reg.decode(data[reg.address - address:reg.end - address])
            if not reg.writable or (reg.area is Area.EEPROM and m.torque_on):
                return ERR_ACCESS
            if reg.name in _GOALS and m.watchdog_tripped:
                return ERR_DATA_RANGE
            if not reg.check(value):
                return ERR_DATA_RANGE
            error = self._check_dependent(m, reg, value)
            if error:
                return error
        return 0

    def _check_dependent(self, m: _Motor, reg: Register, value: int) -> int:
        name = reg.name
        if name == "Operating Mode" and value not in OPERATING_MODES:
            return ERR_DATA_RANGE
        if name == "Drive Mode" and value & ~0x0D:
            return ERR_DATA_RANGE
        if name == "Torque Enable" and value and m.get("Hardware Error Status"):
            return ERR_RESULT_FAIL  # shut down: only a reboot clears it
        if name == "Goal Current" and abs(value) > m.get("Current Limit"):
            return ERR_DATA_LIMIT
        if name == "Goal Velocity" and abs(value) > m.get("Velocity Limit"):
            return ERR_DATA_LIMIT
        if name == "Goal PWM" and abs(value) > m.get("PWM Limit"):
            return ERR_DATA_LIMIT
        if (name == "Goal Position" and m.mem[11] == MODE_POSITION
                and not m.get("Min Position Limit") <= value <= m.get("Max Position Limit")):
            return ERR_DATA_LIMIT
        return 0

    def _write(self, m: _Motor, address: int, data: bytes, t: float) -> int:
        error = self._check_write(m, address, data)
        if error:
            return error
        for reg in _TABLE.covering(address, len(data)) or ():
            chunk = data[reg.address - address:reg.end - address]
            m.mem[reg.address:reg.end] = chunk
            self._after_write(m, reg, reg.decode(chunk), t)
        return 0

    def _after_write(self, m: _Motor, reg: Register, value: int, t: float) -> None:
        name = reg.name
        if name == "Torque Enable":
            m.profile = None
            m.vel = 0.0
            _log.info("emulated motor %d: torque %s", m.id, "on" if value else "off")
            if value:
                self.torque_enables += 1
                m.put("Goal Position", round(m.pos))
                m.watchdog_last = t
        elif name == "Goal Position":
            if m.torque_on and m.mem[11] in (MODE_POSITION, MODE_EXTENDED_POSITION,
                                             MODE_CURRENT_BASED_POSITION):
                if m.mem[11] == MODE_CURRENT_BASED_POSITION:
                    self._check_stop(m, value, t)
                self._start_profile(m, value, t)
        elif name == "Bus Watchdog":
            m.watchdog_last = t
        elif name == "Operating Mode":
            m.profile = None
        elif name == "ID" and value != m.id:
            self._motors.pop(m.id, None)
            m.id = value
            self._motors[value] = m

    def _check_stop(self, m: _Motor, goal: int, t: float) -> None:
        """Record a stop (see the module docstring); ``m.pos`` is the position now."""
        profile, closing = m.profile, m.closing_sign
        if profile is None or (profile.goal - m.pos) * closing <= 0:
            return  # not closing
        if (goal - profile.goal) * closing >= 0:
            return  # closing on, or further
        ahead = (goal - m.pos) * closing
        self.stop_checks.append(StopCheck(t, m.id, goal, m.pos, ahead, m.vel))
        if ahead < 0:
            self.stops_behind += 1
            _log.warning("emulated motor %d: stop goal %d lies %.2f counts behind its true "
                         "position %.2f: the stop backed off the squeeze", m.id, goal, -ahead,
                         m.pos)

    # ---------------------------------------------------------------- instructions

    def _handle(self, ins: Instruction, now: float) -> list[tuple[_Motor, bytes]]:
        """Execute one instruction; return the status packets to send, in bus order."""
        present = [m for m in self._motors.values() if not m.missing]
        if not ins.crc_ok:
            m = self._motors.get(ins.motor_id)
            if m is None or m.missing:
                return []
            return [(m, self._status(m, ERR_CRC))]
        for m in present:
            # Every instruction packet on the bus counts as communication for the watchdog.
            m.watchdog_last = now
        inst, params, target = ins.instruction, ins.params, ins.motor_id
        if inst == INST_PING:
            targets = present if target == BROADCAST_ID else [
                m for m in present if m.id == target]
            return [(m, self._status(m, 0, _TABLE["Model Number"].encode(_TABLE.model_number)
                                     + bytes((m.mem[6],)))) for m in sorted(targets, key=_id)]
        if inst in (INST_SYNC_READ, INST_FAST_SYNC_READ, INST_SYNC_WRITE, INST_BULK_READ,
                    INST_BULK_WRITE):
            if target != BROADCAST_ID:
                return []
            return self._handle_group(inst, params, now)
        if target == BROADCAST_ID:
            if inst in (INST_WRITE, INST_REG_WRITE) and len(params) >= 3:
                address = int.from_bytes(params[:2], "little")
                for m in present:
                    self._unicast(m, inst, address, params[2:], now)
            elif inst == INST_ACTION:
                for m in present:
                    self._action(m, now)
            return []
        m = self._motors.get(target)
        if m is None or m.missing:
            return []
        return self._handle_unicast(m, inst, params, now)

    def _handle_unicast(self, m: _Motor, inst: int, params: bytes,
                        now: float) -> list[tuple[_Motor, bytes]]:
        level = m.mem[68]
        addressed = m.id
        if inst == INST_READ:
            if len(params) != 4:
                return [(m, self._status(m, ERR_DATA_LENGTH))] if level >= 1 else []
            address = int.from_bytes(params[:2], "little")
            length = int.from_bytes(params[2:], "little")
            if level < 1:
                return []
            return [(m, self._read_status(m, address, length))]
        if inst in (INST_WRITE, INST_REG_WRITE):
            if len(params) < 3:
                error = ERR_DATA_LENGTH
            else:
                error = self._unicast(m, inst, int.from_bytes(params[:2], "little"), params[2:],
                                      now)
        elif inst == INST_ACTION:
            error = self._action(m, now)
        elif inst == INST_REBOOT:
            error = 0
            self._reboot(m, now)
        else:
            error = ERR_INSTRUCTION
        # The status comes from the ID addressed, even when the write changed it.
        return [(m, self._status(m, error, reply_id=addressed))] if level >= 2 else []

    def _unicast(self, m: _Motor, inst: int, address: int, data: bytes, now: float) -> int:
        if inst == INST_WRITE:
            return self._write(m, address, data, now)
        error = self._check_write(m, address, data)
        if not error:
            m.pending = (address, bytes(data))
            m.put("Registered Instruction", 1)
        return error

    def _action(self, m: _Motor, now: float) -> int:
        if m.pending is None:
            return 0
        address, data = m.pending
        m.pending = None
        m.put("Registered Instruction", 0)
        return self._write(m, address, data, now)

    def _reboot(self, m: _Motor, now: float) -> None:
        for reg in _TABLE.values():
            if reg.area is Area.RAM:
                m.mem[reg.address:reg.end] = reg.encode(reg.default)
        m.profile = None
        m.vel = 0.0
        m.pending = None
        m.put("Goal Position", round(m.pos))
        m.watchdog_last = now

    def _handle_group(self, inst: int, params: bytes,
                      now: float) -> list[tuple[_Motor, bytes]]:
        if inst == INST_BULK_READ:
            replies = []
            for i in range(0, len(params) - 4, 5):
                m = self._motors.get(params[i])
                if m is None or m.missing:
                    continue
                address = int.from_bytes(params[i + 1:i + 3], "little")
                length = int.from_bytes(params[i + 3:i + 5], "little")
                if m.mem[68] >= 1:
                    replies.append((m, self._read_status(m, address, length)))
            return replies
        if inst == INST_BULK_WRITE:
            i = 0
            while i + 5 <= len(params):
                address = int.from_bytes(params[i + 1:i + 3], "little")
                length = int.from_bytes(params[i + 3:i + 5], "little")
                m = self._motors.get(params[i])
                if m is not None and not m.missing:
                    self._write(m, address, params[i + 5:i + 5 + length], now)
                i += 5 + length
            return []
        if len(params) < 4:
            return []
        address = int.from_bytes(params[:2], "little")
        length = int.from_bytes(params[2:4], "little")
        rest = params[4:]
        if inst == INST_SYNC_WRITE:
            for i in range(0, len(rest) - length, length + 1):
                m = self._motors.get(rest[i])
                if m is not None and not m.missing:
                    self._write(m, address, rest[i + 1:i + 1 + length], now)
            return []
        motors = [self._motors.get(i) for i in rest]
        if inst == INST_SYNC_READ:
            return [(m, self._read_status(m, address, length)) for m in motors
                    if m is not None and not m.missing and m.mem[68] >= 1]
        # FAST SYNC READ: one status packet, ID 0xFE, one [error, id, data, crc] block per
        # motor; each block's CRC covers the packet so far, the last one is the packet CRC.
        if not motors or any(m is None or m.missing for m in motors):
            return []  # the daisy chain breaks at a missing motor: the host times out
        return [(motors[0], self._fast_sync_status(motors, address, length))]  # type: ignore[arg-type]

    # ---------------------------------------------------------------- status packets

    def _error_byte(self, m: _Motor, error: int) -> int:
        return error | (ERR_ALERT if m.mem[70] else 0)

    def _status(self, m: _Motor, error: int, params: bytes = b"",
                reply_id: int | None = None) -> bytes:
        body = bytes((INST_STATUS, self._error_byte(m, error))) + params
        packet = bytearray(encode_packet(m.id if reply_id is None else reply_id, body))
        if m.corrupt_left:
            packet[-1] ^= 0xFF
            if m.corrupt_left > 0:
                m.corrupt_left -= 1
        return bytes(packet)

    def _read_status(self, m: _Motor, address: int, length: int) -> bytes:
        if length == 0 or address + length > _TABLE.size:
            return self._status(m, ERR_ACCESS)
        self._refresh(m)
        return self._status(m, 0, bytes(m.mem[address:address + length]))

    def _fast_sync_status(self, motors: list[_Motor], address: int, length: int) -> bytes:
        # Length field: the instruction byte plus the blocks (the last CRC is the packet's).
        # Not byte-stuffed: the SDK's fast path does not unstuff.
        body_len = 1 + (length + 4) * len(motors)
        packet = bytearray(HEADER + bytes((BROADCAST_ID, body_len & 0xFF, body_len >> 8,
                                           INST_STATUS)))
        for m in motors:
            self._refresh(m)
            packet += bytes((self._error_byte(m, 0), m.id)) + m.mem[address:address + length]
            packet += crc16(packet).to_bytes(2, "little")
        return bytes(packet)

def _id(m: _Motor) -> int:
    return m.id
