"""Read-only taps on the tactile ring buffer for the services beside the press: the live
MCAP recording and the operator page's live view.

They never touch the 125 Hz path: the sensor task keeps writing the ring; a tap copies the
rows written since its last look (or the newest few) when it wakes up, on the event loop,
where the ring's single writer also runs (no lock, no torn row). A tap that falls more than
the ring's length behind loses the oldest rows and says how many.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from edge.core.config import PressConfig, SensorConfig
from edge.runtime.events import Subscription
from edge.runtime.ring import FrameRing


@dataclass(frozen=True)
class Rows:
    """Copies of consecutive ring rows, oldest first."""

    count: int  # the ring's frame count after these rows: pass it as ``after`` next time
    raw: np.ndarray  # (n, C) uint16
    recv_time: np.ndarray  # (n,) monotonic seconds
    sensor_time: np.ndarray  # (n,) the sensor server's clock
    seq: np.ndarray  # (n,)
    lost: int = 0  # rows overwritten before this tap read them

    def __len__(self) -> int:
        return int(self.raw.shape[0])


def rows_since(ring: FrameRing, after: int, limit: int | None = None) -> Rows:
    """Rows written after the ring's ``after``-th frame (at most the newest ``limit``)."""
    count = ring.count
    first = max(after, count - ring.capacity, 0)
    lost = max(0, first - after) if after > 0 else 0
    if limit is not None and count - first > limit:
        first = count - limit
    idx = np.arange(first, count) % ring.capacity
    return Rows(count, ring.raw[idx], ring.recv_time[idx], ring.sensor_time[idx],
                ring.seq[idx], lost)


def newest(ring: FrameRing, n: int) -> Rows:
    """The newest ``n`` rows (fewer if the ring holds fewer)."""
    return rows_since(ring, 0, n)


class LiveTaps(Protocol):
    """What the services beside the press read live (the API's events, the operator page's
    live view, the live recording, MQTT): the daemon's events and the ring's taps."""

    def subscribe(self) -> AbstractContextManager[Subscription]:
        """The events from now on, the first a :class:`~edge.runtime.domain.Hello`."""
        ...

    @property
    def frame_count(self) -> int:
        """Frames the ring has taken so far (``after`` for :meth:`rows_since`)."""
        ...

    def rows_since(self, after: int, limit: int | None = None) -> Rows:
        """:func:`rows_since` on the daemon's ring."""
        ...

    def sensor_settings(self) -> SensorConfig:
        """The ``[sensor]`` the stream was opened with (how its rows split into pads)."""
        ...

    def press_settings(self) -> PressConfig:
        """The ``[press]`` settings in force (a reload may replace them)."""
        ...
