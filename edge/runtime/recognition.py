"""Recognition: one press -> its analysis in the compute process -> the VLM -> a stored
episode (:class:`OneRecognition`, its stages in order: the press, the photo, the analysis,
the question while the arm returns, the store); and the retry of episodes whose VLM
question is still due. A press may also be kept with no question (``ask=False``: a press
to teach from, stored ``pressed``).

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
from typing import Any, Literal

from edge import __version__
from edge.core import recording
from edge.core.backoff import backoff_s
from edge.core.config import Config
from edge.core.errors import (
    BadRequest,
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
from edge.runtime.compute import Analysis, ComputeWorker, analyse_press, fuse_presses
from edge.runtime.domain import (
    Episode,
    EpisodeFinished,
    EpisodeStarted,
    Label,
    Neighbour,
    PressAgain,
    Status,
    TactileResult,
    VLMRefused,
    VLMUnreachable,
)
from edge.runtime.events import EventBus
from edge.runtime.metrics import Metrics
from edge.runtime.press import PressController, PressOutcome, outcome_recording
from edge.runtime.startcheck import needs_photo
from edge.runtime.store import EpisodeStore, new_id
from edge.runtime.teaching import PAUSE_S
from edge.vlm.client import VLMClient
from edge.vlm.images import VLMImage, check_image, prepare_for_vlm

log = logging.getLogger(__name__)

# How many episodes that could not be stored at all (disk full) are remembered, for
# whoever asks about them.
UNSTORED_KEPT = 100
# Final statuses a person may have asked again (the server or its settings fixed since).
RE_ASKABLE = (Status.VLM_ERROR, Status.INVALID_ANSWER)
# A recognition's presses of one object ({"presses": N}, fused into one question): at most
# this many, or "auto": a second only where the first is unfamiliar or its offsets disagree.
MAX_FUSED_PRESSES = 5
AUTO = "auto"
Presses = int | Literal["auto"]


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
                        timeout_s: float | None, source: str, ask: bool = True,
                        presses: Presses = 1, pause_s: float = PAUSE_S) -> Episode:
        """Start a recognition: a press, its analysis and, unless ``ask`` is false (a press
        to teach from: no photo, no question), the VLM's question; the episode as it runs,
        or with ``wait`` as stored once it ends (``pressed`` where nothing was asked). With
        ``presses`` N (1..``MAX_FUSED_PRESSES``, or ``AUTO``) the object is pressed N times,
        ``pause_s`` apart (the operator moves it slightly), their analyses fused ([runtime]
        fusion) for the one question. An uploaded ``image`` that does not decode is refused
        (:class:`BadRequest`) before anything moves."""
        if image is not None and not ask:
            raise ValueError("a press with no question takes no photo: give no image")
        if presses != AUTO and (type(presses) is not int
                                or not 1 <= presses <= MAX_FUSED_PRESSES):
            raise BadRequest(f"presses must be an integer 1..{MAX_FUSED_PRESSES} or "
                             f"{AUTO!r}, got {presses!r:.40}")
        upload = Photo(image, await self._decoded(image)) if image is not None else None
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
        running = Episode(episode_id, Status.RUNNING, candidates, source)
        done = asyncio.get_running_loop().create_future()
        one = OneRecognition(self, running, upload, ask, presses, pause_s)
        task = self._spawn(self._recognize(one, done), name=f"recognize {episode_id}")
        self.work.add(task)
        task.add_done_callback(self.work.discard)
        if not wait:
            return running
        try:
            await asyncio.wait_for(asyncio.shield(done), timeout_s)
        except TimeoutError:
            return running.with_(note=f"not finished within {timeout_s} s; poll "
                                      f"/v1/episodes/{episode_id}")
        return await self.episode(episode_id)

    async def _decoded(self, image: bytes) -> VLMImage | None:
        """An uploaded image decoded, once, in the compute process (a decoder crash on a
        hostile file costs that process, not the daemon): prepared for the VLM where its
        question takes one, else only checked. :class:`BadRequest` if it does not decode."""
        limits = self.setup.vlm.image_limits()
        try:
            if limits is None:
                await self.compute.run(check_image, image)
                return None
            return await self.compute.run(prepare_for_vlm, image, *limits)
        except (ImageError, ComputeError) as exc:
            raise BadRequest(f"image must be a JPEG or PNG file that decodes: {exc}") from None

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
    async def _recognize(self, recognition: OneRecognition, done: asyncio.Future) -> None:
        """Run ``recognition``; a failure is kept as a failed episode. Whatever happens, the
        press's end frees the lock, waiters are told, and the episode's end is published."""
        started = recognition.episode
        # The episode as this recognition leaves it (running: cancelled before it was kept).
        final = started
        try:
            final = await recognition.run()
        except EdgeError as exc:
            log.error("episode %s failed: %s", started.id, exc)
            final = await self._keep_failure(started, exc)
        except Exception as exc:
            log.exception("episode %s failed", started.id)
            final = await self._keep_failure(started, exc)
        finally:
            recognition.cancel_leftovers()
            if self.current == started.id:
                self.current = None
            if not done.done():
                done.set_result(None)
            self.events.publish(EpisodeFinished(final))

    async def _keep_failure(self, started: Episode, exc: Exception) -> Episode:
        """The ``started`` episode failed with ``exc``: stored if it can be (else answered
        for from memory)."""
        episode_id = started.id
        error = str(exc) if isinstance(exc, EdgeError) else f"{type(exc).__name__}: {exc}"
        failed = started.with_(status=Status.FAILED, error=error)
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

    # --- the VLM ------------------------------------------------------------------------
    async def ask(self, episode: Episode, image: bytes | VLMImage | None, vlm: VLMClient,
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
            reason=answer.reason, vlm=answer.to_dict(), attempts=attempts,
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
        await self.ask(episode, image, self.setup.vlm)



@dataclass(frozen=True)
class Photo:
    """A recognition's photo: as taken or uploaded (kept with the episode), its form for the
    VLM where it was prepared, and why the camera gave none."""

    data: bytes | None
    prepared: VLMImage | None = None
    error: str | None = None

    @property
    def for_vlm(self) -> bytes | VLMImage | None:
        """What the question sends: the prepared form, else the bytes (the client prepares
        them itself, or refuses a photo that cannot be sent)."""
        return self.prepared if self.prepared is not None else self.data


NO_PHOTO = Photo(None)


class OneRecognition:
    """One recognition: its stages in the order they run (:meth:`run`), the press going on
    beside the others. It holds the configuration in force when it began (a reload swaps
    the recognizer's between presses).

    Of several presses, each but the last is analysed and kept while the arm returns, then
    the operator's pause; the last one's analysis is fused with theirs
    (:func:`edge.runtime.compute.fuse_presses`) before the one question. The lock is held
    from the first press until the last has ended."""

    def __init__(self, recognizer: Recognizer, episode: Episode, upload: Photo | None,
                 ask: bool, presses: Presses = 1, pause_s: float = PAUSE_S) -> None:
        self.recognizer = recognizer
        self.setup = recognizer.setup
        self.episode = episode  # as it began (running)
        self.upload = upload  # decoded (and prepared) before anything moved
        self.ask = ask
        self.presses = presses
        self.pause_s = pause_s
        self.t0 = time.monotonic()
        loop = asyncio.get_running_loop()
        self.window: asyncio.Future[PressOutcome] = loop.create_future()
        self.checked: asyncio.Future[None] = loop.create_future()
        self.stored: asyncio.Future[Episode] = loop.create_future()
        self.photo: asyncio.Task[Photo] | None = None
        self.asking: asyncio.Task[Episode | None] | None = None
        # The lock stays held past a press's end while another press may follow.
        self.holding = presses != 1
        self.freed = False
        # Each press so far: its recording (for the fusion) and how it went (the episode's
        # ``presses``); the time the current one began.
        self.recs: list[recording.Recording] = []
        self.pressed: list[dict[str, Any]] = []
        self.press_t0 = self.t0

    async def run(self) -> Episode:
        """The stages in order; the episode as stored (with its answer, if asked)."""
        self.recognizer.events.publish(EpisodeStarted(self.episode.id))
        earlier: dict[str, bytes] = {}  # the files of the presses before the last
        while True:
            pressing = self.press()  # frees the lock once the arm is back from the last
            try:
                if self.photo is None:
                    self.photo = self.take_photo()  # once the motors are checked
                outcome = await self.window_complete(pressing)  # the arm still to return
                episode, files = await self.analysis(outcome)
                if self.again(episode):
                    outcome = await pressing  # the arm back from it, or not
                    if outcome.contact:
                        earlier |= await self.kept_earlier(outcome, files)
                        await self.pause()
                        continue
                    # It did not return: no further press, and the recognition fails with
                    # every press so far kept, as where a later press fails.
                    episode = episode.with_(status=Status.FAILED,
                                            error=outcome.message or str(outcome.result))
                self.last_press(pressing)
                episode, files = await self.fused(episode, files, earlier)
                photo = await self.photo if self.photo is not None else NO_PHOTO
                episode = self.keep_photo(episode, photo, files)
                self.asking = self.question(episode, photo)  # leaves while the arm returns
                outcome = await pressing
            except BaseException as exc:
                self.last_press(pressing)
                if isinstance(exc, asyncio.CancelledError):
                    pressing.cancel()
                raise
            break
        episode = await self.store(episode, outcome, files)
        return (await self.asking or episode) if self.asking is not None else episode

    def cancel_leftovers(self) -> None:
        """After a failure: the photo it never needed, the question about an episode that
        was never stored."""
        for task in (self.photo, self.asking):
            if task is not None and not task.done():
                task.cancel()

    # --- the stages, in order ------------------------------------------------------------
    def press(self) -> asyncio.Task[PressOutcome]:
        """The press as a task that releases the lock once it has ended: the arm is back
        (or left where it stands), whatever the recognition does meanwhile. ``checked``
        is resolved by its motor check, or by its end where it never got that far."""
        recognizer, checked = self.recognizer, self.checked
        self.press_t0 = time.monotonic()
        if self.window.done():  # a press after the first: its own window (the photo
            self.window = asyncio.get_running_loop().create_future()  # waited for the first)
        try:
            pressing = asyncio.create_task(
                recognizer.press.run(self.window, None if checked.done() else checked),
                name="press")
        except BaseException:
            self._free()
            raise

        def ended(_: asyncio.Task) -> None:
            if not self.holding:
                self._free()
            if not checked.done():
                checked.set_result(None)

        pressing.add_done_callback(ended)
        return pressing

    def _free(self) -> None:
        if not self.freed:
            self.freed = True
            self.recognizer.lock.release()

    def last_press(self, pressing: asyncio.Task[PressOutcome]) -> None:
        """``pressing`` is the recognition's last press: the lock is freed as it ends (now,
        if it has)."""
        self.holding = False
        if pressing.done():
            self._free()

    def again(self, episode: Episode) -> bool:
        """Whether the object is pressed again after the press analysed as ``episode``:
        N presses asked for, or ``auto`` and the first is unfamiliar or its subsampling
        offsets disagree on its nearest class."""
        n = len(self.pressed)
        if episode.status == Status.FAILED:
            return False
        if self.presses == AUTO:
            first = self.pressed[0]
            return n == 1 and (bool(first["unfamiliar"]) or first["agreement"] < 1.0)
        return n < self.presses

    async def kept_earlier(self, outcome: PressOutcome, files: dict[str, bytes]
                           ) -> dict[str, bytes]:
        """A press before the last, its arm back: its files (numbered from the second
        press on), for the episode written at the end."""
        n = len(self.pressed)
        self.recognizer.metrics.observe_press(outcome)
        self.pressed[-1]["press_s"] = time.monotonic() - self.press_t0
        return {_numbered(name, n): data
                for name, data in (files | await self._press_file(outcome)).items()}

    async def pause(self) -> None:
        """The operator's time to move the object slightly before the next press (said
        on the event stream and logged)."""
        n = len(self.pressed) + 1
        presses = None if self.presses == AUTO else int(self.presses)
        of = "" if presses is None else f" of {presses}"
        message = f"move the object slightly on the table: press {n}{of} in {self.pause_s:g} s"
        log.info("episode %s: %s", self.episode.id, message)
        self.recognizer.events.publish(
            PressAgain(self.episode.id, n, presses, self.pause_s, message))
        await asyncio.sleep(self.pause_s)

    async def fused(self, episode: Episode, files: dict[str, bytes],
                    earlier: dict[str, bytes]) -> tuple[Episode, dict[str, bytes]]:
        """The last press's episode with the presses' fused analysis, where there were
        several; a failed press of a recognition of several fails it, naming the press,
        with every press so far."""
        n, failed = len(self.pressed), episode.status == Status.FAILED
        if self.presses == 1 or (n == 1 and not failed):  # (auto: one press was enough)
            return episode, files
        files = earlier | {_numbered(name, n): data for name, data in files.items()}
        if failed:
            return episode.with_(error=f"press {n}: {episode.error}",
                                 presses=self.pressed), files
        setup, t = self.setup, time.monotonic()
        fusion = setup.cfg.runtime.fusion
        analysis: Analysis = await self.recognizer.compute.run(
            fuse_presses, setup.model, self.recs, fusion,
            setup.cfg.runtime.unfamiliar_percentile)
        files["model_io-fused.npz"] = analysis.model_io_npz
        return episode.with_(
            code=analysis.code, z=analysis.z,
            topk=[Neighbour(label, d) for label, d in analysis.topk],
            description=analysis.description, familiarity=analysis.familiarity,
            unfamiliar=analysis.unfamiliar, presses=self.pressed, fusion=fusion,
            timings={**episode.timings, "fuse_s": time.monotonic() - t}), files

    def take_photo(self) -> asyncio.Task[Photo] | None:
        """The photo, taken and prepared while the press runs; none for a press with no
        question."""
        if not self.ask:
            return None
        return asyncio.create_task(self._photo(), name="photo")

    async def _photo(self) -> Photo:
        """The upload as decoded, else the camera's photo, prepared for the VLM in the
        compute process, so that the question leaves with no image work once the window is
        complete."""
        if self.upload is not None:
            return self.upload
        # Once the press has checked the motors (or ended): the photo's work (a capture, an
        # encode, a megabyte handed to the compute process) would otherwise hold the host
        # while the check's round trips wait for it, and the press would start later.
        await asyncio.shield(self.checked)
        camera, episode_id = self.recognizer.camera, self.episode.id
        if camera is None:
            return NO_PHOTO
        try:
            image = await camera.capture()
        except (EdgeError, OSError) as exc:
            why = " ".join(str(exc).split()) or type(exc).__name__
            log.warning("episode %s: camera failed: %s", episode_id, why)
            return Photo(None, error=why)
        limits = self.setup.vlm.image_limits()
        if limits is None:
            return Photo(image)
        try:
            # What the VLM client would run itself (its offload is the compute process).
            prepared = await self.recognizer.compute.run(prepare_for_vlm, image, *limits)
        except (ComputeError, ImageError) as exc:
            # Left to the client, which refuses a photo that cannot be sent.
            log.warning("episode %s: the photo was not prepared ahead: %s", episode_id, exc)
            return Photo(image)
        return Photo(image, prepared)

    async def window_complete(self, pressing: asyncio.Task[PressOutcome]) -> PressOutcome:
        """The press as of its complete window (it goes on: the gripper opens, the arm
        returns), or as it ended without one."""
        await asyncio.wait({self.window, pressing}, return_when=asyncio.FIRST_COMPLETED)
        return self.window.result() if self.window.done() else pressing.result()

    async def analysis(self, outcome: PressOutcome) -> tuple[Episode, dict[str, bytes]]:
        """The episode (``failed``; ``pending`` for the VLM, or ``pressed`` with no
        question) and the model's files: one round trip to the compute process, on the
        press's model window."""
        setup = self.setup
        episode = self.episode.with_(software_version=__version__, x_th=setup.cfg.press.x_th,
                                     vlm_mode=setup.vlm.mode)
        self.pressed.append({"t": time.time() - (time.monotonic() - self.press_t0),
                             "result": str(outcome.result)})
        if not outcome.contact or outcome.window is None or len(outcome.window.raw) < 2:
            return (episode.with_(status=Status.FAILED,
                                  error=outcome.message or outcome.result), {})
        t = time.monotonic()
        try:
            rec = outcome_recording(outcome, setup.cfg)
            analysis: Analysis = await self.recognizer.compute.run(
                analyse_press, setup.model, rec, setup.cfg.runtime.unfamiliar_percentile,
                self.presses != 1)
        except EdgeError as exc:
            # E.g. the stream died before the window after the stop was complete: the press
            # is still kept, raw, with why it could not be recognised.
            log.error("episode %s: press not usable for recognition: %s", episode.id, exc)
            why = ("its analysis failed" if isinstance(exc, ComputeError | ModelError)
                   else "its tactile window is unusable")
            return (episode.with_(status=Status.FAILED,
                                  error=f"the press worked but {why}: {exc}"), {})
        episode = episode.with_(
            status=Status.PENDING if self.ask else Status.PRESSED, code=analysis.code,
            z=analysis.z, topk=[Neighbour(label, d) for label, d in analysis.topk],
            description=analysis.description, familiarity=analysis.familiarity,
            unfamiliar=analysis.unfamiliar,
            timings={**episode.timings, "encode_s": time.monotonic() - t})
        self.recognizer.metrics.observe_familiarity(analysis.familiarity, analysis.unfamiliar)
        self.recs.append(rec)
        self.pressed[-1].update(encode_s=episode.timings["encode_s"],
                                topk=episode.topk_json(), familiarity=analysis.familiarity,
                                unfamiliar=analysis.unfamiliar, agreement=analysis.agreement)
        return episode, {"model_io.npz": analysis.model_io_npz}

    def keep_photo(self, episode: Episode, photo: Photo, files: dict[str, bytes]) -> Episode:
        """The photo among the episode's files; ``camera_error`` where the question needs
        the photo the camera did not give (the VLM would refuse it)."""
        if photo.data is not None:
            kind = ".png" if photo.data.startswith(b"\x89PNG") else ".jpg"
            files["image" + kind] = photo.data
        if (photo.error is not None and episode.status == Status.PENDING
                and needs_photo(self.setup.vlm.mode)):
            return episode.with_(status=Status.CAMERA_ERROR, error=photo.error)
        return episode

    def question(self, episode: Episode, photo: Photo) -> asyncio.Task[Episode | None] | None:
        """The VLM asked at once about a ``pending`` episode; its answer is stored once the
        episode is (:attr:`stored`)."""
        if episode.status != Status.PENDING:
            return None
        return asyncio.create_task(
            self.recognizer.ask(episode, photo.for_vlm, self.setup.vlm, self.stored),
            name=f"ask {episode.id}")

    async def store(self, episode: Episode, outcome: PressOutcome, files: dict[str, bytes]
                    ) -> Episode:
        """The episode with its whole press (the window's margins came in after the
        question left), written; its tactile result published."""
        recognizer = self.recognizer
        n = len(self.pressed)
        files.update({_numbered(name, n): data
                      for name, data in (await self._press_file(outcome)).items()})
        recognizer.metrics.observe_press(outcome)
        if episode.presses is not None:  # (as it ended: an arm that did not return, say)
            self.pressed[-1].update(press_s=time.monotonic() - self.press_t0,
                                    result=str(outcome.result))
        episode = episode.with_(press=outcome.summary(),
                                timings={"press_s": time.monotonic() - self.t0,
                                         **episode.timings})
        if episode.status in (Status.PENDING, Status.PRESSED) and not outcome.contact:
            # The return failed after the window: said on the episode (naming the press, of
            # several), as without a label.
            press = "" if episode.presses is None else f"press {n}: "
            episode = episode.with_(status=Status.FAILED, error=press + outcome.message)
        # The durable write (~10 ms of fsyncs) overlaps the VLM request. A crash before
        # the write completes loses the press, as it would have a moment earlier.
        await asyncio.to_thread(recognizer.store.create, episode, files)
        if episode.topk is not None:
            recognizer.events.publish(TactileResult(episode))
        self.stored.set_result(episode)
        return episode

    async def _press_file(self, outcome: PressOutcome) -> dict[str, bytes]:
        """The press as a recording file, when it has a window (a compressed write: CPU
        work for the compute process, or a thread when the process cannot)."""
        try:
            rec = outcome_recording(outcome, self.setup.cfg)
        except EdgeError:
            return {}  # no stop, no window: nothing was recorded
        try:
            data = await self.recognizer.compute.run(recording.to_bytes, rec)
        except ComputeError:
            data = await asyncio.to_thread(recording.to_bytes, rec)
        return {"press.press.npz": data}


def _numbered(name: str, press: int) -> str:
    """An episode file's name for its ``press``-th press: the first's as one press's
    (``press.press.npz``), the next numbered (``press-2.press.npz``, ``model_io-2.npz``)."""
    if press <= 1:
        return name
    stem, dot, ext = name.partition(".")
    return f"{stem}-{press}{dot}{ext}"
