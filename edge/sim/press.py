"""A whole press on the simulated robot, without device emulators.

Reproduces the protocol of docs/method.md, 'Press': idle (tare), close at a set speed, stop when
the tactile norm of an arriving frame exceeds ``x_th`` (the stop takes effect after the
controller's reaction latency, an input, so a slower stop overshoots the force), hold
``dt_stopping``, open. The gripper is current-limited (it stalls at ``force_cap_n``) and the
stop is a goal a little past the present position, as on the real gripper. Output is a
:class:`edge.core.recording.Recording` in raw counts plus a summary of the press.

Deterministic for a seed: everything random comes from one ``numpy.random.Generator``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edge.core import preprocess
from edge.core.config import PressConfig, SimConfig
from edge.core.recording import Recording
from edge.hw.arm import GRIPPER_OPEN_SPEED_MPS
from edge.sim.catalogue import ObjectClass, get
from edge.sim.contact import Contact, ObjectInstance
from edge.sim.skin import Skin
from edge.sim.world import WIDTH_PER_RAW_M

SENSOR_MODEL = "XR1944"
# Sensor server clock: wall-clock-like seconds, unrelated to the host's monotonic clock.
_SENSOR_EPOCH = 1.77e9
_PRESS = PressConfig()
_SIM = SimConfig()


@dataclass(frozen=True)
class PressParams:
    # The press itself takes the runtime's defaults ([press] and [sim] of the config), so
    # training data and the robot's presses share one definition.
    x_th: float = _PRESS.x_th
    dt_stopping_s: float = _PRESS.dt_stopping_s
    close_speed_mps: float = _PRESS.close_speed_mps
    # Finger-gap speeds; the gripper driver commands the joint ("width"), which moves each
    # finger, so the gap opens at twice its 0.02 m/s.
    open_speed_mps: float = 2 * GRIPPER_OPEN_SPEED_MPS
    reaction_latency_s: float = _SIM.reaction_latency_s
    sensor_rate_hz: float = _SIM.sensor_rate_hz
    # Idle before closing; the tare averages its last tare_s.
    idle_s: float = 0.5
    tare_s: float = _PRESS.tare_s
    clearance_m: tuple[float, float] = (0.003, 0.008)
    # The stop goal lies press.stop_squeeze_raw encoder counts past the present position, as
    # the driver writes it: a gentle squeeze (the present position itself would release the
    # object). Each count moves both fingers, so the gap closes by twice its width.
    squeeze_m: float = 2 * _PRESS.stop_squeeze_raw * WIDTH_PER_RAW_M
    # Position loop of the gripper motor: how fast it settles on a new goal.
    position_tau_s: float = 0.005
    # Current-limited gripper: Goal Current 200 (~0.54 A) gives ~10 N per finger.
    force_cap_n: float = 10.0
    # Recording continues this long after t_stop (the crop needs 0.6 s).
    tail_s: float = 0.7
    physics_dt_s: float = 0.0005
    transport_delay_s: float = 0.001
    frame_jitter_s: float = 0.0003
    gripper_trace_hz: float = 100.0
    abort_factor: float = _PRESS.abort_factor


@dataclass(frozen=True)
class PressResult:
    recording: Recording
    contact: bool  # did the threshold trigger before the gripper closed fully
    t_contact: float | None  # first physical contact
    t_cross: float | None  # receive time of the first frame over x_th
    t_stop: float | None
    force_at_cross_n: float
    peak_force_n: float
    aborted: bool

    @property
    def overshoot_n(self) -> float:
        return self.peak_force_n - self.force_at_cross_n


def simulate_press(obj: ObjectClass | str, rng: np.random.Generator | int,
                   params: PressParams = PressParams(), t0: float = 100.0) -> PressResult:
    """Press ``obj`` once; ``t0`` is the monotonic time at which the recording starts."""
    cls = get(obj) if isinstance(obj, str) else obj
    rng = np.random.default_rng(rng) if isinstance(rng, int) else rng
    inst = ObjectInstance.draw(cls, rng)
    contact = Contact(inst)
    skin = Skin(inst, rng)
    p = params

    open_gap = inst.width_m + rng.uniform(*p.clearance_m)
    gap = open_gap
    dt = p.physics_dt_s
    frame_period = 1.0 / p.sensor_rate_hz
    trace_period = 1.0 / p.gripper_trace_hz
    force_per_ma = p.force_cap_n / (200 * 2.69)

    frames, recv, sens, seqs = [], [], [], []
    g_t, g_w, g_i = [], [], []
    tare_counts: np.ndarray | None = None
    t = 0.0
    next_frame = rng.uniform(0.0, frame_period)
    next_trace = 0.0
    seq = int(rng.integers(1000, 100000))
    t_contact = t_cross = t_stop = None
    force_at_cross = 0.0
    peak = 0.0
    aborted = False
    phase = "idle"  # idle -> closing -> stopping -> holding -> opening
    target = gap
    t_end = math.inf
    max_t = p.idle_s + open_gap / p.close_speed_mps + 2.0

    while t < t_end and t < max_t:
        # Gripper: a goal reached at limited speed; it cannot close against force_cap_n.
        # Until the stop takes effect (the reaction latency) the gripper keeps closing.
        if phase in ("closing", "stopping"):
            step = -p.close_speed_mps * dt
        else:
            speed = p.open_speed_mps if phase == "opening" else p.close_speed_mps
            pull = (target - gap) * min(1.0, dt / p.position_tau_s)
            step = max(-speed * dt, min(speed * dt, pull))
        if step < 0 and contact.force >= p.force_cap_n:
            step = 0.0
        gap = max(gap + step, 0.0)
        force = contact.step(gap, dt)
        t += dt
        if force > 0 and t_contact is None:
            t_contact = t0 + t
        peak = max(peak, force)

        if t >= next_trace:
            g_t.append(t0 + t)
            g_w.append(gap)
            g_i.append(force / force_per_ma)
            next_trace += trace_period
        if t >= next_frame:
            raw = skin.frame(t, force, contact.contact_radius())
            t_recv = t + p.transport_delay_s + abs(rng.normal(0.0, p.frame_jitter_s))
            frames.append(raw)
            recv.append(t0 + t_recv)
            sens.append(_SENSOR_EPOCH + t)
            seqs.append(seq)
            seq += 1
            next_frame += frame_period
            # Controller: the threshold is checked on every arriving frame.
            if phase == "idle" and t >= p.idle_s:
                window = np.asarray(frames)[np.asarray(recv) >= t0 + p.idle_s - p.tare_s]
                tare_counts = preprocess.tare(window)
                phase = "closing"
            elif phase == "closing" and tare_counts is not None:
                level = float(preprocess.norm(preprocess.to_units(raw, tare_counts)))
                if level > p.x_th:
                    t_cross = t0 + t_recv
                    force_at_cross = force
                    t_stop = t_cross + p.reaction_latency_s
                    phase = "stopping"
            elif phase in ("stopping", "holding") and tare_counts is not None:
                level = float(preprocess.norm(preprocess.to_units(raw, tare_counts)))
                if level > p.abort_factor * p.x_th and not aborted:
                    aborted = True
                    phase, target = "opening", open_gap
        if phase == "stopping" and t0 + t >= t_stop:
            target = max(gap - p.squeeze_m, 0.0)
            phase = "holding"
        elif phase == "holding" and t0 + t >= t_stop + p.dt_stopping_s:
            phase, target = "opening", open_gap
        if phase == "closing" and gap <= 0.0:
            # Fully closed without crossing x_th: no contact; open and finish.
            phase, target = "opening", open_gap
            t_end = t + 0.2
        if t_stop is not None and t_end == math.inf:
            t_end = t_stop - t0 + p.tail_s

    if tare_counts is None:
        raise RuntimeError("press ended before the tare was taken; idle_s is too short")
    crossed = t_stop is not None
    rec = Recording(
        frames=np.asarray(frames, dtype=np.uint16),
        recv_time=np.asarray(recv),
        sensor_time=np.asarray(sens),
        seq=np.asarray(seqs, dtype=np.int64),
        tare=tare_counts,
        t_stop=t_stop if crossed else t0 + t,
        label=cls.name,
        threshold=p.x_th,
        sensor_model=SENSOR_MODEL,
        gripper_time=np.asarray(g_t),
        gripper_width_m=np.asarray(g_w),
        gripper_current_ma=np.asarray(g_i),
        source="sim",
        extra={
            "contact": crossed,
            "t_contact": t_contact,
            "t_cross": t_cross,
            "reaction_latency_s": p.reaction_latency_s,
            "peak_force_n": peak,
            "force_at_cross_n": force_at_cross,
            "aborted": aborted,
            "width_m": inst.width_m,
        },
    )
    return PressResult(rec, crossed, t_contact, t_cross, t_stop, force_at_cross, peak, aborted)
