"""The tactile contract: frames, the source protocol, stream counters and an in-memory fake.

A frame carries raw 16-bit counts in the project's channel order (``pad*48 + taxel*3 + axis``
for 4x4 pads; pads by sensor number, taxels row-major from the top left, axes x, y, z).
Converting to tactile units (``(raw - tare) / 65536``) is the consumer's job.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Iterable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Protocol, Self, runtime_checkable

import numpy as np

from edge.core.errors import StaleSensorError

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class TactileFrame:
    """One fresh update of all pads, as the source received it."""

    seq: int
    # The server's own clock (xela_server: Unix time; NaN if it sends none): only its
    # advance matters.
    sensor_time: float
    # time.monotonic() when the frame arrived: the timestamp the runtime places samples by.
    recv_time: float
    # (C,) uint16 raw counts, read-only.
    raw: np.ndarray
    # Model name per pad, in pad order.
    models: tuple[str, ...]

    def __post_init__(self) -> None:
        if self.raw.dtype != np.uint16 or self.raw.ndim != 1:
            raise ValueError(
                f"TactileFrame.raw must be a 1-D uint16 array, got {self.raw.dtype} "
                f"with shape {self.raw.shape}"
            )
        # Frames are shared between the sampler, threshold check and store: nobody may edit one.
        self.raw.flags.writeable = False


@dataclass
class StreamStats:
    """Counters of one tactile stream. ``observe`` decides whether a frame is new."""

    frames: int = 0  # fresh frames delivered
    repeats: int = 0  # frames whose seq or time did not advance (a frozen server)
    gaps: int = 0  # times the seq jumped forward by more than one
    lost: int = 0  # seq numbers missing in those jumps
    resets: int = 0  # times the seq went backwards (server restarted)
    skipped: int = 0  # undecodable frames dropped
    overruns: int = 0  # fresh frames dropped because the consumer fell behind
    reconnects: int = 0  # successful connections after the first
    _last_seq: int | None = field(default=None, repr=False)
    _last_time: float | None = field(default=None, repr=False)
    _new_link: bool = field(default=False, repr=False)

    def observe(self, seq: int, sensor_time: float) -> bool:
        """Count ``seq``/``sensor_time``; True when the frame is new data.

        A frame is new only when both the sequence number and the server time changed: a dead
        server that keeps resending its last frame must read as stale, not as "no contact".
        """
        last_seq, last_time = self._last_seq, self._last_time
        if self._new_link:
            # A restarted server may reuse a seq number: only the very same frame repeats.
            self._new_link = False
            repeat = seq == last_seq and sensor_time == last_time
        else:
            repeat = last_seq is not None and (seq == last_seq or sensor_time == last_time)
        if repeat:
            self.repeats += 1
            self._last_seq = seq
            return False
        if last_seq is not None:
            if seq > last_seq + 1:
                self.gaps += 1
                self.lost += seq - last_seq - 1
                log.debug("seq gap %d -> %d (%d lost)", last_seq, seq, seq - last_seq - 1)
            elif seq < last_seq:
                self.resets += 1
                log.debug("seq went back %d -> %d (server restarted?)", last_seq, seq)
        self._last_seq, self._last_time = seq, sensor_time
        self.frames += 1
        return True

    def new_connection(self) -> None:
        """Note a (re)connection: the next frame is judged against the last one leniently."""
        self._new_link = True


@runtime_checkable
class TactileSource(Protocol):
    """Anything that yields :class:`TactileFrame` s: the XELA client, a fake, a replay.

    ``frames()`` yields fresh frames to one consumer and raises
    :class:`~edge.core.errors.StaleSensorError` when no fresh frame arrived within the source's
    stale timeout; the source keeps running (and reconnecting), so call ``frames()`` again to
    resume. Iteration ends after ``close()``.
    """

    stats: StreamStats

    async def start(self) -> None: ...

    async def close(self) -> None: ...

    async def __aenter__(self) -> Self: ...

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...

    def frames(self) -> AsyncIterator[TactileFrame]: ...

    def is_fresh(self) -> bool: ...


_END = object()


class FakeTactileSource:
    """In-memory :class:`TactileSource` for tests.

    Either replays ``raw`` (shape (N, C)) at ``rate_hz`` on an absolute time grid (``None``:
    as fast as the consumer takes them; ``loop=True`` starts over), or, without ``raw``, yields
    what is fed with :meth:`put` until :meth:`finish`. With ``stale_timeout_s`` set,
    ``frames()`` raises StaleSensorError like the real client when nothing arrives in time.
    """

    def __init__(
        self,
        raw: np.ndarray | Iterable[np.ndarray] | None = None,
        *,
        rate_hz: float | None = 125.0,
        models: tuple[str, ...] = ("XR1944", "XR1944"),
        stale_timeout_s: float | None = None,
        loop: bool = False,
        start_seq: int = 1,
    ) -> None:
        self._rows = None if raw is None else [_as_raw(r) for r in raw]
        if rate_hz is not None and rate_hz <= 0:
            raise ValueError(f"rate_hz must be > 0 or None, got {rate_hz!r}")
        self._period_s = None if rate_hz is None else 1.0 / rate_hz
        self._models = tuple(models)
        self._stale_timeout_s = stale_timeout_s
        self._loop = loop
        self._seq = start_seq
        self._queue: asyncio.Queue[object] = asyncio.Queue()
        self._last_recv: float | None = None
        self._closed = False
        self.stats = StreamStats()

    async def start(self) -> None:
        pass

    async def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._queue.put_nowait(_END)

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    def put(
        self, raw: np.ndarray, *, seq: int | None = None, sensor_time: float | None = None
    ) -> None:
        """Feed one frame; ``seq``/``sensor_time`` default to the next number and now."""
        if seq is None:
            seq = self._seq
        self._seq = seq + 1
        if sensor_time is None:
            sensor_time = time.time()
        self._queue.put_nowait((seq, sensor_time, _as_raw(raw)))

    def fail(self, exc: BaseException) -> None:
        """Make the consumer's ``frames()`` raise ``exc`` after what is already queued."""
        self._queue.put_nowait(exc)

    def finish(self) -> None:
        """End iteration after what is already queued."""
        self._queue.put_nowait(_END)

    def is_fresh(self) -> bool:
        if self._closed or self._last_recv is None:
            return False
        if self._stale_timeout_s is None:
            return True
        return time.monotonic() - self._last_recv < self._stale_timeout_s

    async def frames(self) -> AsyncIterator[TactileFrame]:
        items = self._replay() if self._rows is not None else self._fed()
        async for seq, sensor_time, raw in items:
            if self._closed:
                return
            if not self.stats.observe(seq, sensor_time):
                continue
            self._last_recv = time.monotonic()
            yield TactileFrame(seq, sensor_time, self._last_recv, raw, self._models)

    async def _replay(self) -> AsyncIterator[tuple[int, float, np.ndarray]]:
        assert self._rows is not None
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        i = 0
        while self._rows and not self._closed:
            if self._period_s is not None:
                # Absolute grid: a late wake-up never shifts the following frames.
                await asyncio.sleep(max(0.0, t0 + i * self._period_s - loop.time()))
            # A made-up server clock that advances with seq, so no frame reads as a repeat.
            yield self._seq, self._seq * (self._period_s or 1e-3), self._rows[i % len(self._rows)]
            self._seq += 1
            i += 1
            if i >= len(self._rows) and not self._loop:
                return

    async def _fed(self) -> AsyncIterator[tuple[int, float, np.ndarray]]:
        while True:
            try:
                async with asyncio.timeout(self._stale_timeout_s):
                    item = await self._queue.get()
            except TimeoutError:
                raise StaleSensorError(
                    f"fake tactile source: no frame for {self._stale_timeout_s} s"
                ) from None
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item  # type: ignore[misc]


def _as_raw(row: np.ndarray) -> np.ndarray:
    arr = np.asarray(row)
    if arr.ndim != 1 or arr.dtype.kind not in "ui":
        raise ValueError(f"raw frame must be a 1-D integer array, got {arr.dtype} {arr.shape}")
    if arr.size and (arr.min() < 0 or arr.max() > 0xFFFF):
        raise ValueError("raw counts must be in 0..65535")
    return arr.astype(np.uint16)
