"""What the bench reads from the running daemon, through its public hooks only: every packet
the bus thread writes (the bus's ``on_write``), every sampler tick (``Sampler.on_tick`` and
its ``stats``), and the frame ring (``Runtime.ring``) for the first frame over ``x_th``."""

from __future__ import annotations

import collections
import time
from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

import numpy as np

from edge.core import preprocess
from edge.daemon.press import PressOutcome

READ_INSTRUCTION = 0x02


def first_crossing(ring: Any, outcome: PressOutcome,
                   x_th: float) -> tuple[float, int, float] | None:
    """Receive time, sequence number and sensor time (the server's wall clock) of the first
    frame over ``x_th`` after closing began (the controller's own norm), up to the stop."""
    states = dict(outcome.states)
    if outcome.tare is None or outcome.t_stop is None or "closing" not in states:
        return None
    win = ring.window(states["closing"] - 0.05, outcome.t_stop)
    if len(win.raw) == 0:
        return None
    level = np.linalg.norm(win.raw - outcome.tare, axis=1) / preprocess.UNITS_SCALE
    over = np.flatnonzero(level > x_th)
    if over.size == 0:
        return None
    i = int(over[0])
    return float(win.recv_time[i]), int(win.seq[i]), float(win.sensor_time[i])


def instrument_port(bus: Any) -> collections.deque[tuple[float, bytes]]:
    """The time and header of every packet the bus thread writes (the bus's ``on_write``
    hook).

    The stop is READ Present Position, then WRITE Goal Position (its write time is the stop
    latency's end); the READ's write time splits the latency into the software part (loop,
    hand-off to the bus thread, a transaction already on the wire) and the bus round trip.
    """
    writes: collections.deque[tuple[float, bytes]] = collections.deque(maxlen=8192)
    bus.on_write = lambda t, head: writes.append((t, head))
    return writes


def stop_read_time(writes: Sequence[tuple[float, bytes]], t_stop: float,
                   motor_id: int) -> float | None:
    """Write time of the last READ to ``motor_id`` before the stop's WRITE at ``t_stop``."""
    for t, head in reversed(list(writes)):
        if t < t_stop and len(head) >= 8 and head[4] == motor_id \
                and head[7] == READ_INSTRUCTION:
            return t
    return None


class SamplerWindow:
    """Records the runtime sampler from now until :meth:`close`: each wake-up's lateness
    (the sampler's own bench switch) and the time between samples (a stall shows whole,
    where the lateness is taken modulo the period after missed ticks)."""

    def __init__(self, sampler: Any) -> None:
        self.sampler = sampler
        self.before = asdict(sampler.stats)
        self.t0 = time.monotonic()
        self.intervals: list[float] = []
        self.lateness: list[float] = []
        last = [time.monotonic()]

        def on_tick(now: float, late: float) -> None:
            self.intervals.append(now - last[0])
            self.lateness.append(late)
            last[0] = now

        sampler.on_tick = on_tick

    def close(self) -> dict[str, Any]:
        sampler = self.sampler
        sampler.on_tick = None
        lateness = self.lateness
        after = asdict(sampler.stats)
        gaps = self.intervals[1:]
        return {
            "window_s": time.monotonic() - self.t0, "lateness_s": lateness,
            **{k: after[k] - self.before[k] for k in ("ticks", "missed_ticks", "gaps",
                                                      "extra_frames")},
            "max_interval_ms": 1e3 * max(gaps, default=0.0),
            "intervals_over_16ms": sum(v > 0.016 for v in gaps),
        }
