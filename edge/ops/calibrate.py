"""``vt-edge calibrate threshold``: find the press threshold x_th for this robot's own pads.

The paper's x_th = 0.004 tactile units belongs to its uncalibrated sensor: another pad reads
the same force on another scale, with another idle noise (docs/hardware.md, 'Finding x_th').
The procedure, on the real drivers (on the emulated robot they talk to the emulators):

(a) idle: the arm at ``lowered``, the fingers open and touching nothing; tared as a press
    tares (the mean of ``[press] tare_s`` of frames), the norm over the following seconds
    gives the noise; the threshold is kept at least ``NOISE_FLOOR_FACTOR`` times its p99.9.
(b) probe: tared again, the gripper closes slowly on the lab's reference object, its Goal
    Current capped, while the norm, the gripper's width and Present Current (and the
    ``calibrated`` newtons where xela_server sends them) are recorded; it opens as soon as
    the squeeze is well past the target force, and on every way out.
(c) proposal: x_th is the norm at which the squeeze reached the gentle force the lab states
    (motor current above the free-closing current, or newtons), the fragile threshold
    ``FRAGILE_RATIO`` x_th, both at least the noise floor; the curve goes to a PNG and x_th
    into the configuration, comments kept.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from edge.core import preprocess, tomledit
from edge.core.atomic import atomic_write_text
from edge.core.config import Config
from edge.core.errors import EdgeError, SensorError, SensorLayoutError, StaleSensorError
from edge.core.prompt import NO_PROMPT, Prompt, ask, in_daemon_thread, read_line
from edge.hw.arm import GRIPPER_CLOSED_WIDTH_M
from edge.hw.contracts import Devices, GripperState
from edge.hw.control_table import CURRENT_MA_PER_UNIT
from edge.runtime.press import PressController
from edge.runtime.ring import FrameRing
from edge.runtime.sensor import SENSOR_RETRY_S

log = logging.getLogger(__name__)

# (a) Idle: seconds recorded (the first tare_s of them are the tare), and how far above the
# idle norm's p99.9 a threshold must stay: a press watches the norm for seconds, and drift
# and the slow wander of the pads reach past what a few seconds of idle show. On pads with
# the real XR1944's noise (the emulated ones, docs/hardware.md 'Tactile units') p99.9 is
# ~0.0012, so the paper's own pair, 0.004 and 0.003, lies 3.3x and 2.4x above it: 2x keeps
# both clear of the noise without raising them.
IDLE_S = 4.0
NOISE_FLOOR_FACTOR = 2.0
# The object is taken as touched from the first frame over this many times the idle p99.9:
# the end of free closing and the start of the curve.
CONTACT_FACTOR = 1.5
MIN_IDLE_FRAMES = 50
# (b) Probe: gap closing speed (the press closes at [press] close_speed_mps, 0.01; at 0.004
# one 125 Hz frame is 32 um of gap, so the curve is quasi-static); the probe goes on to this
# many times the target force, then opens.
PROBE_SPEED_MPS = 0.004
PROBE_BEYOND = 2.0
# The free-closing current: the median squeeze from this long after the start of closing
# (the motor accelerating) to the first touch (CONTACT_FACTOR); at least this many reads.
FREE_SKIP_S = 0.3
MIN_FREE_READS = 5
# How often the gripper is read while probing (one sync read of the bus, ~2.4 ms on the arm).
PROBE_READ_S = 0.01
# Closing this long without the squeeze reaching its end ends the probe (an object too soft
# to push back within the gripper's travel, a gripper stuck).
PROBE_TIMEOUT_S = 30.0
# The gripper is taken as closed on nothing within this of its closed end.
CLOSED_MARGIN_M = 0.001
# The probe never commands more than this current (mA) unless --max-ma says otherwise, and
# never more than the configuration's Goal Current.
MAX_MA = 200.0
# (c) Proposal: the default gentle force, as motor current above free closing. On the
# emulated robot (edge.sim.world FORCE_PER_MA_N: 0.0186 N per mA, no friction) 20 mA is
# ~0.37 N per finger, where today's x_th = 0.004 is crossed by a flat face covering the pad
# (edge.sim.skin): on the emulated XR1944 pads the default reproduces today's threshold with
# the kitchen sponge as the reference object (docs/hardware.md, 'Finding x_th').
FORCE_MA = 20.0
# The paper presses very fragile objects at 0.003 against 0.004: the same ratio here.
FRAGILE_RATIO = 0.75
# From the first touch to the target force, at least this many frames:
# fewer, and the object is too stiff for the probe to resolve the gentle part of its curve.
MIN_CURVE_FRAMES = 10
# Norm and current are averaged over this many frames (40 ms at 125 Hz) before the force
# target is looked up: Present Current moves in 2.69 mA steps and jitters.
SMOOTH_FRAMES = 5
STREAM_START_TIMEOUT_S = 5.0
# Before anything moves, --force-n needs `calibrated` newtons in one of this many frames.
NEWTONS_CHECK_FRAMES = 25
# Frames kept: the probe and idle take well under a minute at 125 Hz.
RING_FRAMES = 16_000


_NO_NEWTONS = ("--force-n needs xela_server's `calibrated` newtons, which these pads do not "
               "send (the XR1944 is uncalibrated): state the force with --force-ma")


@dataclass(frozen=True)
class IdleNoise:
    frames: int
    seconds: float
    p50: float
    p999: float
    max: float

    @property
    def floor(self) -> float:
        return NOISE_FLOOR_FACTOR * self.p999


@dataclass(frozen=True)
class ProbeTrace:
    """The probe, one row per tactile frame from the start of closing to the end."""

    t: np.ndarray  # s from the start of closing
    norm: np.ndarray  # tactile units
    closing_m: np.ndarray  # gripper width closed since the start, m
    squeeze_ma: np.ndarray  # Present Current pushing the fingers closed, mA
    newtons: np.ndarray | None  # per-finger normal force from `calibrated`, N; or None
    free_ma: float  # squeeze while closing on nothing
    t_contact: float  # first frame over CONTACT_FACTOR x the idle p99.9, s from the start
    end: str  # why the probe ended


@dataclass(frozen=True)
class Proposal:
    x_th: float
    fragile: float
    # Where each threshold is crossed on the probe (s from the start, closing in m, squeeze
    # above free closing in mA, newtons when sent).
    at_x_th: dict
    at_fragile: dict
    target: str  # the gentle force in words
    clipped: bool  # raised to the noise floor


@dataclass(frozen=True)
class Measurement:
    """What the robot part of the procedure found: the report is made from it."""

    proposal: Proposal
    trace: ProbeTrace
    idle: IdleNoise


class _Stream:
    """Every frame of the tactile source into a ring, reconnecting as the sensor task
    does; :meth:`fresh` raises when nothing arrived for ``stale_s`` (the probe then ends and
    the gripper opens)."""

    def __init__(self, source, channels: int, clock: Callable[[], float],
                 stale_s: float) -> None:
        self.source = source
        self.stale_s = stale_s
        self.ring = FrameRing(channels, RING_FRAMES)
        # `calibrated` newtons beside the ring's rows; NaN where a frame had none.
        self.newtons = np.full((RING_FRAMES, channels), np.nan)
        self.sent_newtons = False
        self.clock = clock
        self.error: BaseException | None = None

    async def run(self) -> None:
        while True:
            try:
                async for frame in self.source.frames():
                    row = self.ring.count % RING_FRAMES
                    if frame.newtons is None:
                        self.newtons[row] = np.nan
                    else:
                        self.newtons[row] = frame.newtons
                        self.sent_newtons = True
                    self.ring.push(frame.raw, frame.recv_time, frame.sensor_time, frame.seq)
            except SensorLayoutError as exc:
                self.error = exc
                return
            except SensorError as exc:  # stale or broken: reconnect as the sensor task does
                self.error = exc
            await asyncio.sleep(SENSOR_RETRY_S)

    def fresh(self) -> None:
        if isinstance(self.error, SensorLayoutError):
            raise self.error
        age = self.clock() - self.ring.latest_time()
        if age > self.stale_s:
            since = f"for {age:.2f} s" if self.ring.count else "yet"
            why = f" ({self.error})" if self.error is not None else ""
            raise StaleSensorError(f"no tactile frame {since}{why}: check that xela_server "
                                   "runs and the pads are connected")

    async def wait_frames(self, n: int) -> None:
        deadline = self.clock() + STREAM_START_TIMEOUT_S
        while self.ring.count < n:
            if self.clock() > deadline or isinstance(self.error, SensorLayoutError):
                self.fresh()
                raise StaleSensorError(f"only {self.ring.count} tactile frames in "
                                       f"{STREAM_START_TIMEOUT_S:g} s: the stream is too slow")
            await asyncio.sleep(0.05)

    def since(self, t0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Receive times, raw frames and (where every frame has them) newtons from ``t0``."""
        ring = self.ring
        counts = np.arange(ring.count - min(ring.count, ring.capacity), ring.count)
        rows = counts % ring.capacity
        rows = rows[ring.recv_time[rows] >= t0]
        forces = self.newtons[rows]
        newtons = forces if len(rows) and np.isfinite(forces).all() else None
        return ring.recv_time[rows].copy(), ring.raw[rows].copy(), newtons


async def measure_idle(stream: _Stream, cfg: Config, idle_s: float) -> IdleNoise:
    """(a) The idle norm, tared as a press tares."""
    t0 = stream.clock()
    await asyncio.sleep(idle_s)
    stream.fresh()
    t, raw, _ = stream.since(t0)
    # (the tare's frames as preprocess.tared_norms takes them, as doctor measures too)
    after = t >= t[0] + cfg.press.tare_s if len(t) else np.zeros(0, dtype=bool)
    if after.sum() < MIN_IDLE_FRAMES or (~after).sum() < 3:
        raise StaleSensorError(f"only {len(t)} tactile frames in {idle_s} s of idle: the "
                               "stream is too slow to measure its noise")
    norms = preprocess.tared_norms(t, raw, cfg.press.tare_s)
    return IdleNoise(int(after.sum()), float(t[after][-1] - t[after][0]),
                     float(np.median(norms)), float(np.percentile(norms, 99.9)),
                     float(norms.max()))


def _per_finger_newtons(forces: np.ndarray, pads: int) -> np.ndarray:
    """Normal (z) force per finger: the sum of each pad's taxels, averaged over the pads."""
    z = forces[:, 2::3].reshape(len(forces), pads, -1)
    return z.sum(axis=2).mean(axis=1)


async def probe(stream: _Stream, devices: Devices, cfg: Config, idle: IdleNoise, *,
                cap_ma: float, stop_ma: float | None, stop_n: float | None,
                speed_mps: float) -> ProbeTrace:
    """(b) Close slowly on the object until the squeeze (current above free closing, or
    newtons) reaches ``stop_ma``/``stop_n`` or the current cap; the caller opens."""
    clock = stream.clock
    t_tare = clock()
    await asyncio.sleep(cfg.press.tare_s)
    stream.fresh()
    _, tare_raw, tare_forces = stream.since(t_tare)
    tare = preprocess.tare(tare_raw)
    tare_n = (None if tare_forces is None
              else float(_per_finger_newtons(tare_forces, cfg.sensor.pads).mean()))
    gripper = devices.gripper
    t_start = clock()
    # Both fingers move: each closes at half the gap speed.
    await gripper.close(speed_mps / 2, cap_ma)
    states: list[GripperState] = []
    free_ma: float | None = None
    t_contact: float | None = None
    end = ""
    while not end:
        await asyncio.sleep(PROBE_READ_S)
        stream.fresh()
        state = await gripper.state()
        states.append(state)
        raw = stream.ring.raw[stream.ring.latest_index]
        level = float(np.linalg.norm(raw - tare)) / preprocess.UNITS_SCALE
        if t_contact is None and level > CONTACT_FACTOR * idle.p999:
            t_contact = stream.ring.latest_time()
            free = [s.squeeze_ma for s in states if t_start + FREE_SKIP_S <= s.t < t_contact]
            if len(free) < MIN_FREE_READS:
                raise EdgeError(
                    f"the pads felt the object {t_contact - t_start:.2f} s after the gripper "
                    "started closing, before its free-closing current could be measured: "
                    "open wider ([press] open_width_m) or centre a narrower reference object")
            free_ma = float(np.median(free))
        if free_ma is not None:
            above = state.squeeze_ma - free_ma
            newest = stream.newtons[stream.ring.latest_index]
            if stop_ma is not None and above >= stop_ma:
                end = f"squeeze {above:.0f} mA above free closing"
            elif stop_n is not None and tare_n is not None and np.isfinite(newest).all() and (
                    _per_finger_newtons(newest[None], cfg.sensor.pads)[0] - tare_n >= stop_n):
                end = f"{stop_n:.2f} N per finger"
        if not end and state.squeeze_ma >= 0.9 * cap_ma:
            end = f"current cap ({cap_ma:.0f} mA)"
        if state.width_m <= GRIPPER_CLOSED_WIDTH_M + CLOSED_MARGIN_M:
            raise EdgeError("the gripper closed without the pads feeling anything over their "
                            f"idle noise ({idle.p999:.5f}): place the reference object "
                            "between the fingers, or check the pads")
        if clock() - t_start > PROBE_TIMEOUT_S:
            raise EdgeError(f"the probe closed for {PROBE_TIMEOUT_S:.0f} s without reaching "
                            "its end force: a stiffer reference object, or a higher --max-ma")
    # Stop where it stands and hold as a press holds before the caller opens.
    await gripper.stop_now(0)
    await asyncio.sleep(cfg.press.dt_stopping_s)
    assert free_ma is not None and t_contact is not None
    t, raw, forces = stream.since(t_start)
    gt = np.array([s.t for s in states])
    newtons = None
    if forces is not None and tare_n is not None:
        newtons = _per_finger_newtons(forces, cfg.sensor.pads) - tare_n
    width0 = states[0].width_m
    return ProbeTrace(
        t=t - t_start,
        norm=np.asarray(preprocess.norm(preprocess.to_units(raw, tare)), dtype=np.float64),
        closing_m=width0 - np.interp(t, gt, [s.width_m for s in states]),
        squeeze_ma=np.interp(t, gt, [s.squeeze_ma for s in states]),
        newtons=newtons, free_ma=free_ma, t_contact=t_contact - t_start, end=end)


def _smooth(x: np.ndarray) -> np.ndarray:
    if len(x) < SMOOTH_FRAMES:
        return x
    kernel = np.ones(SMOOTH_FRAMES) / SMOOTH_FRAMES
    padded = np.pad(x, SMOOTH_FRAMES // 2, mode="edge")
    return np.convolve(padded, kernel, mode="valid")


def _first_crossing(x: np.ndarray, level: float) -> float | None:
    """Fractional index where ``x`` first reaches ``level`` (linear between frames)."""
    hit = np.flatnonzero(x >= level)
    if hit.size == 0:
        return None
    i = int(hit[0])
    if i == 0:
        return 0.0
    return i - 1 + float((level - x[i - 1]) / (x[i] - x[i - 1]))


def _at(trace: ProbeTrace, index: float) -> dict:
    frames = np.arange(len(trace.t))

    def value(x: np.ndarray) -> float:
        return float(np.interp(index, frames, x))

    out = {"t_s": value(trace.t), "closing_mm": 1e3 * value(trace.closing_m),
           "above_free_ma": value(_smooth(trace.squeeze_ma)) - trace.free_ma}
    if trace.newtons is not None:
        out["newtons"] = value(_smooth(trace.newtons))
    return out


def propose(trace: ProbeTrace, idle: IdleNoise, *, force_ma: float | None = None,
            force_n: float | None = None) -> Proposal:
    """(c) The norm at which the squeeze reached the gentle force; fragile at
    ``FRAGILE_RATIO`` of it; both at least the noise floor."""
    norm = _smooth(trace.norm)
    if force_n is not None:
        if trace.newtons is None:
            raise EdgeError(_NO_NEWTONS)
        force, target = _smooth(trace.newtons), f"{force_n:g} N per finger"
        level = force_n
    else:
        assert force_ma is not None
        force = _smooth(trace.squeeze_ma) - trace.free_ma
        target, level = f"{force_ma:g} mA above free closing ({trace.free_ma:.0f} mA)", force_ma
    # Only from the contact on: the motor's start-up current is no squeeze.
    start = int(np.searchsorted(trace.t, trace.t_contact))
    hit = _first_crossing(force[start:], level)
    if hit is None:
        raise EdgeError(f"the probe never reached {target} (its most: "
                        f"{float(force[start:].max(initial=0.0)):.2f}): lower the force, "
                        "or raise --max-ma")
    if hit < MIN_CURVE_FRAMES:
        raise EdgeError(f"the squeeze went from first touch to {target} within {hit:.0f} "
                        f"frames (fewer than {MIN_CURVE_FRAMES}): the reference object is too "
                        "stiff for the probe to resolve; use a softer one (a kitchen sponge, a "
                        "foam block) or a slower --speed-mps")
    index = start + hit
    x_th = float(np.interp(index, np.arange(len(norm)), norm))
    clipped = x_th < idle.floor
    x_th = max(x_th, idle.floor)
    fragile = max(FRAGILE_RATIO * x_th, idle.floor)
    at_fragile = _first_crossing(norm[start:], fragile)
    return Proposal(round(x_th, 5), round(fragile, 5), _at(trace, index),
                    _at(trace, start + (at_fragile or 0.0)), target, clipped)


async def calibrate_threshold(cfg: Config, config_path: str | Path, out: str | Path, *,
                              force_ma: float | None = FORCE_MA, force_n: float | None = None,
                              max_ma: float = MAX_MA, idle_s: float = IDLE_S,
                              speed_mps: float = PROBE_SPEED_MPS,
                              prompt: Prompt | None = read_line,
                              confirm: Prompt | None = read_line,
                              devices: Devices | None = None) -> Proposal:
    """The whole procedure: :func:`measure_threshold`, then :func:`report` off the event
    loop once the devices are closed; returns the proposal."""
    m = await measure_threshold(cfg, force_ma=force_ma, force_n=force_n, max_ma=max_ma,
                                idle_s=idle_s, speed_mps=speed_mps, prompt=prompt,
                                devices=devices)
    # (a daemon thread: a Ctrl-C at the question does not wait for Enter)
    return await in_daemon_thread(report, m, cfg, config_path, out, confirm)


async def measure_threshold(cfg: Config, *, force_ma: float | None = FORCE_MA,
                            force_n: float | None = None, max_ma: float = MAX_MA,
                            idle_s: float = IDLE_S, speed_mps: float = PROBE_SPEED_MPS,
                            prompt: Prompt | None = read_line,
                            devices: Devices | None = None) -> Measurement:
    """Idle, probe and proposal on ``devices`` (by default the configuration's real ones,
    opened and closed here)."""
    from edge.runtime.devices import close_devices, enable_torque, open_devices

    for name, value, ok, want in (
            ("--force-ma", force_ma, force_ma is None or force_ma > 0, "> 0 mA"),
            ("--force-n", force_n, force_n is None or force_n > 0, "> 0 N"),
            ("--max-ma", max_ma, max_ma > 0, "> 0 mA"),
            ("--idle-s", idle_s, idle_s >= cfg.press.tare_s + 1.0,
             f">= 1 s more than [press] tare_s ({cfg.press.tare_s} s)"),
            ("--speed-mps", speed_mps, 0 < speed_mps <= cfg.press.close_speed_mps,
             f"in (0, [press] close_speed_mps = {cfg.press.close_speed_mps}] m/s")):
        if not ok:
            raise EdgeError(f"{name} {value}: must be {want}")
    config_cap_ma = cfg.bus.gripper_goal_current * CURRENT_MA_PER_UNIT
    cap_ma = min(max_ma, config_cap_ma)
    wanted = (force_ma or 0.0) * PROBE_BEYOND
    if force_n is None and wanted >= 0.9 * cap_ma:
        raise EdgeError(f"--force-ma {force_ma:g}: the probe goes to {PROBE_BEYOND:g} x that "
                        f"above free closing, past the current cap {cap_ma:.0f} mA (--max-ma "
                        f"{max_ma:g}, [bus] gripper_goal_current {config_cap_ma:.0f} mA)")
    own = devices is None
    if own:
        devices = await open_devices(cfg)
    assert devices is not None
    if hasattr(devices.tactile, "newtons"):
        devices.tactile.newtons = True  # the XELA client: keep `calibrated` where sent
    clock = asyncio.get_running_loop().time
    stream = _Stream(devices.tactile, cfg.sensor.channels, clock, cfg.sensor.stale_timeout_s)
    reader = asyncio.create_task(stream.run(), name="calibrate-sensor")
    # The press's own opening: capped at Goal Current, retried, the watchdog cleared.
    press = PressController(cfg, devices.gripper, devices.arm, stream.ring,
                            recover=devices.recover, clock=clock)
    timeout = cfg.runtime.move_timeout_s
    gripper_stuck = False
    try:
        if own:
            await enable_torque(devices)
        # (frames the client parsed before it was asked for newtons may come first)
        await stream.wait_frames(NEWTONS_CHECK_FRAMES)
        if force_n is not None and not stream.sent_newtons:
            raise EdgeError(_NO_NEWTONS)
        await press.open_gripper()
        await devices.arm.move_to("above", timeout)
        if prompt is not None:
            await ask(prompt, "place the reference object where presses happen (the fingers "
                              "will close on it), then Enter ", NO_PROMPT)
        await devices.arm.move_to("lowered", timeout)
        idle = await measure_idle(stream, cfg, idle_s)
        print(f"idle: {idle.frames} frames over {idle.seconds:.1f} s, norm p50 "
              f"{idle.p50:.5f}, p99.9 {idle.p999:.5f}, max {idle.max:.5f}; noise floor "
              f"{NOISE_FLOOR_FACTOR:g} x p99.9 = {idle.floor:.5f}")
        try:
            trace = await probe(stream, devices, cfg, idle, cap_ma=cap_ma,
                                stop_ma=None if force_n is not None else wanted,
                                stop_n=None if force_n is None else force_n * PROBE_BEYOND,
                                speed_mps=speed_mps)
        finally:
            failed = await press.open_gripper_retrying()
            if failed is not None:
                gripper_stuck = True
                raise EdgeError(f"GRIPPER MAY STILL BE CLOSED: opening failed ({failed}); "
                                "free the object by hand")
        await devices.arm.move_to("above", timeout)
    finally:
        reader.cancel()
        try:
            await reader
        except asyncio.CancelledError:
            pass
        except Exception:  # the outcome above is the one to report
            log.exception("the tactile reader failed")
        if own:
            if gripper_stuck and devices.bus is not None:
                # As a press that could not open leaves it: the arm where it stands (moving
                # it could drag the gripped object), torque off; then the rest is closed.
                try:
                    await devices.bus.close()
                except Exception as exc:
                    log.error("bus shutdown: %s", exc)
            await close_devices(devices, timeout)
    print(f"probe: closed {1e3 * trace.closing_m[-1]:.1f} mm in {trace.t[-1]:.1f} s at "
          f"{1e3 * speed_mps:g} mm/s; free closing {trace.free_ma:.1f} mA; contact at "
          f"{trace.t_contact:.2f} s; stopped at {trace.end}")
    proposal = propose(trace, idle, force_ma=None if force_n is not None else force_ma,
                       force_n=force_n)
    return Measurement(proposal, trace, idle)


def report(m: Measurement, cfg: Config, config_path: str | Path, out: str | Path,
           confirm: Prompt | None) -> Proposal:
    """The curve's PNG and data into ``out``, then x_th into ``config_path`` if ``confirm``
    says yes (None: without asking). Blocking: run it outside the event loop."""
    from edge.ops.calibrate_png import plot_curve

    proposal, trace, idle = m.proposal, m.trace, m.idle
    out = Path(out)
    a, f = proposal.at_x_th, proposal.at_fragile
    floor_note = (f" (raised to the noise floor {idle.floor:.5f})" if proposal.clipped else "")
    print(f"proposed x_th = {proposal.x_th:.5f}{floor_note}: the norm at {proposal.target}, "
          f"{a['closing_mm']:.2f} mm into the closing")
    newtons = f" ({f['newtons']:.2f} N per finger)" if "newtons" in f else ""
    print(f"fragile x_th = {proposal.fragile:.5f} ({FRAGILE_RATIO:g} x): crossed at "
          f"{f['above_free_ma']:.1f} mA above free closing{newtons}, {f['closing_mm']:.2f} mm")
    png = out / "threshold.png"
    plot_curve(trace, proposal, idle, png)
    data = {"x_th": proposal.x_th, "fragile_x_th": proposal.fragile, "target": proposal.target,
            "at_x_th": proposal.at_x_th, "at_fragile": proposal.at_fragile,
            "clipped_to_floor": proposal.clipped, "idle": asdict(idle) | {"floor": idle.floor},
            "free_ma": trace.free_ma, "t_contact_s": trace.t_contact, "end": trace.end,
            "curve": {"t_s": trace.t.tolist(), "norm": trace.norm.tolist(),
                      "closing_m": trace.closing_m.tolist(),
                      "squeeze_ma": trace.squeeze_ma.tolist(),
                      "newtons": None if trace.newtons is None else trace.newtons.tolist()}}
    atomic_write_text(out / "threshold.json", json.dumps(data) + "\n")
    print(f"curve: {png} (data: {out / 'threshold.json'})")
    old = cfg.press.x_th
    question = (f"write [press] x_th = {proposal.x_th:.5f} (now {old:g}) into {config_path}? "
                "[y/N] ")
    try:
        answer = "y" if confirm is None else str(confirm(question))
    except EOFError:  # no terminal to ask on: not written
        answer = ""
    if answer.strip().lower() in ("y", "yes"):
        tomledit.update(config_path, config_path, {"press": {"x_th": proposal.x_th}})
        print(f"[press] x_th: {old:g} -> {proposal.x_th:.5f} in {config_path}")
    else:
        print(f"{config_path} unchanged ([press] x_th = {old:g})")
    print(f"fragile objects: press them with x_th = {proposal.fragile:.5f} (vt-edge collect "
          f"--x-th {proposal.fragile:.5f}; a collection plan's per-class x_th)")
    return proposal
