"""The operator page's live view of both pads: the latest tactile frame, tared, at 30 Hz.

One producer task per daemon, running while at least one viewer is connected: every
1/30 s it reads the newest row of the ring buffer (:mod:`edge.runtime.taps`; the 125 Hz
path is never touched), converts it to tactile units against its own tare, encodes it once
and hands the same bytes to every viewer. A viewer that reads slowly gets the latest frame,
not a backlog (one slot per viewer, overwritten).

The tare is the mean of the newest 0.3 s when the feed starts, again each time a press
enters ``closing`` (the newest rows are then the press's own unloaded tare window) and when
it is back to ``idle`` (the arm above the object, the gripper open), and on request
(``POST /v1/tactile/tare``). Values are sent in micro-units (tactile units x 1e6,
integers) per pad and axis: ``x``/``y`` shear and ``z`` normal load of taxels 0..15.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import AsyncIterator

import numpy as np

from edge.core import preprocess
from edge.core.layout import PadLayout
from edge.core.tasks import cancel_and_wait
from edge.runtime.domain import Hello, PressState, StateChanged
from edge.runtime.taps import LiveTaps

log = logging.getLogger(__name__)

RATE_HZ = 30.0
# Without a new row, the frame is sent again this often (the page shows its age).
HEARTBEAT_S = 0.5
TARE_S = 0.3
SENSOR_RATE_HZ = 125.0


class TactileFeed:
    def __init__(self, taps: LiveTaps, rate_hz: float = RATE_HZ) -> None:
        self.taps = taps
        self.period_s = 1.0 / rate_hz
        self._viewers: set[asyncio.Queue[bytes]] = set()
        self._task: asyncio.Task | None = None
        self._tare: np.ndarray | None = None
        self._state = PressState.IDLE
        self._closed = False
        self.frames_sent = 0

    def tare(self, seconds: float = TARE_S) -> bool:
        """Tare on the newest ``seconds`` of frames; False if there are none."""
        rows = self.taps.rows_since(0, max(1, round(seconds * SENSOR_RATE_HZ)))
        if not len(rows):
            return False
        self._tare = preprocess.tare(rows.raw)
        return True

    async def frames(self) -> AsyncIterator[bytes]:
        """Encoded frames for one viewer, until it goes away or :meth:`close`."""
        if self._closed:
            return
        slot: asyncio.Queue[bytes] = asyncio.Queue(1)
        self._viewers.add(slot)
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._produce(), name="tactile-feed")
        try:
            while payload := await slot.get():
                yield payload
        finally:
            self._viewers.discard(slot)
            if not self._viewers and self._task is not None:
                self._task.cancel()
                self._task = None

    def close(self) -> None:
        """The server stops: every viewer's stream ends (an empty payload ends it)."""
        self._closed = True
        for slot in self._viewers:
            if slot.full():
                slot.get_nowait()
            slot.put_nowait(b"")
        if self._task is not None:
            self._task.cancel()
            self._task = None

    async def _produce(self) -> None:
        events = asyncio.create_task(self._follow_states(), name="tactile-feed-states")
        loop = asyncio.get_running_loop()
        try:
            if self._tare is None:
                self.tare()
            deadline = loop.time()
            last_seq, last_sent = None, 0.0
            while True:
                now = loop.time()
                seq = self.taps.frame_count
                # A frame per new row (a stalled stream is not sent again and again, but a
                # heartbeat still says how old its last frame is).
                if seq != last_seq or now - last_sent >= HEARTBEAT_S:
                    payload = self._encode()
                    if payload is not None:
                        last_seq, last_sent = seq, now
                        self.frames_sent += 1
                        for slot in self._viewers:
                            if slot.full():
                                slot.get_nowait()  # a viewer behind gets only the latest
                            slot.put_nowait(payload)
                deadline += self.period_s
                now = loop.time()
                if deadline < now:  # the loop was late: back on the grid, no burst
                    deadline += math.ceil((now - deadline) / self.period_s) * self.period_s
                await asyncio.sleep(deadline - now)
        finally:
            await cancel_and_wait(events)

    def _encode(self) -> bytes | None:
        rows = self.taps.rows_since(0, 1)
        if not len(rows):
            return None
        if self._tare is None and not self.tare():
            return None
        assert self._tare is not None
        units = (rows.raw[0].astype(np.float64) - self._tare) / preprocess.UNITS_SCALE
        norm = float(np.linalg.norm(units))
        sensor = self.taps.sensor_settings()
        layout = PadLayout.of(sensor)
        pads = (units * 1e6).round().astype(np.int64).reshape(sensor.pads, -1, 3)
        return json.dumps({
            "seq": int(rows.seq[0]),
            "age_s": round(time.monotonic() - float(rows.recv_time[0]), 4),
            "state": self._state, "norm": round(norm, 7),
            "x_th": self.taps.press_settings().x_th,
            "rows": layout.rows, "cols": layout.cols,
            "pads": [{"x": p[:, 0].tolist(), "y": p[:, 1].tolist(), "z": p[:, 2].tolist()}
                     for p in pads],
        }, separators=(",", ":")).encode()

    async def _follow_states(self) -> None:
        with self.taps.subscribe() as stream:
            async for event in stream:
                if isinstance(event, Hello | StateChanged):
                    self._state = event.state
                    if self._state == PressState.CLOSING:  # the press's own tare window
                        self.tare(self.taps.press_settings().tare_s)
                    elif self._state == PressState.IDLE and isinstance(event, StateChanged):
                        self.tare()  # back above the object, the gripper open: unloaded
