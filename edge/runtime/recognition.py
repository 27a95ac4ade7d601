"""Recognition: one press -> its analysis in the compute process -> the VLM -> a stored
episode; and the retry of episodes whose VLM question is still due.

One press at a time (a second trigger gets :class:`BusyError` and never moves the arm). An
episode is noted as accepted (written and fsynced) before the press runs, so a store that
cannot write refuses the press before the arm moves; it is kept whole (the store writes
atomically, or holds it in memory until it can) whatever happens to the press, and waits
``pending`` while the VLM cannot be reached; the retry task asks again with capped
exponential backoff, also after a restart.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from edge import __version__
from edge.core import recording
from edge.core.backoff import backoff_s
from edge.core.config import Config
from edge.core.errors import (
    BusyError,
    ComputeError,
    EdgeError,
    ImageError,
    ModelError,
    NotFoundError,
    SensorError,
    StateError,
    StoreError,
    VLMUnavailableError,
)
from edge.core.model import ModelRef
from edge.hw.contracts import Camera
from edge.runtime.compute import Analysis, ComputeWorker, analyse_press
from edge.runtime.domain import (
    Episode,
    EpisodeFinished,
    EpisodeStarted,
    EventBus,
    Label,
    Neighbour,
    Status,
    TactileResult,
    VLMRefused,
    VLMUnreachable,
)
from edge.runtime.metrics import Metrics
from edge.runtime.press import PressController, PressOutcome, outcome_recording
from edge.runtime.startcheck import needs_photo
from edge.runtime.store import EpisodeStore, new_id
from edge.vlm.client import VLMClient
from edge.vlm.images import VLMImage, prepare_for_vlm

log = logging.getLogger(__name__)

# How many episodes that could not be stored at all (disk full) are remembered, for
# whoever asks about them.
UNSTORED_KEPT = 100
# Final statuses a person may have asked again (the server or its settings fixed since).
RE_ASKABLE = (Status.VLM_ERROR, Status.INVALID_ANSWER)


@dataclass
class Recognition:
    """What a recognition runs with; swapped as a whole on reload, between presses."""

    cfg: Config
    model: ModelRef
    vlm: VLMClient


class Recognizer:
    def __init__(self, setup: Recognition, press: PressController,
                 compute: ComputeWorker, store: EpisodeStore, events: EventBus,
                 metrics: Metrics, camera: Camera | None = None) -> None:
        self.setup = setup
        self.press = press
        self.compute = compute
        self.store = store
        self.events = events
        self.metrics = metrics
        self.camera = camera
        self.lock = asyncio.Lock()  # held while a press runs
        self.current: str | None = None  # the episode whose press runs
        self.accepting = True
        # Why no press may start although the daemon serves (torque off: no sensor stream
        # since the start, a layout refused); None when presses are taken.
        self.refusal: str | None = None
        self.work: set[asyncio.Task] = set()  # recognitions in flight
        self._spawn: Callable[..., asyncio.Task] = asyncio.create_task
        self._retry_wakeup = asyncio.Event()
        # Episodes whose VLM question is in flight: never asked twice at once.
        self._asking: set[str] = set()
        # Episodes that could not be written at all (disk full): why, for whoever asks.
        self._unstored: dict[str, str] = {}

    def spawn_in(self, tg: asyncio.TaskGroup) -> None:
        """Run recognitions inside the daemon's root TaskGroup."""
        self._spawn = tg.create_task

    # --- triggering -------------------------------------------------------------------
    async def recognize(self, candidates: list[str], image: bytes | None, wait: bool,
                        timeout_s: float | None, source: str, ask: bool = True) -> Episode:
        """Start a recognition: a press, its analysis and, unless ``ask`` is false (a press
        to teach from: no photo, no question), the VLM's question; the episode as it runs,
        or with ``wait`` as stored once it ends (``pressed`` where nothing was asked)."""
        if not self.accepting:
            raise BusyError("the daemon is shutting down; not starting a press")
        if self.refusal is not None:
            raise SensorError(self.refusal)
        full = self.store.space_error()
        if full:
            raise StoreError(f"not pressing: the episode could not be kept: {full}")
        if self.lock.locked():
            raise BusyError(f"a press is running (episode {self.current}); one at a time",
                            self.current)
        episode_id = new_id()
        self.current = episode_id
        await self.lock.acquire()  # free: checked above, no await in between
        try:
            # Written and fsynced before anything moves: no press without a place to keep it.
            await asyncio.to_thread(self.store.accept, episode_id, candidates, source)
        except StoreError as exc:
            self.current = None
            self.lock.release()
            raise StoreError(f"not pressing: {exc}") from None
        done = asyncio.get_running_loop().create_future()
        task = self._spawn(self._recognize(episode_id, candidates, image, source, ask, done),
                           name=f"recognize {episode_id}")
        self.work.add(task)
        task.add_done_callback(self.work.discard)
        running = Episode(episode_id, Status.RUNNING, candidates, source)
        if not wait:
            return running
        try:
            await asyncio.wait_for(asyncio.shield(done), timeout_s)
        except TimeoutError:
            return running.with_(note=f"not finished within {timeout_s} s; poll "
                                      f"/v1/episodes/{episode_id}")
        return await self.episode(episode_id)

    async def trigger_default(self, source: str) -> None:
        """A button or a signal: the configured default candidates, the camera's photo."""
        candidates = list(self.setup.cfg.api.default_candidates)
        if not candidates:
            log.warning("%s trigger ignored: api.default_candidates is empty", source)
            return
        try:
            episode = await self.recognize(candidates, None, False, None, source)
            log.info("%s trigger: episode %s", source, episode.id)
        except EdgeError as exc:  # busy, refused (no sensor stream), the store full
            log.warning("%s trigger ignored: %s", source, exc)

    async def episode(self, episode_id: str) -> Episode:
        try:
            return await asyncio.to_thread(self.store.get, episode_id)
        except NotFoundError:
            if episode_id in self._unstored:
                raise StoreError(self._unstored[episode_id]) from None
            raise

    # --- one recognition ----------------------------------------------------------------
    async def _recognize(self, episode_id: str, candidates: list[str], image: bytes | None,
                         source: str, ask: bool, done: asyncio.Future) -> None:
        t0 = time.monotonic()
        setup = self.setup  # one configuration for the whole episode
        asking: asyncio.Task[Episode | None] | None = None
        photo: asyncio.Task | None = None
        # The episode as this recognition leaves it (running: cancelled before it was kept).
        final = Episode(episode_id, Status.RUNNING, candidates, source)
        try:
            self.events.publish(EpisodeStarted(episode_id))
            loop = asyncio.get_running_loop()
            window: asyncio.Future[PressOutcome] = loop.create_future()
            checked: asyncio.Future[None] = loop.create_future()
            pressing = self._start_press(window, checked)
            # Taken (unless given) and prepared for the VLM while the arm moves.
            photo = (asyncio.create_task(self._photo(setup, episode_id, image, checked),
                                         name="photo") if ask else None)
            try:
                # The press as of its complete window (it goes on: the gripper opens, the arm
                # returns), or as it ended without one.
                await asyncio.wait({window, pressing}, return_when=asyncio.FIRST_COMPLETED)
                outcome = window.result() if window.done() else pressing.result()
                episode = Episode(episode_id, Status.RUNNING, candidates, source,
                                  software_version=__version__, x_th=setup.cfg.press.x_th,
                                  vlm_mode=setup.vlm.mode)
                episode, files = await self._analyse(setup, episode, outcome)
                if not ask and episode.status == Status.PENDING:
                    episode = episode.with_(status=Status.PRESSED)
                image, prepared, camera_error = (await photo if photo is not None
                                                 else (None, None, None))
                if image is not None:
                    kind = ".png" if image.startswith(b"\x89PNG") else ".jpg"
                    files["image" + kind] = image
                if (camera_error is not None and episode.status == Status.PENDING
                        and needs_photo(setup.vlm.mode)):
                    # The VLM would refuse the question without its photo: the camera is why.
                    episode = episode.with_(status=Status.CAMERA_ERROR, error=camera_error)
                stored: asyncio.Future[Episode] = loop.create_future()
                if episode.status == Status.PENDING:
                    # Asked while the arm returns; the answer is stored once the episode is.
                    asking = asyncio.create_task(self._ask(
                        episode, prepared if prepared is not None else image, setup.vlm,
                        stored), name=f"ask {episode_id}")
                outcome = await pressing
            except asyncio.CancelledError:
                pressing.cancel()
                raise
            # The whole recording (the window's margins came in after the question left).
            files.update(await self._press_file(setup, outcome))
            self.metrics.observe_press(outcome)
            episode = episode.with_(press=outcome.summary(),
                                    timings={"press_s": time.monotonic() - t0,
                                             **episode.timings})
            if episode.status in (Status.PENDING, Status.PRESSED) and not outcome.contact:
                # The return failed after the window: said on the episode, as without a label.
                episode = episode.with_(status=Status.FAILED, error=outcome.message)
            if asking is None:
                await asyncio.to_thread(self.store.create, episode, files)
                if episode.status == Status.PRESSED:
                    self.events.publish(TactileResult(episode))
                final = episode
                return
            # The durable write (~10 ms of fsyncs) overlaps the VLM request. A crash before
            # the write completes loses the press, as it would have a moment earlier.
            created = loop.run_in_executor(None, self.store.create, episode, files)
            created.add_done_callback(self._tactile_event(episode))
            await created
            stored.set_result(episode)
            final = await asking or episode
        except EdgeError as exc:
            log.error("episode %s failed: %s", episode_id, exc)
            final = await self._keep_failure(episode_id, candidates, source, exc)
        except Exception as exc:
            log.exception("episode %s failed", episode_id)
            final = await self._keep_failure(episode_id, candidates, source, exc)
        finally:
            if photo is not None and not photo.done():
                photo.cancel()  # the episode failed before it needed the photo
            if asking is not None and not asking.done():
                asking.cancel()  # its episode was never stored
            if self.current == episode_id:
                self.current = None
            if not done.done():
                done.set_result(None)
            self.events.publish(EpisodeFinished(final))

    def _start_press(self, window: asyncio.Future[PressOutcome],
                     checked: asyncio.Future[None]) -> asyncio.Task:
        """The press as a task that releases the lock once it has ended: the arm is back
        (or left where it stands), whatever the recognition does meanwhile. ``checked``
        is resolved by its motor check, or by its end where it never got that far."""
        try:
            pressing = asyncio.create_task(self.press.run(window, checked), name="press")
        except BaseException:
            self.lock.release()
            raise

        def ended(_: asyncio.Task) -> None:
            self.lock.release()
            if not checked.done():
                checked.set_result(None)

        pressing.add_done_callback(ended)
        return pressing

    async def _keep_failure(self, episode_id: str, candidates: list[str], source: str,
                            exc: Exception) -> Episode:
        """The failed episode, stored if it can be (else answered for from memory)."""
        error = str(exc) if isinstance(exc, EdgeError) else f"{type(exc).__name__}: {exc}"
        failed = Episode(episode_id, Status.FAILED, candidates, source, error=error)
        try:
            await asyncio.to_thread(self.store.create, failed, {})
        except StoreError as store_exc:
            # Not even the failure could be kept: answer for it from memory.
            self._unstored[episode_id] = (
                error if isinstance(exc, StoreError)
                else f"{error}; and it could not be stored: {store_exc}")
            while len(self._unstored) > UNSTORED_KEPT:
                self._unstored.pop(next(iter(self._unstored)))
            return failed.with_(error=self._unstored[episode_id])
        except Exception:
            log.exception("episode %s: the failure could not be stored", episode_id)
        return failed

    async def _photo(self, setup: Recognition, episode_id: str, image: bytes | None,
                     checked: asyncio.Future[None]
                     ) -> tuple[bytes | None, VLMImage | None, str | None]:
        """(the photo, its form for the VLM, why the camera gave none): the camera's photo
        unless one was given, prepared in the compute process while the press runs, so
        that the question leaves with no image work once the window is complete."""
        # Once the press has checked the motors (or ended): the photo's work (a capture, an
        # encode, a megabyte handed to the compute process) would otherwise hold the host
        # while the check's round trips wait for it, and the press would start later.
        await asyncio.shield(checked)
        if image is None and self.camera is not None:
            try:
                image = await self.camera.capture()
            except (EdgeError, OSError) as exc:
                why = " ".join(str(exc).split()) or type(exc).__name__
                log.warning("episode %s: camera failed: %s", episode_id, why)
                return None, None, why
        limits = setup.vlm.image_limits()
        if image is None or limits is None:
            return image, None, None
        try:
            # What the VLM client would run itself (its offload is the compute process).
            prepared = await self.compute.run(prepare_for_vlm, image, *limits)
        except (ComputeError, ImageError) as exc:
            # Left to the client, which refuses a photo that cannot be sent.
            log.warning("episode %s: the photo was not prepared ahead: %s", episode_id, exc)
            return image, None, None
        return image, prepared, None

    async def _analyse(self, setup: Recognition, episode: Episode, outcome: PressOutcome
                       ) -> tuple[Episode, dict[str, bytes]]:
        """The episode (``failed``, or ``pending`` for the VLM) and the model's files: one
        round trip to the compute process, on the press's model window."""
        if not outcome.contact or outcome.window is None or len(outcome.window.raw) < 2:
            return (episode.with_(status=Status.FAILED,
                                  error=outcome.message or outcome.result), {})
        t = time.monotonic()
        try:
            rec = outcome_recording(outcome, setup.cfg)
            analysis: Analysis = await self.compute.run(analyse_press, setup.model, rec)
        except EdgeError as exc:
            # E.g. the stream died before the window after the stop was complete: the press
            # is still kept, raw, with why it could not be recognised.
            log.error("episode %s: press not usable for recognition: %s", episode.id, exc)
            why = ("its analysis failed" if isinstance(exc, ComputeError | ModelError)
                   else "its tactile window is unusable")
            return (episode.with_(status=Status.FAILED,
                                  error=f"the press worked but {why}: {exc}"), {})
        episode = episode.with_(
            status=Status.PENDING, code=analysis.code, z=analysis.z,
            topk=[Neighbour(label, d) for label, d in analysis.topk],
            description=analysis.description,
            timings={**episode.timings, "encode_s": time.monotonic() - t})
        return episode, {"model_io.npz": analysis.model_io_npz}

    async def _press_file(self, setup: Recognition, outcome: PressOutcome
                          ) -> dict[str, bytes]:
        """The press as a recording file, when it has a window (a compressed write: CPU
        work for the compute process, or a thread when the process cannot)."""
        try:
            rec = outcome_recording(outcome, setup.cfg)
        except EdgeError:
            return {}  # no stop, no window: nothing was recorded
        try:
            data = await self.compute.run(recording.to_bytes, rec)
        except ComputeError:
            data = await asyncio.to_thread(recording.to_bytes, rec)
        return {"press.press.npz": data}

    def _tactile_event(self, episode: Episode) -> Callable[[asyncio.Future], None]:
        """Publishes the tactile result once the episode is stored (a done-callback)."""
        def done(stored: asyncio.Future) -> None:
            if not stored.cancelled() and stored.exception() is None:
                self.events.publish(TactileResult(episode))
        return done

    # --- the VLM ------------------------------------------------------------------------
    async def _ask(self, episode: Episode, image: bytes | VLMImage | None, vlm: VLMClient,
                   stored: asyncio.Future[Episode] | None = None) -> Episode | None:
        """Ask about ``episode``; ``stored`` (the episode as first written, once it is) is
        awaited before any update. Never two questions about one episode at once. The
        episode as stored with the answer (None if it was being asked about already)."""
        if episode.id in self._asking:
            return None
        self._asking.add(episode.id)
        try:
            return await self._ask_once(episode, image, vlm, stored)
        finally:
            self._asking.discard(episode.id)

    async def _ask_once(self, episode: Episode, image: bytes | VLMImage | None,
                        vlm: VLMClient, stored: asyncio.Future | None) -> Episode:
        t = time.monotonic()
        attempts = episode.attempts + 1
        try:
            answer = await vlm.ask(image, episode.description or "", episode.candidates or [])
        except EdgeError as exc:
            if stored is not None:
                episode = await stored
            self.metrics.vlm_errors += 1
            if episode.status == Status.FAILED:
                # The press failed after its window (the arm did not return): that stays
                # the episode's status; asking again would not fix it.
                return await asyncio.to_thread(self.store.update, episode.id,
                                               attempts=attempts, last_error=str(exc))
            if not isinstance(exc, VLMUnavailableError):
                # Refused (4xx), a broken answer or a bad image: asking again will not help.
                log.error("episode %s: VLM error: %s", episode.id, exc)
                refused = await asyncio.to_thread(self.store.update, episode.id,
                                                  status=Status.VLM_ERROR, attempts=attempts,
                                                  last_error=str(exc))
                self.events.publish(VLMRefused(refused))
                return refused
            runtime = self.setup.cfg.runtime
            delay = backoff_s(attempts - 1, runtime.vlm_retry_base_s, runtime.vlm_retry_max_s)
            log.warning("episode %s: VLM unavailable (%s); retry in %.0f s", episode.id, exc,
                        delay)
            # (A re-asked vlm_error or invalid_answer episode waits with the pending ones.)
            pending = await asyncio.to_thread(self.store.update, episode.id,
                                              status=Status.PENDING, attempts=attempts,
                                              last_error=str(exc),
                                              next_retry_at=time.time() + delay)
            self._retry_wakeup.set()  # the retry task plans from the new due time
            self.events.publish(VLMUnreachable(pending))
            return pending
        latency = time.monotonic() - t
        if stored is not None:
            episode = await stored
        self.metrics.observe_vlm(latency, answer.structured_output)
        status = Status.DONE if answer.status == "ok" else Status(answer.status)
        if episode.status == Status.FAILED:
            status = Status.FAILED  # the label is kept; the failed return stays said
        labelled = await asyncio.to_thread(
            self.store.update, episode.id, status=status, label=answer.label,
            vlm=answer.to_dict(), attempts=attempts,
            structured_output=answer.structured_output,
            timings={**episode.timings, "vlm_s": latency})
        self.events.publish(Label(labelled))
        log.info("episode %s: %s%s", episode.id, status,
                 f" -> {answer.label}" if answer.label else "")
        return labelled

    async def retry_pending(self) -> None:
        """The retry task: asks again about every pending episode when it is due."""
        while True:
            # Cleared before the scan: a failure during it (a new due time) wakes the next.
            self._retry_wakeup.clear()
            pending = await asyncio.to_thread(self.store.pending)
            runtime = self.setup.cfg.runtime
            now = time.time()
            next_due = now + runtime.vlm_retry_max_s
            for episode in pending:
                if episode.next_retry_at <= now:
                    try:
                        await self._retry(episode)
                    except Exception:
                        # One broken episode must not stop the daemon or the other retries.
                        log.exception("retrying episode %s failed", episode.id)
                        next_due = min(next_due, now + runtime.vlm_retry_max_s)
                else:
                    next_due = min(next_due, episode.next_retry_at)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._retry_wakeup.wait(),
                                       max(0.05, next_due - time.time()))

    async def retry(self, episode_id: str) -> Episode:
        """Ask again about a ``vlm_error`` or ``invalid_answer`` episode, with its stored
        description and photo, the way the retry task asks a pending one; the episode as
        stored afterwards. :class:`NotFoundError` for an unknown id, :class:`StateError`
        for an episode in another status."""
        episode = await self.episode(episode_id)
        if episode.status not in RE_ASKABLE:
            raise StateError(f"episode {episode_id} is {episode.status}: only "
                             + " or ".join(RE_ASKABLE) + " episodes are asked again")
        if episode.id in self._asking:
            # The retry task is asking about it now: its stored status is about to change.
            raise StateError(f"episode {episode_id} is being asked about now: try again "
                             "once it has an answer")
        await self._retry(episode)
        return await self.episode(episode_id)

    async def _retry(self, episode: Episode) -> None:
        if episode.id in self._asking:
            return
        image = None
        for name in ("image.jpg", "image.png"):
            with contextlib.suppress(NotFoundError):
                path = self.store.file(episode.id, name)
                image = await asyncio.to_thread(path.read_bytes)
        await self._ask(episode, image, self.setup.vlm)

