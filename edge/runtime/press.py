"""The press controller: the state machine of one press (docs/method.md, 'Press').

idle -> above -> lowered -> tare -> closing -> holding -> opening -> returning -> idle

The gripper is opened before the arm moves to ``above`` (it may have been left closed).

The threshold is checked on every arriving frame by the sensor task (:meth:`check`),
which sends the stop itself: the fastest reaction the stream allows. Timeouts and aborts:
closing without crossing ``x_th`` ends with ``no_contact``; the gripper stalled on the object
at its current cap with the norm still under ``x_th`` (a threshold the pads never reach)
opens at once (``below_threshold``, naming x_th, the peak and the model's threshold); a norm
far past the threshold (``abort_factor * x_th``) opens at once (``aborted``); a stale sensor
opens and fails the press. Whatever happens, the gripper is opened before the press returns.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

import numpy as np

from edge.core import preprocess, recording
from edge.core.config import Config
from edge.core.errors import DeviceError, EdgeError, PressRefusedError, StaleSensorError
from edge.core.layout import PadLayout
from edge.core.tasks import cancel_and_wait
from edge.hw.arm import GRIPPER_CLOSED_WIDTH_M
from edge.hw.contracts import Arm, Gripper, GripperState
from edge.hw.control_table import CURRENT_MA_PER_UNIT
from edge.runtime.domain import PressResult, PressState, PressSummary
from edge.runtime.ring import FrameRing, Window

log = logging.getLogger(__name__)

# Extra stream kept on each side of the model's window in the stored recording.
RECORD_MARGIN_S = 0.2
# While the threshold is armed the gripper is read (one sync read of every motor, the
# recording's gripper trace) right after every second tactile frame has been checked: the
# read is over long before the next frame, so the stop, which only a frame triggers, finds
# the bus free, and it extrapolates from a state at most two frames old (the stop's goal
# comes from it: DynamixelBus.stop_ahead). Without frames, it reads every
# GRIPPER_TRACE_PERIOD_S.
GRIPPER_TRACE_FRAMES = 2
GRIPPER_TRACE_PERIOD_S = 0.02
# A stream this long without a fresh frame means the press must not start...
FRESH_FRAME_S = 0.1
# ... unless a fresh one arrives within this long: a busy host can hold a frame back past
# FRESH_FRAME_S with nothing wrong with the pads. Nothing moves before it has arrived.
FRESH_WAIT_S = 0.5
# Tries to open the gripper before a press gives up and says it may still be closed.
OPEN_TRIES = 3
# With press.lift_clearance_m: the fraction of x_th the pads read under once the fingers
# have left the object.
CLEAR_LEVEL_FRACTION = 0.5
# The pads' reading with the arm above the object, the fingers free, over this long: what
# the tare at the object is checked against before the gripper closes.
FREE_WINDOW_S = 0.1
# After the press, how long the recording waits for a late stream to cover its window.
STREAM_CATCH_UP_S = 1.0
# The gripper stalled on the object: its squeeze current at least this fraction of the cap
# (Goal Current; a motor in current-based position mode holds it there, within noise), its
# width within STALL_TRAVEL_M, for STALL_S on end. It squeezes as hard as it is allowed
# to: a norm not over x_th by then will not be (the traced reads come every ~16 ms).
STALL_CURRENT_FRACTION = 0.9
STALL_TRAVEL_M = 0.0002
STALL_S = 0.3


@dataclass
class PressOutcome:
    result: PressResult = PressResult.ERROR
    message: str = ""
    t_cross: float | None = None  # receive time of the first frame over x_th
    t_stop: float | None = None  # when the stop write went out
    t_check: float | None = None  # when the check of the frame over x_th began
    stop_latency_s: float | None = None
    peak_level: float = 0.0
    level_at_cross: float = 0.0
    tare: np.ndarray | None = None
    # How far lowering the arm moved the pads (the norm of the tare against their reading
    # above the object); None without a reading above it.
    lowering_level: float | None = None
    # The frames around the stop: handed over (``run``'s window_ready) through the first
    # frame at or past the crop's last sample; once the press has ended, the whole recording
    # (its margins too).
    window: Window | None = None
    gripper_trace: list[GripperState] = field(default_factory=list)
    states: list[tuple[PressState, float]] = field(default_factory=list)

    @property
    def contact(self) -> bool:
        return self.result == PressResult.OK

    def summary(self) -> PressSummary:
        win, t_stop = self.window, self.t_stop
        rate = (preprocess.stream_rate(win.recv_time, win.sensor_time, win.seq, t_stop)
                if win is not None and t_stop is not None else preprocess.StreamRate(None, None))
        return PressSummary(
            result=self.result,
            message=self.message,
            contact=self.contact,
            t_cross=self.t_cross,
            t_stop=self.t_stop,
            stop_latency_ms=None if self.stop_latency_s is None
            else self.stop_latency_s * 1e3,
            peak_level=self.peak_level,
            level_at_cross=self.level_at_cross,
            peak_squeeze_ma=max((s.squeeze_ma for s in self.gripper_trace), default=None),
            states=tuple(self.states),
            lowering_level=self.lowering_level,
            window_rate_hz=rate.window_hz,
            press_rate_hz=rate.press_hz,
        )


class _Armed:
    """Threshold state while closing/holding; touched only on the event loop."""

    def __init__(self, tare: np.ndarray, x_th: float, abort_level: float) -> None:
        # As floats: math.dist on a list is the cheapest norm on the per-frame path, where
        # numpy's code is out of the caches (np.linalg.norm costs about 2.5x as much there).
        self.tare = tare.tolist()
        self.x_th = x_th
        self.abort_level = abort_level
        self.crossed = asyncio.Event()
        self.abort = asyncio.Event()
        # The gripper stalled at its current cap with the norm under x_th (see STALL_S).
        self.stalled = asyncio.Event()
        self.t_cross: float | None = None
        self.level_at_cross = 0.0
        self.peak = 0.0
        # The stop at the threshold could not be sent: the press aborts and opens.
        self.stop_error: BaseException | None = None
        # Frames checked, and the gripper trace's cue to read (see GRIPPER_TRACE_FRAMES).
        self.checked = 0
        self.trace_due = asyncio.Event()


class PressController:
    """One press at a time. Hooks: ``on_state(state)`` at every state change,
    ``on_outcome(outcome)`` when a press ends, ``clock`` the monotonic clock the frames'
    receive times are on; ``window`` is where the model's crop lies around the stop (the
    recording covers it); ``model_x_th`` the threshold the model's references were pressed
    at (:attr:`edge.core.model.ModelRef.x_th`), named where a press ends under x_th."""

    def __init__(self, cfg: Config, gripper: Gripper, arm: Arm, ring: FrameRing,
                 on_state: Callable[[PressState], None] | None = None,
                 recover: Callable[[], Awaitable[object]] | None = None,
                 on_outcome: Callable[[PressOutcome], None] | None = None,
                 window: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW,
                 clock: Callable[[], float] = time.monotonic,
                 model_x_th: float | None = None) -> None:
        self.cfg = cfg
        self.window = window
        self.model_x_th = model_x_th
        self.clock = clock
        self.on_outcome = on_outcome
        # Clears a tripped Bus Watchdog (a stalled loop stops the motors; that is the point,
        # but the next press must not inherit motors that refuse every goal).
        self.recover = recover
        self.gripper = gripper
        self.arm = arm
        self.ring = ring
        self.on_state = on_state or (lambda state: None)
        self.state = PressState.IDLE
        self._armed: _Armed | None = None
        self._outcome: PressOutcome | None = None
        self._stale = asyncio.Event()
        self._user_abort = asyncio.Event()

    # --- called by the sensor task -------------------------------------------------------
    @property
    def armed(self) -> bool:
        """Whether the threshold is being watched (closing or holding)."""
        return self._armed is not None

    async def check(self, raw: np.ndarray, recv_time: float) -> None:
        """The threshold check on one frame; on the first crossing, the stop. The sensor task
        calls it with every arriving frame: the fastest reaction the stream allows."""
        armed = self._armed
        if armed is None:
            return
        t_check = self.clock()
        level = math.dist(raw.tolist(), armed.tare) / preprocess.UNITS_SCALE
        if level > armed.peak:
            armed.peak = level
        if armed.t_cross is None and level > armed.x_th:
            armed.t_cross = recv_time
            armed.level_at_cross = level
            stopped = False
            try:
                stop = await self.gripper.stop_now(self.cfg.press.stop_squeeze_raw)
                t_sent = stop.t_sent
                if self._outcome is not None:
                    self._outcome.t_stop = t_sent
                    self._outcome.t_check = t_check
                    self._outcome.stop_latency_s = t_sent - recv_time
                stopped = True
            except DeviceError as exc:
                # Not the sensor's fault: keep it out of the sensor task, abort the press.
                log.error("the stop at the threshold failed: %s", exc)
                armed.stop_error = exc
            finally:
                # Only a stop that went out counts as crossed; anything else aborts and opens.
                (armed.crossed if stopped else armed.abort).set()
        elif level > armed.abort_level:
            armed.abort.set()
        # After the check, never before it: the read must not delay a stop.
        armed.checked += 1
        if armed.checked % GRIPPER_TRACE_FRAMES == 0:
            armed.trace_due.set()

    def sensor_stale(self, exc: BaseException) -> None:
        self._stale.set()
        if self._armed is not None:
            self._armed.abort.set()

    def sensor_fresh(self) -> None:
        self._stale.clear()

    @property
    def sensor_is_stale(self) -> bool:
        return self._stale.is_set()

    def request_abort(self) -> bool:
        if self.state in (PressState.IDLE, PressState.RETURNING):
            return False
        self._user_abort.set()
        if self._armed is not None:
            self._armed.abort.set()
        return True

    async def open_gripper(self) -> None:
        """Open to the configured width, the squeeze capped at the configured current."""
        await self.gripper.open(self.cfg.press.open_width_m, self._current_cap_ma())

    def _current_cap_ma(self) -> float:
        return self.cfg.bus.gripper_goal_current * CURRENT_MA_PER_UNIT

    # --- the press ------------------------------------------------------------------------
    def _enter(self, outcome: PressOutcome, state: PressState) -> None:
        self.state = state
        outcome.states.append((state, self.clock()))
        self.on_state(state)
        if self._user_abort.is_set() and state in _ABORTABLE:
            # Asked before the threshold was armed (above, lowered, tare): the press stops
            # at this step instead of going on to close on the object.
            raise _AbortRequested

    async def run(self, window_ready: asyncio.Future[PressOutcome] | None = None,
                  checked: asyncio.Future[None] | None = None) -> PressOutcome:
        """One press; ``window_ready`` gets the outcome as soon as the model's crop is
        complete (the first frame at or past its last sample received), while the gripper
        opens and the arm returns (the press goes on after, and records the margin).
        ``checked`` is resolved once the stream and the motors have been checked, before
        anything moves: work that would compete with the check's round trips for the host
        waits for it."""
        outcome = PressOutcome()
        self._outcome = outcome
        self._user_abort.clear()
        done = _Done()
        try:
            await self._preflight(checked)
            await self._approach(outcome, done)
            armed = await self._close(outcome, done)
            await self._hold(outcome, armed)
        except Exception as exc:
            _ended_by(outcome, exc)
        finally:
            self._armed = None
            # Refused before touching anything (stale sensor, a motor down): nothing to undo.
            opened, opening = (await self._open_safely(outcome) if done.touched
                               else (False, None))
            if done.trace is not None:
                await cancel_and_wait(done.trace)
        returning = self._leave(outcome, done.moved, opened, opening)
        await self._record(outcome, window_ready, returning, opening)
        self._enter(outcome, PressState.IDLE)
        self._outcome = None
        if self.on_outcome is not None:
            self.on_outcome(outcome)
        return outcome

    # --- its phases, in order ---------------------------------------------------------------
    async def _preflight(self, checked: asyncio.Future[None] | None) -> None:
        """A fresh stream and the motors answering (a tripped Bus Watchdog cleared) before
        anything moves; then ``checked``."""
        await self._await_fresh()
        if self.recover is not None:
            await self.recover()
        if checked is not None and not checked.done():
            checked.set_result(None)

    async def _approach(self, outcome: PressOutcome, done: _Done) -> None:
        """The gripper open, the arm above the object, then lowered around it, and the
        tare; refused where lowering the arm alone moved the pads as far as contact."""
        self._enter(outcome, PressState.ABOVE)
        # Open before anything moves: a gripper left closed (a crash, a motor that
        # dropped out) would lift the object and tare on a squeeze.
        done.touched = True
        await self.open_gripper()
        done.moved = True
        await self.arm.move_to("above", self.cfg.runtime.move_timeout_s)
        free = self._pads_now()
        self._enter(outcome, PressState.LOWERED)
        await self.arm.move_to("lowered", self.cfg.runtime.move_timeout_s)
        self._enter(outcome, PressState.TARE)
        outcome.tare = await self._tare()
        self._check_untouched(outcome, free)

    async def _close(self, outcome: PressOutcome, done: _Done) -> _Armed:
        """The threshold armed and the gripper closing, until the stop went out, an abort,
        a stall under x_th or the closing's timeout (the outcome says which)."""
        press = self.cfg.press
        armed = _Armed(outcome.tare, press.x_th, press.abort_factor * press.x_th)
        self._armed = armed
        self._enter(outcome, PressState.CLOSING)
        done.trace = asyncio.create_task(self._trace(outcome, armed), name="gripper-trace")
        goal_ma = self._current_cap_ma()
        # Both fingers move: each closes at half the gap speed.
        await self.gripper.close(press.close_speed_mps / 2, goal_ma)
        await self._wait_closing(armed, outcome)
        return armed

    async def _hold(self, outcome: PressOutcome, armed: _Armed) -> None:
        """After a stop at the threshold, held for ``dt_stopping_s`` (an abort ends it)."""
        if outcome.result != PressResult.OK or outcome.t_stop is None:
            return
        self._enter(outcome, PressState.HOLDING)
        hold_left = outcome.t_stop + self.cfg.press.dt_stopping_s - self.clock()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(armed.abort.wait(), max(hold_left, 0.0))
        # The peak norm takes the hold's squeeze in (preprocess.peak_norm).
        outcome.peak_level = armed.peak
        if armed.abort.is_set():
            self._abort_reason(outcome, armed)

    def _leave(self, outcome: PressOutcome, moved: bool, opened: bool,
               opening: asyncio.Task[DeviceError | None] | None) -> asyncio.Task | None:
        """The arm's return, begun once the gripper opened; where it may still be closed,
        the arm stays where it stands."""
        if moved and not opened:
            # Lifting a gripper that may still hold the object would drag or lift it.
            log.error("the gripper may still be closed: the arm stays where it stands")
            outcome.message += "; arm left where it stands: free the object by hand"
        if not (moved and opened):
            return None
        self._enter(outcome, PressState.RETURNING)
        # The window completes while the arm returns: whoever waits for it starts on it
        # at once, not once the arm is back.
        return asyncio.create_task(self._return(outcome, opening), name="press-return")

    async def _record(self, outcome: PressOutcome,
                      window_ready: asyncio.Future[PressOutcome] | None,
                      returning: asyncio.Task | None,
                      opening: asyncio.Task[DeviceError | None] | None) -> None:
        """The window handed over once the model's crop is complete, the recording's
        margin after it, and the arm back."""
        try:
            if outcome.t_stop is not None:
                # The model's crop is complete with the first frame at or past its last
                # sample; the analysis starts on it at once, while the recording's margin
                # still comes in.
                t_stop, spec = outcome.t_stop, self.window
                start = t_stop - spec.before_s - RECORD_MARGIN_S
                await self._stream_past(t_stop + spec.last_sample_s)
                # (Through that frame: the crop interpolates up to it.)
                outcome.window = self.ring.window(start, self.ring.latest_time())
                if window_ready is not None and not window_ready.done():
                    window_ready.set_result(outcome)
                end = t_stop + spec.after_s + RECORD_MARGIN_S
                await self._stream_past(end)
                outcome.window = self.ring.window(start, end)
            if returning is not None:
                await returning
        finally:
            # (The opening too: the return waits for it, or never started.)
            for task in (returning, opening):
                if task is not None and not task.done():
                    task.cancel()

    async def _return(self, outcome: PressOutcome,
                      opening: asyncio.Task[DeviceError | None] | None) -> None:
        """The arm back above; ``opening``: the gripper's opening, still under way (the
        fingers cleared the object first), which the press waits for too (cancelled with
        the press, by :meth:`run`)."""
        try:
            await self.arm.move_to("above", self.cfg.runtime.move_timeout_s)
        except EdgeError as exc:
            log.error("arm did not return above the object: %s", exc)
            if outcome.result == PressResult.OK:
                outcome.result, outcome.message = PressResult.ERROR, f"return failed: {exc}"
        failed = None if opening is None else await opening
        if failed is not None:
            log.error("the gripper did not open fully once clear of the object: %s", failed)
            outcome.result = PressResult.ERROR
            _say(outcome, f"the gripper cleared the object but did not open fully: {failed}")

    async def _stream_past(self, end: float) -> None:
        """Until the stream covers ``end`` (a frame at or past it); a stream that paused
        after the stop (a server hiccup, a busy host) has ``STREAM_CATCH_UP_S`` more to
        catch up, then the window is what arrived."""
        await self.ring.wait_until(end, max(end - self.clock(), 0.0) + STREAM_CATCH_UP_S)

    async def _await_fresh(self) -> None:
        """A fresh frame before anything moves: waits up to ``FRESH_WAIT_S`` for one where
        the last is older than ``FRESH_FRAME_S`` or the stream was found stale (the sensor
        task clears that with the frame that ends it)."""
        now = self.clock()
        if self._stale.is_set() or now - self.ring.latest_time() > FRESH_FRAME_S:
            await self.ring.wait_until(now, FRESH_WAIT_S)
        self._check_fresh()

    def _check_fresh(self) -> None:
        age = self.clock() - self.ring.latest_time()
        if self._stale.is_set() or age > FRESH_FRAME_S:
            raise StaleSensorError(
                f"tactile stream is stale (last frame {age:.2f} s ago): not pressing; check "
                "that xela_server runs and the pads are connected")

    def _pads_now(self) -> np.ndarray | None:
        """The pads' mean over the last ``FREE_WINDOW_S`` (the arm above the object, the
        fingers free); None with too few frames to tell (the tare then stands alone)."""
        now = self.clock()
        window = self.ring.window(now - FREE_WINDOW_S, now)
        return preprocess.tare(window.raw) if len(window.raw) >= 3 else None

    def _check_untouched(self, outcome: PressOutcome, free: np.ndarray | None) -> None:
        """Refuse to close when lowering the arm alone moved the pads as far as contact
        (x_th): the object already touches the fingers, the press would take its tare on
        it and stop on nothing, and the gripper would never let go of it."""
        if free is None or outcome.tare is None:
            return
        level = float(preprocess.norm(preprocess.to_units(outcome.tare, free)))
        outcome.lowering_level = level
        log.debug("lowering the arm moved the pads by a norm of %.5f (x_th %s)", level,
                  self.cfg.press.x_th)
        if level >= self.cfg.press.x_th:
            if not self.cfg.press.refuse_contact_before_closing:
                log.warning("lowering the arm moved the pads by a norm of %.4f (>= x_th %s); "
                            "pressing on (press.refuse_contact_before_closing = false)",
                            level, self.cfg.press.x_th)
                return
            raise PressRefusedError(
                f"not closing: the pads read contact before the gripper closed (norm "
                f"{level:.4f} >= x_th {self.cfg.press.x_th} against their reading above the "
                "object): the object touched the fingers as the arm lowered. It is wider "
                f"than the open gripper (press.open_width_m = {self.cfg.press.open_width_m} "
                "m) or off centre: widen open_width_m or centre the object. If nothing was "
                "between the fingers, the pads shift with the arm's motion alone: set "
                "press.refuse_contact_before_closing = false")

    async def _tare(self) -> np.ndarray:
        tare_s = self.cfg.press.tare_s
        t0 = self.clock()
        await asyncio.sleep(tare_s)
        self._check_fresh()
        window = self.ring.window(t0, self.clock())
        if len(window.raw) < max(3, int(tare_s * 50)):
            raise StaleSensorError(
                f"only {len(window.raw)} frames in the {tare_s} s tare: the stream is too slow")
        return preprocess.tare(window.raw)

    async def _wait_closing(self, armed: _Armed, outcome: PressOutcome) -> None:
        crossed = asyncio.create_task(armed.crossed.wait())
        aborted = asyncio.create_task(armed.abort.wait())
        stalled = asyncio.create_task(armed.stalled.wait())
        try:
            await asyncio.wait({crossed, aborted, stalled},
                               timeout=self.cfg.runtime.close_timeout_s,
                               return_when=asyncio.FIRST_COMPLETED)
        finally:
            crossed.cancel()
            aborted.cancel()
            stalled.cancel()
        outcome.peak_level = armed.peak
        if armed.crossed.is_set():  # (set only once the stop went out)
            outcome.t_cross = armed.t_cross
            outcome.level_at_cross = armed.level_at_cross
            outcome.result = PressResult.OK
            return
        if armed.abort.is_set():
            self._abort_reason(outcome, armed)
            return
        if armed.stalled.is_set():
            outcome.result = PressResult.BELOW_THRESHOLD
            model = ("" if self.model_x_th is None else
                     f"; the model's references were pressed at x_th = {self.model_x_th:g}")
            outcome.message = (
                f"below the threshold: the gripper squeezed at its current cap "
                f"({self._current_cap_ma():.0f} mA) and stalled on the object, but the pads "
                f"peaked at a norm of {armed.peak:.4f}, under x_th = {armed.x_th:g}{model}. "
                "x_th is likely wrong for these pads: set [press] x_th to this robot's "
                "calibrated value (`vt-edge calibrate threshold`)")
            log.warning("press: %s", outcome.message)
            return
        outcome.result = PressResult.NO_CONTACT
        outcome.message = (f"no contact: the norm stayed below x_th = {armed.x_th} (peak "
                           f"{armed.peak:.4f}) for {self.cfg.runtime.close_timeout_s} s of "
                           "closing")
        # A host stall past the Bus Watchdog stops the gripper short of the object with no
        # error on any read: ask the motors before calling it no contact.
        tripped = await self._cleared_watchdog_trips()
        if tripped:
            outcome.result = PressResult.ERROR
            outcome.message = (f"the gripper stopped closing: the Bus Watchdog has tripped on "
                               f"motors {tripped} (the host was silent on the bus longer than "
                               "the watchdog allows); cleared, opening")

    async def _cleared_watchdog_trips(self) -> list[int]:
        if self.recover is None:
            return []
        try:
            tripped = await self.recover()
        except DeviceError as exc:
            log.warning("reading the motors' Bus Watchdog failed: %s", exc)
            return []
        return list(tripped) if isinstance(tripped, list) else []

    def _abort_reason(self, outcome: PressOutcome, armed: _Armed) -> None:
        outcome.peak_level = max(outcome.peak_level, armed.peak)
        if armed.stop_error is not None:
            outcome.result = PressResult.ERROR
            outcome.message = (f"the stop at the threshold failed ({armed.stop_error}): "
                               "opening the gripper")
        elif self._stale.is_set():
            outcome.result = PressResult.STALE
            outcome.message = "tactile stream went stale during the press: gripper opened"
        elif self._user_abort.is_set():
            outcome.result, outcome.message = PressResult.ABORTED, "aborted on request"
        else:
            outcome.result = PressResult.ABORTED
            outcome.message = (f"force far past the threshold (norm {armed.peak:.4f} > "
                               f"{armed.abort_level:.4f}): gripper opened")

    async def _open_safely(self, outcome: PressOutcome
                           ) -> tuple[bool, asyncio.Task[DeviceError | None] | None]:
        """Open the gripper (see :meth:`open_gripper_retrying`). Returns whether the fingers
        are off the object (False, and said in the outcome, if the opening failed) and, where
        they cleared it before the gripper was fully open (``press.lift_clearance_m``), the
        opening still under way."""
        self._enter(outcome, PressState.OPENING)
        clear_width = self._clear_width(outcome)
        if clear_width is None:
            failed = await self.open_gripper_retrying()
        else:
            opening = asyncio.create_task(self.open_gripper_retrying(), name="press-open")
            try:
                if await self._cleared(outcome, clear_width, opening):
                    return True, opening
                failed = await opening
            except BaseException:
                await cancel_and_wait(opening)
                raise
        if failed is None:
            return True, None
        if outcome.result == PressResult.OK:
            outcome.result = PressResult.ERROR
        _say(outcome,
             f"GRIPPER MAY STILL BE CLOSED: opening failed {OPEN_TRIES} times (last: {failed})")
        return False, None

    def _clear_width(self, outcome: PressOutcome) -> float | None:
        """The gripper width past which the fingers are clear of the object: the width where
        the press crossed x_th plus ``press.lift_clearance_m``; None where the arm waits for
        the full opening (the option off, or no crossing to measure from)."""
        clearance = self.cfg.press.lift_clearance_m
        if clearance <= 0 or outcome.t_cross is None or outcome.tare is None:
            return None
        at_cross = next((s.width_m for s in reversed(outcome.gripper_trace)
                         if s.t <= outcome.t_cross), None)
        return None if at_cross is None else at_cross + clearance

    async def _cleared(self, outcome: PressOutcome, clear_width: float,
                       opening: asyncio.Task[DeviceError | None]) -> bool:
        """Whether the fingers are clear of the object (the gripper trace's latest width past
        ``clear_width``, the pads' latest fresh frame under half of x_th) while ``opening``
        still runs; False once it has ended (the caller takes its result)."""
        assert outcome.tare is not None and outcome.t_cross is not None
        release_level = self.cfg.press.x_th * CLEAR_LEVEL_FRACTION
        ring = self.ring
        while not opening.done():
            # The press's gripper trace goes on reading the gripper while it opens: its
            # latest width, not a read of our own beside the opening's and the trace's.
            last = outcome.gripper_trace[-1] if outcome.gripper_trace else None
            if (last is not None and last.t > outcome.t_cross and last.width_m >= clear_width
                    and ring.latest_time() >= self.clock() - FRESH_FRAME_S
                    and preprocess.norm(preprocess.to_units(ring.raw[ring.latest_index],
                                                            outcome.tare)) < release_level):
                return True
            await asyncio.wait({opening}, timeout=GRIPPER_TRACE_PERIOD_S)
        return False

    async def open_gripper_retrying(self) -> DeviceError | None:
        """Open the gripper, up to ``OPEN_TRIES`` times, clearing a tripped Bus Watchdog
        between tries; the last error if every try failed, else None."""
        last: DeviceError | None = None
        for attempt in range(OPEN_TRIES):
            try:
                await self.open_gripper()
                return None
            except DeviceError as exc:
                last = exc
                log.error("opening the gripper failed (attempt %d): %s", attempt + 1, exc)
                if self.recover is not None:
                    with contextlib.suppress(DeviceError):
                        await self.recover()
        return last

    async def _trace(self, outcome: PressOutcome, armed: _Armed) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(GRIPPER_TRACE_PERIOD_S):
                    await armed.trace_due.wait()
            armed.trace_due.clear()
            try:
                outcome.gripper_trace.append(await self.gripper.state())
            except DeviceError as exc:
                log.debug("gripper trace read failed: %s", exc)
                continue
            if armed.t_cross is None and _stalled(outcome.gripper_trace,
                                                  self._current_cap_ma()):
                armed.stalled.set()


# The states a press can be stopped at by an abort request before the threshold is armed.
_ABORTABLE = frozenset({PressState.LOWERED, PressState.TARE, PressState.CLOSING})


class _AbortRequested(Exception):
    """An abort request reached the press before the gripper closed."""


@dataclass
class _Done:
    """What a press has done so far: what its end undoes."""

    touched: bool = False  # the gripper commanded: it is opened
    moved: bool = False  # the arm moved: it returns (once the gripper opened)
    trace: asyncio.Task | None = None  # the gripper trace: ended


def _ended_by(outcome: PressOutcome, exc: Exception) -> None:
    """Said on ``outcome``: what ended the press before its stop and hold were through."""
    if isinstance(exc, _AbortRequested):
        outcome.result, outcome.message = PressResult.ABORTED, "aborted on request"
    elif isinstance(exc, StaleSensorError):
        outcome.result, outcome.message = PressResult.STALE, str(exc)
    elif isinstance(exc, EdgeError):
        outcome.result, outcome.message = PressResult.ERROR, str(exc)
        log.error("press failed: %s", exc)
    else:
        # A bug must still end in an open gripper and a press that says what went wrong.
        log.exception("press failed on an unexpected error")
        outcome.result = PressResult.ERROR
        outcome.message = f"internal error: {type(exc).__name__}: {exc}"


def _stalled(trace: list[GripperState], cap_ma: float) -> bool:
    """Whether the gripper has squeezed at its current cap without moving for ``STALL_S``
    up to its latest traced state."""
    last = trace[-1]
    since = last.t
    for s in reversed(trace):
        if (s.squeeze_ma < STALL_CURRENT_FRACTION * cap_ma
                or abs(s.width_m - last.width_m) > STALL_TRAVEL_M):
            break
        since = s.t
    return last.t - since >= STALL_S


def _say(outcome: PressOutcome, text: str) -> None:
    """Add ``text`` to what the outcome says."""
    outcome.message = f"{outcome.message}; {text}" if outcome.message else text


def outcome_recording(outcome: PressOutcome, cfg: Config, label: str = "unknown"
                      ) -> recording.Recording:
    """The stored form of a press (recordings format): raw window, tare, gripper trace."""
    win = outcome.window
    if win is None or outcome.t_stop is None or outcome.tare is None:
        raise EdgeError(f"press has no window to record ({outcome.result}: {outcome.message})")
    trace = outcome.gripper_trace
    return recording.Recording(
        frames=win.raw, recv_time=win.recv_time, sensor_time=win.sensor_time, seq=win.seq,
        tare=outcome.tare, t_stop=outcome.t_stop, label=label, threshold=cfg.press.x_th,
        sensor_model=cfg.sensor.model,
        gripper_time=np.array([s.t for s in trace], dtype=np.float64),
        gripper_width_m=np.array([s.width_m for s in trace], dtype=np.float64),
        gripper_current_ma=np.array([s.squeeze_ma for s in trace], dtype=np.float64),
        source=cfg.mode,
        extra={"stop_latency_s": outcome.stop_latency_s, "t_cross": outcome.t_cross,
               "peak_level": outcome.peak_level, "result": outcome.result,
               # The gripper goals the press wrote, for exports that carry them as actions.
               "t_open": outcome.summary().entered(PressState.OPENING),
               "gripper_goal_m": {"open": cfg.press.open_width_m,
                                  "closed": GRIPPER_CLOSED_WIDTH_M}}
        | PadLayout.of(cfg.sensor).extra())
