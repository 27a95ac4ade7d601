"""The press controllers the bench compares: the production one, which checks the threshold
on every arriving frame, and two that check it only on a periodic tick (the sampler's 125 Hz,
a 100 Hz control loop as in the usual ROS 2 arrangement).

The comparison controllers live here, not in production code. They are made by the runtime's
public factory (``Runtime.make_press_controller``) and use only the controller's public
hooks: ``on_outcome``, ``on_frame``, ``check`` and ``armed``.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

import numpy as np

from edge.daemon.press import PressController, PressOutcome


class RecordingController(PressController):
    """The production controller, unchanged; its ``on_outcome`` hook hands each outcome to
    the bench."""

    name = "per_frame"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.outcomes: asyncio.Queue[PressOutcome] = asyncio.Queue()
        super().__init__(*args, on_outcome=self.outcomes.put_nowait, **kwargs)


class TickedController(RecordingController):
    """The threshold checked only on a periodic tick, with the latest frame.

    The sensor path only records the latest frame; a ticker on an absolute grid (period
    ``period_s``) runs the same check as the production controller (stop included) on it.
    The grid's phase against the frame stream is drawn afresh for every press: a 125 Hz tick
    against a 125 Hz stream would otherwise sit at one arbitrary phase for the whole run.
    """

    def __init__(self, *args: Any, name: str, period_s: float, rng: np.random.Generator,
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.name = name
        self.period_s = period_s
        self.rng = rng
        self.latest: tuple[np.ndarray, float] | None = None

    async def on_frame(self, raw: np.ndarray, recv_time: float) -> None:
        self.latest = (raw, recv_time)

    async def run(self, window_ready: asyncio.Future[PressOutcome] | None = None
                  ) -> PressOutcome:
        ticker = asyncio.create_task(self.tick(), name=f"bench-{self.name}-ticker")
        try:
            return await super().run(window_ready)
        finally:
            ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await ticker

    async def tick(self) -> None:
        """Check the latest frame on each tick of the grid while the press is armed."""
        loop = asyncio.get_running_loop()
        period = self.period_s
        deadline = loop.time() + float(self.rng.uniform(0.0, period))
        while True:
            await asyncio.sleep(max(0.0, deadline - loop.time()))
            latest = self.latest
            if latest is not None and self.armed:
                await self.check(*latest)
            deadline += period
            behind = loop.time() - deadline
            if behind > period:
                deadline += (behind // period) * period
