"""Teaching the running robot: an object pressed a few times and named, or an episode's press
named for what it really was, added to the references taught beside the model
(:mod:`edge.runtime.references`); the next recognition looks presses up with them.

The daemon owns the bus, so teaching presses through the recognizer, one press at a time,
each a press with no VLM question (``Recognizer.recognize(..., ask=False)``: an episode with
status ``pressed`` and its recording), taught in the compute process
(:func:`edge.runtime.compute.teach_press`). Everything that would refuse the presses is
checked before the arm moves: the label, the description (it names the object, never how it
feels), ``append`` for a label the database already has, and the robot's ``[press] x_th``
and its stream's rate against the class's (:meth:`ReferenceStore.check`).

Between presses the operator is asked to move the object slightly (a :class:`TeachProgress`
event with step ``move``, shown by the page and logged) and the teacher pauses ``pause_s``:
a pause, not a shifted arm, since the arm's poses are taught joint positions and a shift of
a few millimetres in the gripper's frame would need the arm's kinematics. One teaching at a
time; while it runs, a recognition through the runtime is refused as busy.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from edge.core import recording
from edge.core.errors import BadRequest, BusyError, EdgeError, NotFoundError, StateError
from edge.core.model import ModelRef
from edge.runtime.compute import model_for, teach_press
from edge.runtime.domain import Status, TeachProgress, TeachRun, TeachStep
from edge.runtime.references import ReferenceStore, Source, TaughtReference

if TYPE_CHECKING:
    from edge.runtime.events import EventBus
    from edge.runtime.recognition import Recognizer

log = logging.getLogger(__name__)

# Presses one teaching may ask for: enough for a class (a built one has 10), few enough that
# a typo cannot keep the robot busy for long.
MAX_PRESSES = 10
# Between presses, how long the operator has to move the object slightly (default, and most).
PAUSE_S = 5.0
MAX_PAUSE_S = 60.0
# The recording of a taught episode's press, as the store keeps it.
PRESS_FILE = "press.press.npz"

def check_teach(ref: ModelRef, label: str, description: str | None, source: Source,
                append: bool, x_th: float, rate_hz: float | None) -> str:
    """In the compute process: what would refuse presses of ``label``
    (:meth:`ReferenceStore.check` against the model loaded there); the description they
    would be taught with."""
    return _store(ref).check(model_for(ref), label, description, source=source, append=append,
                             x_th=x_th, rate_hz=rate_hz)


def teach_file(ref: ModelRef, path: str, label: str, description: str | None, source: Source,
               episode: str, append: bool) -> TaughtReference:
    """In the compute process: the press recorded at ``path`` taught as ``label``."""
    return teach_press(ref, recording.load(path), label, description, source, episode, append)


def _store(ref: ModelRef) -> ReferenceStore:
    if ref.references is None:
        raise BadRequest(f"{ref.directory}: no directory for taught references is configured")
    return ReferenceStore(ref.references)


class Teacher:
    """Teaches through the daemon's recognizer. ``stream_rate`` measures the tactile
    stream's rate now (frames/s; None: not measured)."""

    def __init__(self, recognizer: Recognizer, events: EventBus,
                 stream_rate: Callable[[], float | None]) -> None:
        self.recognizer = recognizer
        self.events = events
        self.stream_rate = stream_rate
        self.current: TeachRun | None = None  # the teaching running, or the last one
        self._task: asyncio.Task[TeachRun] | None = None
        # The references another model embedded, as last read (the health says them).
        self.stale: tuple[TaughtReference, ...] = ()

    @property
    def active(self) -> bool:
        return self._task is not None and not self._task.done()

    async def teach(self, label: str, description: str | None, presses: int = 1,
                    append: bool = False, source: Source = "api", *, pause_s: float = PAUSE_S,
                    wait: bool = True) -> TeachRun:
        """Press the object ``presses`` times (1..``MAX_PRESSES``, ``pause_s`` apart: up to
        ``MAX_PAUSE_S``, checked by the interfaces) and teach each press as ``label``. Refused
        before the arm moves (:class:`BadRequest`, one line) where a press would be; a
        press running or a teaching under way: :class:`BusyError`. With ``wait``, the
        teaching once it ended (``failed`` with why where a press failed: the presses taught
        before it stay); without, as it started (follow its :class:`TeachProgress` events
        or :attr:`current`)."""
        self._check_idle()
        setup = self.recognizer.setup
        described = await self.recognizer.compute.run(
            check_teach, setup.model, label, description, source, append,
            setup.cfg.press.x_th, self.stream_rate())
        self._check_idle()  # (a press may have begun while the check ran)
        teaching = TeachRun(label, described, presses, append, source)
        self.current = teaching
        self._task = asyncio.create_task(self._run(teaching, pause_s), name=f"teach {label}")
        if not wait:
            return teaching
        return await asyncio.shield(self._task)

    def _check_idle(self) -> None:
        if self.active:
            assert self.current is not None
            raise BusyError(f"teaching {self.current.label!r} is under way; one at a time")
        if self.recognizer.lock.locked():
            raise BusyError(f"a press is running (episode {self.recognizer.current}); one at "
                            "a time", self.recognizer.current)

    async def _run(self, teaching: TeachRun, pause_s: float) -> TeachRun:
        label, n = teaching.label, teaching.presses
        try:
            for i in range(1, n + 1):
                if i > 1:
                    message = (f"move the {label} slightly on the table: press {i} of {n} "
                               f"in {pause_s:g} s")
                    log.info("teaching %s: %s", label, message)
                    self._publish(teaching, "move", i, message=message)
                    await asyncio.sleep(pause_s)
                t0 = time.monotonic()
                self._publish(teaching, "pressing", i)
                episode = await self.recognizer.recognize(
                    [label], None, True, None, teaching.source, ask=False)
                teaching.episodes.append(episode.id)
                if episode.status != Status.PRESSED:
                    raise StateError(f"press {i} of {n} (episode {episode.id}) ended "
                                     f"{episode.status}: {episode.why or 'no press'}")
                # The first press makes a new class; the next add presses to it.
                ref = await self._teach(episode.id, label, teaching.description,
                                        teaching.source, teaching.append or i > 1)
                teaching.references.append(ref.id)
                teaching.press_s.append(time.monotonic() - t0)
                self._publish(teaching, "taught", i, episode.id, ref.id)
            teaching.status = "done"
            log.info("taught %s: %d presses (%s), %.1f s a press", label, n,
                     ", ".join(teaching.references), sum(teaching.press_s) / n)
            self._publish(teaching, "done", n)
        except asyncio.CancelledError:
            teaching.status, teaching.error = "failed", "the daemon stopped"
            self._publish(teaching, "failed", len(teaching.episodes), message=teaching.error)
            raise
        except Exception as exc:
            # Said on the teaching (a bug included: it must not read "running" forever).
            why = str(exc) if isinstance(exc, EdgeError) else f"{type(exc).__name__}: {exc}"
            teaching.status, teaching.error = "failed", why
            log.error("teaching %s stopped after %d of %d presses: %s", label,
                      len(teaching.references), n, why,
                      exc_info=not isinstance(exc, EdgeError))
            self._publish(teaching, "failed", len(teaching.episodes), message=why)
        return teaching

    async def teach_episode(self, episode_id: str, label: str, description: str | None,
                            source: Source = "api") -> TaughtReference:
        """What the object of episode ``episode_id`` really was: its press taught as
        ``label`` (more presses of a label the database has, or a new class with its
        description). :class:`NotFoundError` for an unknown episode or one without a press;
        :class:`BadRequest` where the reference rules refuse it."""
        episode = await self.recognizer.episode(episode_id)
        if not episode.status.final:
            raise StateError(f"episode {episode_id} is {episode.status}: teach it once it "
                             "has ended")
        return await self._teach(episode_id, label, description, source, True)

    async def _teach(self, episode_id: str, label: str, description: str | None,
                     source: str, append: bool) -> TaughtReference:
        try:
            path = self.recognizer.store.file(episode_id, PRESS_FILE)
        except NotFoundError:
            raise NotFoundError(f"episode {episode_id} has no press recording to teach "
                                "(its press failed before the window)") from None
        return await self.recognizer.compute.run(
            teach_file, self.recognizer.setup.model, str(path), label, description, source,
            episode_id, append)

    def _publish(self, teaching: TeachRun, step: TeachStep, press: int, episode: str | None = None,
                 reference: str | None = None, message: str | None = None) -> None:
        self.events.publish(TeachProgress(
            teaching.label, step, press, teaching.presses, episode, reference, message,
            teaching))

    # --- the references ------------------------------------------------------------------
    async def references(self) -> dict[str, Any]:
        """Every taught reference (``stale``: another model embedded it, not used)."""
        model = self.recognizer.setup.model
        store = _store(model)
        overlay = await asyncio.to_thread(store.load, model.digest)
        return {"directory": str(store.root), "references": overlay.to_json()}

    async def remove(self, ref_id: str | None = None, label: str | None = None
                     ) -> list[TaughtReference]:
        """Remove the reference ``ref_id``, or every one of ``label``; the next press is
        looked up without them. :class:`NotFoundError` where there is none."""
        store = _store(self.recognizer.setup.model)
        if ref_id is not None:
            removed = [await asyncio.to_thread(store.remove, ref_id)]
        elif label is not None:
            removed = await asyncio.to_thread(store.remove_label, label)
        else:
            raise BadRequest("say which references to remove: an id, or a label")
        if {ref.id for ref in removed} & {ref.id for ref in self.stale}:
            await self.check_references()
        return removed

    async def check_references(self) -> None:
        """Read the taught references as the daemon's model sees them and log what is used
        (those another model embedded are logged as not used, by the store); a malformed
        index: :class:`ModelError` naming the file and field (the compute process refuses it
        at start and on reload, before this); those another model embedded are kept in
        :attr:`stale`."""
        model = self.recognizer.setup.model
        if model.references is None:
            self.stale = ()
            return
        overlay = await asyncio.to_thread(ReferenceStore(model.references).load, model.digest)
        self.stale = overlay.stale
        if overlay.current or overlay.stale:
            log.info("taught references in %s: %d used (%s), %d not used", model.references,
                     len(overlay.current), ", ".join(sorted(overlay.labels())) or "none",
                     len(overlay.stale))

    async def stop(self) -> None:
        """End a teaching under way (the daemon stops): its press is aborted by the
        runtime, the presses taught so far stay."""
        if self._task is not None and not self._task.done():
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task


def listed(ref: TaughtReference) -> dict[str, Any]:
    """A taught reference as the interfaces list it: without its embedding."""
    return {k: v for k, v in ref.to_json().items() if k not in ("z", "code")}


__all__ = ["MAX_PAUSE_S", "MAX_PRESSES", "PAUSE_S", "Teacher",
           "check_teach", "listed", "teach_file"]
