"""The sensor path: the task that feeds every tactile frame to the ring buffer
(:mod:`edge.runtime.ring`) and the press controller, and the 125 Hz sampler.

Every arriving frame is written, with its receive time and sequence number, into a
preallocated ring (no allocation on the per-frame path). The crop around ``t_stop`` is cut
from these timestamped frames on an ideal 8 ms grid (:mod:`edge.core.preprocess`), so a late
wake-up of the sampler never shifts the data.

The sampler runs on an absolute 125 Hz deadline grid and watches the stream's health: it
counts ticks without a new frame (gaps), frames that arrived between ticks beyond the first
(several per tick), and its own lateness, which is what the benchmark reports as the period
error. The data itself needs no second copy: the crop resamples the frame ring.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from edge.core.errors import SensorError, SensorLayoutError, StaleSensorError
from edge.hw.contracts import TactileFrame, TactileSource
from edge.runtime.ring import FrameRing

if TYPE_CHECKING:
    from edge.runtime.press import PressController

log = logging.getLogger(__name__)

# After the stream failed: how long before connecting again.
SENSOR_RETRY_S = 0.2


@dataclass
class SamplerStats:
    ticks: int = 0
    gaps: int = 0  # ticks with no new frame since the previous tick
    extra_frames: int = 0  # frames beyond one per tick (they are kept in the frame ring)
    missed_ticks: int = 0  # deadlines skipped because the loop was too late
    max_late_s: float = 0.0


class Sampler:
    """Samples the latest frame at a fixed rate on an absolute deadline grid."""

    def __init__(self, ring: FrameRing, rate_hz: float = 125.0) -> None:
        self.ring = ring
        self.period_s = 1.0 / rate_hz
        self.stats = SamplerStats()
        self._frames_at_last_tick: int | None = None
        # Called after each tick with (its monotonic time, its lateness in s): a
        # benchmark's probe; None in production, where the tick allocates nothing.
        self.on_tick: Callable[[float, float], None] | None = None

    def sample(self, now: float) -> None:
        """One tick at monotonic time ``now``."""
        st = self.stats
        frames = self.ring.count
        prev = self._frames_at_last_tick
        new = frames - (max(frames - 1, 0) if prev is None else prev)
        if new <= 0:
            st.gaps += 1
        elif new > 1:
            st.extra_frames += new - 1
        self._frames_at_last_tick = frames
        st.ticks += 1

    async def run(self) -> None:
        """Tick until cancelled. Sleeps to each absolute deadline; never drifts."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.period_s
        while True:
            await asyncio.sleep(max(0.0, deadline - loop.time()))
            now = loop.time()
            late = now - deadline
            if late > self.period_s:
                # The loop was blocked for more than a period: skip ahead, count the misses.
                skipped = int(late // self.period_s)
                self.stats.missed_ticks += skipped
                deadline += skipped * self.period_s
                late -= skipped * self.period_s
            self.stats.max_late_s = max(self.stats.max_late_s, late)
            now = time.monotonic()
            self.sample(now)
            if self.on_tick is not None:
                self.on_tick(now, late)
            deadline += self.period_s


class SensorTask:
    """Feeds every frame of a :class:`TactileSource` into the ring and to the press
    controller, which checks the threshold on it (and sends the stop) before the next frame
    is read; reconnects after a failure and tells the controller while the stream is stale.

    A source that runs the per-frame hook in its own task before queueing a frame
    (:meth:`TactileSource.set_frame_hook`: the XELA client) gets the threshold check there:
    the stop leaves without the frame's hop through the source's queue to this task. Other
    sources (fakes, replays) are checked here.
    """

    def __init__(self, source: TactileSource, ring: FrameRing, controller: PressController,
                 on_unusable: Callable[[str], None] | None = None) -> None:
        self.source = source
        self.ring = ring
        self.controller = controller
        self.on_unusable = on_unusable or (lambda why: None)
        self.frames = 0
        self.stale_events = 0
        # A layout the configuration does not match: reconnecting gives the same one, so
        # the task reports it once and reads no more.
        self.fatal: SensorLayoutError | None = None

    async def run(self) -> None:
        """Until cancelled: a bug or a dead stream on the sensor path must not take the
        daemon (and the arm) down."""
        inline = self.source.set_frame_hook(self._check)
        try:
            await self._run(inline)
        finally:
            if inline:
                self.source.set_frame_hook(None)

    async def _check(self, frame: TactileFrame) -> None:
        """The threshold check on the source's own task (see the class docstring)."""
        controller = self.controller
        try:
            await controller.check(frame.raw, frame.recv_time)
        except Exception as exc:
            log.exception("threshold check failed on frame %d", frame.seq)
            controller.sensor_stale(exc)

    async def _run(self, inline: bool) -> None:
        while True:
            try:
                async for frame in self.source.frames():
                    self.ring.push(frame.raw, frame.recv_time, frame.sensor_time, frame.seq)
                    self.frames += 1
                    controller = self.controller
                    if not inline:
                        await controller.check(frame.raw, frame.recv_time)
                    if controller.sensor_is_stale:
                        controller.sensor_fresh()
                        log.debug("tactile stream fresh again")
            except StaleSensorError as exc:
                # The source has said so (the XELA client, at most once a minute with a count
                # of the spells between): a warning here too would repeat every spell.
                if not self.controller.sensor_is_stale:
                    log.debug("%s", exc)
                self.stale_events += 1
                self.controller.sensor_stale(exc)
            except SensorLayoutError as exc:
                log.error("tactile sensor unusable until the configuration or xela_server is "
                          "fixed and the daemon restarted: %s", exc)
                self.fatal = exc
                self.controller.sensor_stale(exc)
                self.on_unusable(f"sensor error: {exc}")
                return
            except SensorError as exc:
                # A broken stream: no pressing on it; keep serving the API and say why.
                log.error("tactile sensor unusable: %s", exc)
                self.controller.sensor_stale(exc)
                self.on_unusable(f"sensor error: {exc}")
            except Exception as exc:
                log.exception("sensor task error")
                self.controller.sensor_stale(exc)
            await asyncio.sleep(SENSOR_RETRY_S)
