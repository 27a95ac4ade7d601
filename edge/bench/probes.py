"""What the bench reads from the running daemon, through its public hooks only: every packet
the bus thread writes (the bus's ``on_write``), when each frame was parsed (the XELA client's
``on_parsed``), each stop's timing (the bus's ``last_stop``), every sampler tick
(``Sampler.on_tick`` and its ``stats``), and the frame ring (``Runtime.ring``) for the first
frame over ``x_th``."""

from __future__ import annotations

import collections
import time
from dataclasses import asdict, dataclass
from typing import Any, ClassVar

import numpy as np

from edge.core import preprocess
from edge.runtime.domain import PressState
from edge.runtime.press import PressOutcome

# Frames whose parse time is kept (about 2 minutes at 125 Hz).
PARSE_TIMES = 1 << 14


def first_crossing(ring: Any, outcome: PressOutcome,
                   x_th: float) -> tuple[float, int, float] | None:
    """Receive time, sequence number and sensor time (the server's wall clock) of the first
    frame over ``x_th`` after closing began (the controller's own norm), up to the stop."""
    closing = outcome.summary().entered(PressState.CLOSING)
    if outcome.tare is None or outcome.t_stop is None or closing is None:
        return None
    win = ring.window(closing - 0.05, outcome.t_stop)
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
    hook)."""
    writes: collections.deque[tuple[float, bytes]] = collections.deque(maxlen=8192)
    bus.on_write = lambda t, head: writes.append((t, head))
    return writes


class ParseTimes:
    """When each frame was parsed, by sequence number (the XELA client's ``on_parsed``)."""

    def __init__(self, capacity: int = PARSE_TIMES) -> None:
        self.seq = np.full(capacity, -1, dtype=np.int64)
        self.t = np.zeros(capacity)

    def record(self, seq: int, recv_time: float, t_parsed: float) -> None:
        i = seq % len(self.seq)
        self.seq[i], self.t[i] = seq, t_parsed

    def get(self, seq: int) -> float | None:
        i = seq % len(self.seq)
        return float(self.t[i]) if self.seq[i] == seq else None


def instrument_parse(tactile: Any) -> ParseTimes:
    times = ParseTimes()
    tactile.on_parsed = times.record
    return times


@dataclass(frozen=True)
class StopParts:
    """One production stop, frame received -> stop packet written, in its parts (ms):
    ``parse`` (the frame's JSON into counts, in the XELA client), ``queue`` (to the sensor
    task), ``check`` (the norm, the threshold, down to the hand-over), ``handover`` (to the
    bus thread running the stop), ``in_flight`` (the rest of a transaction already on the
    wire), ``write`` (the goal and its packet, to the write call). They add up to the stop
    latency. ``write_return`` follows it: the write call returning to the bus thread (the
    system call, and any wait for a CPU or the GIL after it)."""

    NAMES: ClassVar[tuple[str, ...]] = ("parse", "queue", "check", "handover", "in_flight",
                                        "write", "write_return")
    parse: float | None
    queue: float | None
    check: float
    handover: float
    in_flight: float
    write: float
    write_return: float


def stop_parts(stop: Any, t_recv: float, t_check: float, t_parsed: float | None) -> StopParts:
    """The parts of ``stop`` (the bus's ``StopRecord``) for the frame received at ``t_recv``
    whose check began at ``t_check``."""
    ms = 1e3
    return StopParts(
        parse=None if t_parsed is None else ms * (t_parsed - t_recv),
        queue=None if t_parsed is None else ms * (t_check - t_parsed),
        check=ms * (stop.t_submit - t_check),
        handover=ms * (stop.t_start - stop.t_submit - stop.in_flight_s),
        in_flight=ms * stop.in_flight_s,
        write=ms * (stop.t_write_call - stop.t_start),
        write_return=ms * (stop.t_written - stop.t_write_call))


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


# Protocol 2.0: the instruction byte of a packet's first 8 bytes (the bus's ``on_write``).
_INSTRUCTION = 7
_WRITE = 0x03


class HotPathCPU:
    """The thread CPU time (``time.thread_time_ns``: what a thread ran, not how long it
    waited for a core, so another process's load does not inflate it) the production hot
    path costs, through the runtime's hooks:

    - per frame checked while the threshold is armed (closing, holding), on the loop
      thread, from the XELA client's ``on_received`` (the message handed over by the
      WebSocket) to the end of the controller's threshold check, for the frames whose check
      sent no stop;
    - per stop: the loop thread from that frame's arrival to the stop's hand-over (the
      controller's ``gripper.stop_now``), plus the bus thread from there to its stop packet's
      write call returning (the bus's ``on_write``, read on the bus thread; the bus thread's
      CPU clock read from the loop at the hand-over). ``in_flight`` stops, whose bus thread
      was still finishing another transaction at the hand-over, count that remainder too.

    Only the production controller's stops (checked on the frame) are recorded; each
    sample carries its monotonic time, for the phase windows.
    """

    def __init__(self, bus: Any) -> None:
        self.bus = bus
        self.frames: list[tuple[float, float]] = []  # (time, loop µs)
        self.stops: list[dict[str, Any]] = []  # time, loop_us, bus_us, in_flight
        self._arrived: int | None = None
        self._handover: tuple[int, int] | None = None  # (loop ns, bus thread's clock)
        self._stop_written: int | None = None  # the bus thread's CPU at the stop's write
        previous = bus.on_write

        def written(t: float, head: bytes) -> None:
            if previous is not None:
                previous(t, head)
            self._written(head)

        bus.on_write = written

    def arrived(self) -> None:
        self._arrived = time.thread_time_ns()
        self._handover = self._stop_written = None

    def handover(self) -> None:
        if self._arrived is None:  # a ticked controller's stop: no frame's path
            return
        loop_ns = time.thread_time_ns() - self._arrived
        bus = self.bus.thread_id
        self._handover = (loop_ns, time.clock_gettime_ns(time.pthread_getcpuclockid(bus)))

    def _written(self, head: bytes) -> None:
        # On the bus thread: the first WRITE after the hand-over is the stop's Goal Position
        # (a stop without a fresh state reads Present Position first).
        if (self._handover is not None and self._stop_written is None
                and len(head) > _INSTRUCTION and head[_INSTRUCTION] == _WRITE):
            self._stop_written = time.thread_time_ns()

    def checked(self, armed: bool) -> None:
        """The controller's check of the frame ended (on the loop thread); ``armed``: the
        threshold was watched when it began."""
        if self._arrived is None:
            return
        now = time.monotonic()
        if self._handover is None and armed:
            self.frames.append((now, (time.thread_time_ns() - self._arrived) / 1e3))
        elif self._stop_written is not None:
            loop_ns, bus_at_handover = self._handover
            stop = self.bus.last_stop
            self.stops.append({"t": now, "loop_us": loop_ns / 1e3,
                               "bus_us": (self._stop_written - bus_at_handover) / 1e3,
                               "in_flight": bool(stop and stop.in_flight_s > 0)})
        self._arrived = self._handover = self._stop_written = None
