"""In-memory fakes of the device contracts in :mod:`edge.hw.contracts`, for tests.

Each one implements its Protocol (``tests/hw/test_contracts.py`` checks it) and records what
it was asked to do, so a test can drive the daemon's code without a robot or an emulator.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable, Iterable, Mapping
from typing import Self

import numpy as np

from edge.core.errors import StaleSensorError
from edge.hw.arm import GRIPPER_CLOSED_WIDTH_M, GRIPPER_OPEN_WIDTH_M, gripper_raw
from edge.hw.contracts import (
    DEFAULT_MOVE_TIMEOUT_S,
    FrameHook,
    GripperState,
    GripperStop,
    JointPose,
    StreamStats,
    TactileFrame,
    named_pose,
)

# --- tactile ------------------------------------------------------------------------------

_END = object()


class FakeTactileSource:
    """In-memory :class:`~edge.hw.contracts.TactileSource`.

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
        self.server_models: tuple[str, ...] | None = self._models

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

    def set_frame_hook(self, hook: FrameHook | None) -> bool:
        return False  # frames go straight to frames(): the consumer runs its step

    async def wait_first_frame(self, timeout_s: float) -> None:
        return None  # its frames are in memory: there from the start

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


# --- arm and gripper -----------------------------------------------------------------------


class FakeGripper:
    """In-memory gripper: closes at the commanded speed and stops against an
    object of width ``object_width_m`` (None: nothing between the fingers), squeezing at the
    current cap there. Every call is appended to ``calls``."""

    def __init__(
        self,
        *,
        object_width_m: float | None = None,
        start_width_m: float = GRIPPER_OPEN_WIDTH_M,
        closed_width_m: float = GRIPPER_CLOSED_WIDTH_M,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.object_width_m = object_width_m
        self._closed_width_m = closed_width_m
        self._clock = clock
        self._width = start_width_m
        self._t0 = clock()
        self._speed = 0.0
        self._cap_ma = 0.0
        self.calls: list[str] = []

    def _width_now(self) -> float:
        if self._speed <= 0:
            return self._width
        width = max(self._closed_width_m, self._width - self._speed * (self._clock() - self._t0))
        if self.object_width_m is not None:
            width = max(width, self.object_width_m)
        return width

    def _squeeze_ma(self, width: float) -> float:
        touching = self.object_width_m is not None and width <= self.object_width_m + 1e-9
        return self._cap_ma if touching else 0.0

    async def open(self, width_m: float, current_cap_ma: float) -> None:
        self.calls.append(f"open {width_m} {current_cap_ma}")
        self._width, self._speed, self._cap_ma = width_m, 0.0, 0.0

    async def close(self, speed_mps: float, current_cap_ma: float) -> None:
        self.calls.append(f"close {speed_mps} {current_cap_ma}")
        self._width, self._t0 = self._width_now(), self._clock()
        self._speed, self._cap_ma = speed_mps, current_cap_ma

    async def stop_now(self, squeeze_raw: int) -> GripperStop:
        self.calls.append(f"stop_now {squeeze_raw}")
        self._width, self._speed = self._width_now(), 0.0
        return GripperStop(gripper_raw(self._width) - squeeze_raw, self._clock())

    async def state(self) -> GripperState:
        width = self._width_now()
        return GripperState(self._clock(), width, self._squeeze_ma(width), gripper_raw(width))


class FakeArm:
    """In-memory arm: arrives at once; ``history`` lists the poses visited;
    set ``fail_next`` to make the next move raise it."""

    def __init__(self, poses: Mapping[str, JointPose], start: str | None = None) -> None:
        self._poses = dict(poses)
        first = start if start is not None else next(iter(self._poses))
        self._joints = named_pose(self._poses, first)
        self.history: list[str] = []
        self.fail_next: Exception | None = None

    @property
    def poses(self) -> Mapping[str, JointPose]:
        return self._poses

    async def move_to(self, pose: str, timeout_s: float = DEFAULT_MOVE_TIMEOUT_S) -> None:
        target = named_pose(self._poses, pose)
        if self.fail_next is not None:
            exc, self.fail_next = self.fail_next, None
            raise exc
        self._joints = target
        self.history.append(pose)

    async def joints(self) -> JointPose:
        return self._joints


# --- camera and button ---------------------------------------------------------------------


class FakeCamera:
    """Returns fixed bytes; counts captures."""

    def __init__(self, image: bytes) -> None:
        self.image = image
        self.captures = 0

    async def capture(self) -> bytes:
        self.captures += 1
        return self.image


class FakeButton:
    """A button pressed by calling :meth:`press`."""

    def __init__(self) -> None:
        self._queue: asyncio.Queue[float] = asyncio.Queue()

    def press(self) -> None:
        self._queue.put_nowait(time.monotonic())

    async def presses(self) -> AsyncIterator[float]:
        while True:
            yield await self._queue.get()

    async def close(self) -> None:
        return None
