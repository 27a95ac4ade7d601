"""The device contracts: the Protocols every driver implements and the values they pass.

The daemon, the tools and the tests are written against these, never against a driver, so a
real device, an emulated one and an in-memory fake are interchangeable. This module imports
no SDK and no network, serial, camera or GPIO library (``tests/hw/test_contracts.py`` checks
it): typing against a device must not need its hardware library installed.

Tactile frames carry raw 16-bit counts in the project's channel order (``pad*48 + taxel*3 +
axis`` for 4x4 pads; pads by sensor number, taxels row-major from the top left, axes x, y, z).
Converting to tactile units (``(raw - tare) / 65536``) is the consumer's job.

Motor positions are raw Dynamixel counts (4096 per turn) unless a name says metres.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from types import TracebackType
from typing import Protocol, Self, runtime_checkable

import numpy as np

log = logging.getLogger(__name__)

# How long an arm move may take when the caller names no timeout.
DEFAULT_MOVE_TIMEOUT_S = 5.0

# Raw positions of the four arm joints, in joint ID order.
JointPose = tuple[int, int, int, int]


# --- tactile ------------------------------------------------------------------------------


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
    # xela_server's `calibrated` forces (N, x, y, z per taxel, the raw channels' order) where
    # the model is calibrated and the source was asked for them; else None.
    newtons: np.ndarray | None = None

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


# The per-frame hook: awaited with each fresh frame (the daemon's threshold check).
FrameHook = Callable[[TactileFrame], Awaitable[None]]


@runtime_checkable
class TactileSource(Protocol):
    """Anything that yields :class:`TactileFrame` s: the XELA client, a fake, a replay.

    ``frames()`` yields fresh frames to one consumer and raises
    :class:`~edge.core.errors.StaleSensorError` when no fresh frame arrived within the source's
    stale timeout; the source keeps running (and reconnecting), so call ``frames()`` again to
    resume. Iteration ends after ``close()``.
    """

    stats: StreamStats
    # The model of each sensor the source sends, in pad order; None until its first frame.
    server_models: tuple[str, ...] | None

    def set_frame_hook(self, hook: FrameHook | None) -> bool:
        """Run ``hook`` on each fresh frame in the source's own task, before the frame is
        handed on (``None``: no more); True if this source does so. A source that hands its
        frames straight to ``frames()`` (a fake, the virtual robot's stream) returns False
        and the consumer runs the step on each frame it gets."""
        ...

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

    async def wait_first_frame(self, timeout_s: float) -> None:
        """Until the first fresh frame has arrived, its layout checked; consumes no frame.
        Raises :class:`~edge.core.errors.SensorLayoutError` for a layout the configuration
        does not match, and :class:`~edge.core.errors.StaleSensorError` saying why (the
        server unreachable, or silent) when no frame came within ``timeout_s``. A source
        whose frames are made in this process (a fake, a replay, the virtual robot's stream)
        has them from its start and returns at once."""
        ...


# --- arm and gripper -----------------------------------------------------------------------


@dataclass(frozen=True)
class GripperState:
    """``t``: monotonic time of the reading; ``squeeze_ma``: motor current pushing the fingers
    closed (positive while squeezing, whatever the Drive Mode)."""

    t: float
    width_m: float
    squeeze_ma: float
    position_raw: int


@dataclass(frozen=True)
class GripperStop:
    """What :meth:`Gripper.stop_now` sent: ``goal_raw`` is the Goal Position written,
    ``t_sent`` the monotonic time the stop packet went out to the port (the end of the
    threshold-to-stop latency)."""

    goal_raw: int
    t_sent: float


@runtime_checkable
class Gripper(Protocol):
    """The gripper. Opening width and current cap are arguments of every call, not settings
    copied into the driver at start, so a configuration reload takes effect on the next
    press."""

    async def open(self, width_m: float, current_cap_ma: float) -> None:
        """Open to ``width_m`` with the squeeze capped at ``current_cap_ma`` and wait until
        there (``DeviceTimeoutError`` past the timeout)."""
        ...

    async def close(self, speed_mps: float, current_cap_ma: float) -> None:
        """Start closing at ``speed_mps`` with the squeeze capped at ``current_cap_ma``;
        returns once commanded (watch :meth:`state` and call :meth:`stop_now`)."""
        ...

    async def stop_now(self, squeeze_raw: int) -> GripperStop:
        """Stop at once, keeping the squeeze: one Goal Position write ``squeeze_raw`` counts
        past the present position in the closing direction (the present position itself
        would release the squeeze), ahead of anything queued."""
        ...

    async def state(self) -> GripperState: ...


def named_pose(poses: Mapping[str, JointPose], pose: str) -> JointPose:
    """``poses[pose]``, or ValueError naming the known poses (every Arm refuses alike)."""
    try:
        return poses[pose]
    except KeyError:
        raise ValueError(f"unknown arm pose {pose!r}; known: {', '.join(sorted(poses))}") from None


@runtime_checkable
class Arm(Protocol):
    @property
    def poses(self) -> Mapping[str, JointPose]:
        """Named joint poses (raw positions of the four joints, in joint ID order)."""
        ...

    async def move_to(self, pose: str, timeout_s: float = DEFAULT_MOVE_TIMEOUT_S) -> None:
        """Move to a named pose and wait for arrival (``DeviceTimeoutError`` past
        ``timeout_s``)."""
        ...

    async def joints(self) -> JointPose:
        """Present raw joint positions."""
        ...


# --- the motor bus ------------------------------------------------------------------------


@runtime_checkable
class BusStatus(Protocol):
    """What the daemon reports of the motor bus (``/healthz``, ``/metrics``)."""

    @property
    def fault(self) -> str | None:
        """What is wrong with the bus now (a motor that does not answer...), or None."""
        ...

    @property
    def torque_on(self) -> bool: ...

    @property
    def stops(self) -> int:
        """Stops sent to the gripper."""
        ...

    @property
    def stop_fallbacks(self) -> int:
        """Stops that read Present Position first (no gripper state fresh enough)."""
        ...


@runtime_checkable
class MotorBus(BusStatus, Protocol):
    """The motor bus as the daemon drives it, beside the arm and gripper on it."""

    @property
    def native_thread_id(self) -> int | None:
        """The thread that calls the SDK (for real-time scheduling), None without one."""
        ...

    async def set_torque(self, enabled: bool) -> None: ...

    async def recover_watchdog(self) -> list[int]:
        """Before a press: check torque is on everywhere and clear watchdog trips."""
        ...

    async def close(self, safe_pose: Callable[[], Awaitable[object]] | None = None) -> None:
        """With torque on, ``safe_pose`` first; then torque off and the port released."""
        ...


# --- camera and button ---------------------------------------------------------------------


@runtime_checkable
class Camera(Protocol):
    async def capture(self) -> bytes:
        """One still image, JPEG or PNG bytes."""
        ...


@runtime_checkable
class Button(Protocol):
    def presses(self) -> AsyncIterator[float]:
        """Yields the monotonic time of each debounced press."""
        ...

    async def close(self) -> None: ...


# --- all of them ---------------------------------------------------------------------------


@dataclass
class Devices:
    """Everything the daemon talks to; built by :mod:`edge.runtime.devices`."""

    tactile: TactileSource
    gripper: Gripper
    arm: Arm
    camera: Camera | None = None
    button: Button | None = None
    bus: MotorBus | None = None  # closed (safe pose, torque off) by the caller

    @property
    def recover(self) -> Callable[[], Awaitable[list[int]]] | None:
        """What a press runs before it moves (:meth:`MotorBus.recover_watchdog`); None
        without a bus of its own."""
        return self.bus.recover_watchdog if self.bus is not None else None
