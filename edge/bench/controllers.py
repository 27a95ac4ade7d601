"""The press controllers the bench compares: the production one, which checks the threshold
on every arriving frame, and two that check it only on a periodic tick (the sampler's 125 Hz,
a 100 Hz control loop as in the usual ROS 2 arrangement).

They are one controller, the daemon's for its whole life (``assemble(...,
controller_factory=BenchController)``), whose check is a strategy switched between presses
(:meth:`BenchController.use`); it lives here, not in production code, and uses only the
controller's public hooks: ``on_outcome``, ``check``, ``armed`` and ``gripper`` (whose
``stop_now`` the CPU probe sees handed over).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from edge.bench.probes import HotPathCPU
from edge.core.errors import BusyError
from edge.core.tasks import cancel_and_wait
from edge.runtime.domain import PressState
from edge.runtime.press import PressController, PressOutcome

# How each compared controller checks the threshold: on every frame (None), or on a tick of
# this period (s). The names are settings.CONTROLLERS.
TICK_PERIOD_S: dict[str, float | None] = {"per_frame": None, "tick125": 1 / 125.0,
                                          "loop100": 1 / 100.0}
# The ticks' phase against the frame stream is drawn from this seed's generator.
TICK_PHASE_SEED = 0

# The threshold check the sensor task makes with every frame (raw, receive time).
Check = Callable[[np.ndarray, float], Awaitable[None]]


class BenchController(PressController):
    """The production controller; its ``on_outcome`` hook hands each outcome to the bench
    (``outcomes``), and :meth:`use` picks how the next presses check the threshold."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.outcomes: asyncio.Queue[PressOutcome] = asyncio.Queue()
        super().__init__(*args, on_outcome=self.outcomes.put_nowait, **kwargs)
        self.name = "per_frame"
        self.period_s: float | None = None
        self.rng = np.random.default_rng(TICK_PHASE_SEED)
        self.latest: tuple[np.ndarray, float] | None = None
        # The thread CPU probe of the production check (:meth:`measure_cpu`).
        self.cpu: HotPathCPU | None = None
        self.gripper = _TimedGripper(self.gripper, self)
        self._check: Check = super().check

    @property  # type: ignore[override]
    def check(self) -> Check:
        """The check the sensor task calls with every frame: the strategy :meth:`use`
        picked, per frame the production check itself (nothing added on the frame's
        path but this lookup)."""
        return self._check

    def measure_cpu(self, probe: HotPathCPU) -> None:
        """From now on the production check tells ``probe`` when it ends."""
        self.cpu = probe
        self.use(self.name)

    async def _timed_check(self, raw: np.ndarray, recv_time: float) -> None:
        armed = self.armed
        try:
            await PressController.check(self, raw, recv_time)
        finally:
            if self.cpu is not None:
                self.cpu.checked(armed)

    def use(self, name: str) -> None:
        """From the next press on, the threshold checked as controller ``name`` does
        (:data:`TICK_PERIOD_S`): on every frame by the production check itself, which the
        sensor task calls (nothing added, but the CPU probe's call at its end once one
        measures), or only on a periodic tick with the latest frame (the sensor task's call
        keeps the frame)."""
        if self.state != PressState.IDLE:
            raise BusyError(f"a press is running ({self.state}); switch between presses")
        period_s = TICK_PERIOD_S[name]
        self.name = name
        self.period_s = period_s
        if period_s is not None:
            self._check = self._keep_latest
        elif self.cpu is not None:
            self._check = self._timed_check
        else:
            self._check = super().check

    async def _keep_latest(self, raw: np.ndarray, recv_time: float) -> None:
        self.latest = (raw, recv_time)

    async def run(self, window_ready: asyncio.Future[PressOutcome] | None = None,
                  checked: asyncio.Future[None] | None = None) -> PressOutcome:
        if self.period_s is None:
            return await super().run(window_ready, checked)
        ticker = asyncio.create_task(self._tick(self.period_s),
                                     name=f"bench-{self.name}-ticker")
        try:
            return await super().run(window_ready, checked)
        finally:
            await cancel_and_wait(ticker)

    async def _tick(self, period: float) -> None:
        """Check the latest frame on each tick of an absolute grid while the press is
        armed. The grid's phase against the frame stream is drawn afresh for every press:
        a 125 Hz tick against a 125 Hz stream would otherwise sit at one arbitrary phase
        for the whole run."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + float(self.rng.uniform(0.0, period))
        while True:
            await asyncio.sleep(max(0.0, deadline - loop.time()))
            latest = self.latest
            if latest is not None and self.armed:
                await PressController.check(self, *latest)
            deadline += period
            behind = loop.time() - deadline
            if behind > period:
                deadline += (behind // period) * period


class _TimedGripper:
    """The controller's gripper; the CPU probe hears when a stop is handed over."""

    def __init__(self, gripper: Any, controller: BenchController) -> None:
        self._gripper = gripper
        self._controller = controller

    def __getattr__(self, name: str) -> Any:
        return getattr(self._gripper, name)

    async def stop_now(self, squeeze_raw: int) -> Any:
        if self._controller.cpu is not None:
            self._controller.cpu.handover()
        return await self._gripper.stop_now(squeeze_raw)
