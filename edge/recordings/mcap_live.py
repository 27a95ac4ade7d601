"""Live MCAP recording of the daemon: the tactile stream and every event, to segment files.

On with ``[runtime] record_mcap_dir``. The task ``mcap-record`` wakes every
``FLUSH_PERIOD_S``, copies the tactile rows written since its last look from the ring
buffer (:mod:`edge.runtime.taps`; the 125 Hz path is never touched) and the events it got
from the runtime's event stream, and hands them to a writer process of its own (a
:class:`~edge.runtime.compute.ComputeWorker`: JSON encoding and zstd compression of 125
frames/s must not compete with the loop for the GIL). The loop pays the pickling of a few
kB per wake-up. While the writer is busy (a slow disk) rows wait in the ring; a writer more
than the ring's length (45 s) behind loses the oldest and the segment's metadata counts them.

Each segment (``vtzero-YYYYmmddTHHMMSSZ.mcap``, one per ``record_mcap_segment_s``) is written
to ``.NAME.tmp`` and renamed when complete, so a complete ``.mcap`` is always a whole file; a
``.tmp`` left by a crash holds the chunks written so far (``mcap recover`` repairs it).
Topics and clock: :mod:`edge.recordings.mcaplog` (``/tactile/raw``, ``/press/state``,
``/events``). With ``[runtime] record_format = "rosbag2"`` each segment is a rosbag2 bag
directory instead (:mod:`edge.recordings.rosbag`: ``/xServTopic``, ``/press/state``,
``/events``; wall-clock stamps), staged beside its name and renamed when complete.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from edge.core.errors import EdgeError
from edge.core.tasks import cancel_and_wait
from edge.recordings.mcaplog import LIVE_TOPICS, SUFFIX, McapLog
from edge.runtime.taps import LiveTaps, Rows

log = logging.getLogger(__name__)

# How often the recorder hands what arrived to its writer.
FLUSH_PERIOD_S = 0.25
# Events kept for the writer between two flushes (a burst past this loses the oldest).
EVENT_BACKLOG = 1000
# After a failed segment (the writer died, the disk refused), a new one is tried this late.
RETRY_S = 1.0
# Closing the open segment at shutdown.
CLOSE_TIMEOUT_S = 10.0
# Smaller chunks than the default 1 MiB: a crash loses less of the open segment.
CHUNK_BYTES = 256 * 1024


@dataclass
class Batch:
    """What arrived since the last flush (pickled to the writer process)."""

    rows: Rows
    # (monotonic time, the event's JSON form), as they arrived
    events: list[tuple[float, dict[str, Any]]] = field(default_factory=list)
    pads: int = 2  # [sensor] pads: how the rows' channels split
    lost: int = 0  # frames before these that no segment holds (overwritten or abandoned)


def segment_name(now: float | None = None, fmt: str = "mcap") -> str:
    """An MCAP file's name, or a rosbag2 bag directory's (no suffix)."""
    ts = datetime.fromtimestamp(now if now is not None else time.time(), UTC)
    return f"vtzero-{ts:%Y%m%dT%H%M%S}Z{SUFFIX if fmt == 'mcap' else ''}"


class McapRecorder:
    """The ``mcap-record`` task: ``await McapRecorder(taps, directory).run()``."""

    def __init__(self, taps: LiveTaps, directory: str | Path, segment_s: float = 600.0,
                 worker: Any = None, *, record_format: str = "mcap") -> None:
        self.taps = taps
        self.directory = Path(directory)
        self.segment_s = segment_s
        self.record_format = record_format
        self._worker = worker
        self._events: collections.deque[tuple[float, dict[str, Any]]] = collections.deque(
            maxlen=EVENT_BACKLOG)
        self.files: list[Path] = []  # segments completed
        self.lost = 0  # frames no segment holds (the sum of the batches' lost)
        self._after = 0
        self._in_segment = 0  # frames the open segment holds
        self._unwritten = 0  # frames lost since the last batch sent, not counted in one yet
        # The batch handed to the writer and not yet answered, with its row count: a
        # shutdown waits for it rather than cutting it off (cancelled before the writer
        # began it, its rows would be in no segment and counted nowhere).
        self._appending: tuple[asyncio.Future[None], int] | None = None

    async def run(self) -> None:
        from edge.runtime.compute import ComputeWorker

        # From the first frame and event on: the writer starting below takes a moment, and a
        # press may begin meanwhile.
        self._after = self.taps.frame_count
        pump = asyncio.create_task(self._pump(), name="mcap-record-events")
        own = self._worker is None
        worker = self._worker or ComputeWorker()
        # True from the moment the writer is asked to open a segment: a cancellation that
        # interrupts the opening (the writer finishes a call it has begun) still closes it.
        opened = False
        try:
            await asyncio.to_thread(self.directory.mkdir, parents=True, exist_ok=True)
            if own:
                await worker.start()
            while True:
                batch: Batch | None = None
                try:
                    if not opened:
                        opened = True
                        await worker.run(segment_open, str(self.directory),
                                         segment_name(fmt=self.record_format),
                                         self.record_format,
                                         self.taps.sensor_settings().model)
                        started = time.monotonic()
                        log.info("recording the live stream to %s", self.directory)
                    await asyncio.sleep(FLUSH_PERIOD_S)
                    batch = self._batch()
                    appending = asyncio.ensure_future(worker.run(segment_append, batch))
                    self._appending = (appending, len(batch.rows))
                    await asyncio.shield(appending)
                    self._appending = None
                    self._in_segment += len(batch.rows)
                    if time.monotonic() - started >= self.segment_s:
                        opened = False
                        self._done(await worker.run(segment_close))
                except EdgeError as exc:  # the writer died (ComputeError) or the disk failed
                    self._appending = None
                    log.error("live MCAP recording: %s; a new segment in %.0f s", exc,
                              RETRY_S)
                    opened = False
                    # The abandoned segment's frames and the batch it refused are counted
                    # in the next segment's frames_lost, not silently dropped.
                    self._unwritten += self._in_segment + (len(batch.rows) if batch else 0)
                    self._in_segment = 0
                    with contextlib.suppress(EdgeError):
                        await worker.run(segment_abandon)
                    await asyncio.sleep(RETRY_S)
        finally:
            await cancel_and_wait(pump)
            if opened:
                closing = asyncio.ensure_future(self._close(worker))
                try:
                    await asyncio.wait_for(asyncio.shield(closing), CLOSE_TIMEOUT_S)
                except (TimeoutError, EdgeError, asyncio.CancelledError) as exc:
                    log.error("live MCAP recording: the last segment was not closed: %r", exc)
            if own:
                await worker.stop()

    def _batch(self) -> Batch:
        """The rows and events that arrived since the last batch."""
        rows = self.taps.rows_since(self._after)
        self._after = rows.count
        lost, self._unwritten = rows.lost + self._unwritten, 0
        self.lost += lost
        events = list(self._events)
        self._events.clear()
        return Batch(rows, events, self.taps.sensor_settings().pads, lost)

    async def _close(self, worker: Any) -> None:
        """The batch still being appended, what arrived since, then the segment completed."""
        if self._appending is not None:
            (appending, rows), self._appending = self._appending, None
            try:
                await appending
                self._in_segment += rows
            except EdgeError as exc:
                log.error("live MCAP recording: the last batch was not written: %s", exc)
                self._unwritten += rows
        self._done(await worker.run(segment_finish, self._batch()))

    def _done(self, path: str | None) -> None:
        self._in_segment = 0
        if path:
            self.files.append(Path(path))
            log.info("live MCAP segment complete: %s", path)

    async def _pump(self) -> None:
        with self.taps.subscribe() as stream:
            async for event in stream:
                self._events.append((time.monotonic(), event.to_json()))


# --------------------------------------------------------------------------------------
# In the writer process


class _Segment:
    def __init__(self, directory: str, name: str, fmt: str, sensor_model: str) -> None:
        if fmt == "rosbag2":
            from edge.recordings.rosbag import LIVE_TOPICS as BAG_TOPICS
            from edge.recordings.rosbag import RosbagLog, live_offset

            self.log = RosbagLog(Path(directory) / name, BAG_TOPICS, offset_s=live_offset(),
                                 sensor_model=sensor_model)
        else:
            self.log = McapLog(Path(directory) / name, LIVE_TOPICS, chunk_size=CHUNK_BYTES)
        self.lost = 0
        self.frames = 0

    def append(self, batch: Batch) -> None:
        rows = batch.rows
        self.lost += batch.lost
        self.frames += len(rows)
        if len(rows):
            self.log.tactile("/tactile/raw", rows.recv_time, rows.sensor_time, rows.seq,
                             np.asarray(rows.raw), batch.pads)
        for t, event in batch.events:
            if event.get("type") == "state":
                self.log.add("/press/state", t, {"state": str(event.get("state")),
                                                 "episode": event.get("episode")})
            self.log.add("/events", t, {k: v for k, v in event.items() if k != "timestamp"})

    def close(self) -> str:
        self.log.metadata("vtzero", {"clock": "monotonic (seconds since the robot booted)",
                                     "frames": self.frames, "frames_lost": self.lost})
        return str(self.log.finish())


_segment: _Segment | None = None


def segment_open(directory: str, name: str, fmt: str = "mcap", sensor_model: str = "") -> None:
    global _segment
    if _segment is not None:
        _segment.log.abandon()
        _segment = None
    try:
        _segment = _Segment(directory, name, fmt, sensor_model)
    except OSError as exc:
        raise EdgeError(f"live MCAP recording: cannot create a segment in {directory}: "
                        f"{exc}") from None


def segment_append(batch: Batch) -> None:
    if _segment is None:
        raise EdgeError("live MCAP recording: no segment is open")
    try:
        _segment.append(batch)
    except OSError as exc:
        raise EdgeError(f"live MCAP recording: cannot write {_segment.log.tmp}: {exc}") from None


def segment_finish(batch: Batch) -> str | None:
    """The last batch appended and the segment completed; None when none is open (its
    opening failed, or a rotation had just closed it)."""
    if _segment is None:
        return None
    try:
        segment_append(batch)
    finally:
        path = segment_close()
    return path


def segment_close() -> str | None:
    global _segment
    segment, _segment = _segment, None
    if segment is None:
        return None
    try:
        return segment.close()
    except OSError as exc:
        raise EdgeError(f"live MCAP recording: cannot complete {segment.log.path}: "
                        f"{exc}") from None


def segment_abandon() -> None:
    global _segment
    if _segment is not None:
        _segment.log.abandon()
        _segment = None
