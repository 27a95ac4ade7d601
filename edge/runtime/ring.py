"""The ring buffer of raw tactile frames with their times: written by the sensor task, read by
the press (its crop), the sampler and the services beside the press (:mod:`edge.runtime.taps`).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Window:
    """A copy of the frames received in a time interval."""

    raw: np.ndarray  # (N, C) uint16
    recv_time: np.ndarray  # (N,)
    sensor_time: np.ndarray  # (N,)
    seq: np.ndarray  # (N,)


class FrameRing:
    """Preallocated ring of raw frames with their times; single writer (the sensor task)."""

    def __init__(self, channels: int, capacity: int) -> None:
        self.capacity = capacity
        self.raw = np.zeros((capacity, channels), dtype=np.uint16)
        self.recv_time = np.full(capacity, -np.inf)
        self.sensor_time = np.zeros(capacity)
        self.seq = np.zeros(capacity, dtype=np.int64)
        self.count = 0  # frames ever written
        # (time, future) of whoever waits for a frame received at or after that time.
        self._waiters: list[tuple[float, asyncio.Future[None]]] = []

    def push(self, raw: np.ndarray, recv_time: float, sensor_time: float, seq: int) -> None:
        i = self.count % self.capacity
        self.raw[i] = raw
        self.recv_time[i] = recv_time
        self.sensor_time[i] = sensor_time
        self.seq[i] = seq
        self.count += 1
        if self._waiters:
            self._wake(recv_time)

    def _wake(self, recv_time: float) -> None:
        # (Each waiter takes its own entry out when it resumes: nothing allocated here.)
        for t, future in self._waiters:
            if recv_time >= t and not future.done():
                future.set_result(None)

    async def wait_until(self, t: float, timeout_s: float) -> bool:
        """Until a frame received at or after ``t`` is in the ring (True) or ``timeout_s``
        has passed (False). Woken by the frame's push, not by polling: the press hands its
        window over the moment the frame that completes it arrives."""
        if self.latest_time() >= t:
            return True
        future = asyncio.get_running_loop().create_future()
        self._waiters.append((t, future))
        try:
            await asyncio.wait_for(future, timeout_s)
        except TimeoutError:
            return self.latest_time() >= t
        finally:
            self._waiters = [(w, f) for w, f in self._waiters if f is not future]
        return True

    @property
    def latest_index(self) -> int:
        return (self.count - 1) % self.capacity if self.count else -1

    def latest_time(self) -> float:
        return float(self.recv_time[self.latest_index]) if self.count else -np.inf

    def window(self, t_from: float, t_to: float) -> Window:
        """Frames with ``t_from <= recv_time <= t_to``, oldest first."""
        n = min(self.count, self.capacity)
        start = self.count - n
        order = (np.arange(start, self.count) % self.capacity)
        times = self.recv_time[order]
        keep = order[(times >= t_from) & (times <= t_to)]
        return Window(self.raw[keep].copy(), self.recv_time[keep].copy(),
                      self.sensor_time[keep].copy(), self.seq[keep].copy())

    def oldest_time(self) -> float:
        if self.count == 0:
            return np.inf
        return float(self.recv_time[(self.count - min(self.count, self.capacity))
                                    % self.capacity])
