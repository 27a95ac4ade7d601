"""The on-robot daemon: one asyncio loop, one root TaskGroup, every task named.

Tasks: ``sensor`` (frames -> ring buffer + per-frame threshold), ``sampler`` (125 Hz),
``api`` (HTTP), ``button``, ``vlm-retry`` (pending episodes), ``watchdog`` (sd_notify only
while frames keep arriving), and one ``recognize`` task per request. The bus has its own
owner thread (:mod:`edge.hw.dynamixel`). Signals set events: SIGTERM/SIGINT stop taking
work, open the gripper and flush the store; SIGHUP reloads model, database and press
settings between presses; SIGUSR1 triggers a recognition with the default candidates.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import asdict, dataclass, replace
from typing import Any, TypeVar

import numpy as np

from edge import __version__
from edge.core import recording
from edge.core.config import Config
from edge.core.errors import (
    BusyError,
    ComputeError,
    EdgeError,
    ModelError,
    NotFoundError,
    SensorError,
    StaleSensorError,
    StoreError,
)
from edge.core.model import ModelRef
from edge.core.vlm import VLMUnavailableError
from edge.daemon.compute import ComputeWorker, analyse_press, warm_up
from edge.daemon.metrics import Metrics
from edge.daemon.press import PressController, PressOutcome, outcome_recording
from edge.daemon.sensor import FrameRing, Sampler
from edge.daemon.services import optional_services
from edge.daemon.store import EpisodeStore, new_id
from edge.daemon.systemd import Notifier, watchdog_period_s

log = logging.getLogger(__name__)
T = TypeVar("T")

RING_SECONDS = 30.0
SENSOR_RETRY_S = 0.2
EVENT_QUEUE = 256
FIRST_FRAME_TIMEOUT_S = 5.0


@dataclass
class Devices:
    """Everything the daemon talks to; built by :mod:`edge.daemon.devices`."""

    tactile: Any  # TactileSource
    gripper: Any  # Gripper
    arm: Any  # Arm
    camera: Any | None = None  # Camera
    button: Any | None = None  # Button
    bus: Any | None = None  # DynamixelBus: closed (safe pose, torque off) on shutdown


class Runtime:
    def __init__(self, cfg: Config, devices: Devices, model: ModelRef, vlm: Any,
                 store: EpisodeStore, compute: ComputeWorker,
                 notifier: Notifier | None = None, reload: Any = None) -> None:
        self.cfg = cfg
        self.devices = devices
        self.model = model
        self.compute = compute
        self.vlm = vlm
        self.store = store
        self.notifier = notifier or Notifier("")
        self._reload = reload  # callable returning (cfg, model, vlm) on SIGHUP
        rate = 125.0
        self.ring = FrameRing(cfg.sensor.channels, int(RING_SECONDS * rate * 1.5))
        self.sampler = Sampler(self.ring, rate)
        self.metrics = Metrics()
        recover = devices.bus.recover_watchdog if devices.bus is not None else None
        self.press = PressController(cfg, devices.gripper, devices.arm, self.ring,
                                     on_state=self._on_press_state, recover=recover)
        self._press_lock = asyncio.Lock()
        self._current: str | None = None
        self._subscribers: set[asyncio.Queue] = set()
        self._stopping = asyncio.Event()
        self._tg: asyncio.TaskGroup | None = None
        self._work: set[asyncio.Task] = set()
        self._retry_wakeup = asyncio.Event()
        # Episodes whose VLM question is in flight: never asked twice at once.
        self._asking: set[str] = set()
        # Episodes that could not be written at all (disk full): why, for whoever asks.
        self._unstored: dict[str, str] = {}
        self.ready = asyncio.Event()
        self.started_at = time.monotonic()

    # --- events -----------------------------------------------------------------------
    def publish(self, event: dict[str, Any]) -> None:
        event = {"t": time.time(), **event}
        for queue in list(self._subscribers):
            if queue.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    queue.get_nowait()  # a slow client loses the oldest event, not the daemon
            queue.put_nowait(event)

    async def subscribe(self) -> AsyncIterator[dict[str, Any]]:
        queue: asyncio.Queue = asyncio.Queue(EVENT_QUEUE)
        self._subscribers.add(queue)
        try:
            yield {"type": "hello", "state": self.press.state, "episode": self._current}
            while True:
                yield await queue.get()
        finally:
            self._subscribers.discard(queue)

    def _on_press_state(self, state: str) -> None:
        self.publish({"type": "state", "state": state, "episode": self._current})

    # --- the tasks --------------------------------------------------------------------
    async def _sensor(self) -> None:
        source = self.devices.tactile
        while True:
            try:
                async for frame in source.frames():
                    self.ring.push(frame.raw, frame.recv_time, frame.sensor_time, frame.seq)
                    self.metrics.frames += 1
                    await self.press.on_frame(frame.raw, frame.recv_time)
                    if self.press.sensor_is_stale:
                        self.press.sensor_fresh()
                        log.info("tactile stream fresh again")
            except StaleSensorError as exc:
                if not self.press.sensor_is_stale:
                    log.warning("%s", exc)
                self.metrics.stale_events += 1
                self.press.sensor_stale(exc)
            except SensorError as exc:
                # A wrong layout is fatal for pressing; keep serving the API and say why.
                log.error("tactile sensor unusable: %s", exc)
                self.press.sensor_stale(exc)
                self.notifier.status(f"sensor error: {exc}")
            except Exception as exc:
                # A bug on the sensor path must not take the daemon (and the arm) down.
                log.exception("sensor task error")
                self.press.sensor_stale(exc)
            await asyncio.sleep(SENSOR_RETRY_S)

    async def _watchdog(self) -> None:
        period = watchdog_period_s()
        if period is None:
            return
        while True:
            await asyncio.sleep(period)
            # WATCHDOG=1 only while the sensor path makes progress.
            if time.monotonic() - self.ring.latest_time() < max(1.0, period):
                self.notifier.watchdog()

    async def _button(self) -> None:
        button = self.devices.button
        if button is None:
            return
        async for _ in button.presses():
            await self._trigger_default("button")

    async def _trigger_default(self, source: str) -> None:
        candidates = list(self.cfg.api.default_candidates)
        if not candidates:
            log.warning("%s trigger ignored: api.default_candidates is empty", source)
            return
        try:
            episode = await self.recognize(candidates, None, False, None, source)
            log.info("%s trigger: episode %s", source, episode["id"])
        except BusyError as exc:
            log.warning("%s trigger ignored: %s", source, exc)

    async def _vlm_retry(self) -> None:
        cfg = self.cfg.runtime
        while True:
            # Cleared before the scan: a failure during it (a new due time) wakes the next.
            self._retry_wakeup.clear()
            pending = await asyncio.to_thread(self.store.pending)
            now = time.time()
            next_due = now + cfg.vlm_retry_max_s
            for episode in pending:
                due = episode.get("next_retry_at", 0.0)
                if due <= now:
                    try:
                        await self._ask_vlm(episode["id"], retry=True)
                    except Exception:
                        # One broken episode must not stop the daemon or the other retries.
                        log.exception("retrying episode %s failed", episode["id"])
                        next_due = min(next_due, now + cfg.vlm_retry_max_s)
                else:
                    next_due = min(next_due, due)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._retry_wakeup.wait(),
                                       max(0.05, next_due - time.time()))

    # --- recognition ------------------------------------------------------------------
    async def recognize(self, candidates: list[str], image: bytes | None, wait: bool,
                        timeout_s: float | None, source: str) -> dict[str, Any]:
        if self._stopping.is_set():
            raise BusyError("the daemon is shutting down; not starting a press")
        full = self.store.space_error()
        if full:
            raise StoreError(f"not pressing: the episode could not be kept: {full}")
        if self._press_lock.locked():
            raise BusyError(f"a press is running (episode {self._current}); one at a time",
                            self._current)
        episode_id = new_id()
        self._current = episode_id
        await self._press_lock.acquire()  # free: checked above, no await in between
        done = asyncio.get_running_loop().create_future()
        # Inside the root TaskGroup when running (its failures are caught in _recognize).
        spawn = self._tg.create_task if self._tg is not None else asyncio.create_task
        task = spawn(self._recognize(episode_id, candidates, image, source, done),
                     name=f"recognize {episode_id}")
        self._work.add(task)
        task.add_done_callback(self._work.discard)
        if not wait:
            return {"id": episode_id, "status": "running", "candidates": candidates}
        try:
            await asyncio.wait_for(asyncio.shield(done), timeout_s)
        except TimeoutError:
            return {"id": episode_id, "status": "running", "candidates": candidates,
                    "note": f"not finished within {timeout_s} s; poll /v1/episodes/{episode_id}"}
        return await self.episode(episode_id)

    async def _recognize(self, episode_id: str, candidates: list[str], image: bytes | None,
                         source: str, done: asyncio.Future) -> None:
        t0 = time.monotonic()
        timings: dict[str, float] = {}
        # Noted while the press starts (its fsyncs off the loop): a crash before the episode
        # is kept leaves it "interrupted" after the restart, not unknown.
        noted = asyncio.get_running_loop().run_in_executor(
            None, self.store.accept, episode_id, candidates, source)
        try:
            self.publish({"type": "episode", "episode": episode_id, "status": "running"})
            camera_task = None
            if image is None and self.devices.camera is not None:
                # The photo is taken while the arm moves.
                camera_task = asyncio.create_task(self.devices.camera.capture(), name="camera")
            try:
                outcome = await self.press.run()
            finally:
                self._press_lock.release()
            timings["press_s"] = time.monotonic() - t0
            self.metrics.observe_press(outcome)
            if camera_task is not None:
                try:
                    image = await camera_task
                except EdgeError as exc:
                    log.warning("camera failed: %s", exc)
            episode, files = await self._analyse(episode_id, candidates, image, source,
                                                 outcome, timings)
            await self._noted(noted)
            if episode["status"] != "pending":
                await asyncio.to_thread(self.store.create, episode, files)
            else:
                # The durable write and the VLM request overlap (the write takes ~10 ms of
                # fsyncs); the answer is stored only once the episode is. A crash before the
                # write completes loses the press, as it would have a moment earlier.
                stored = asyncio.get_running_loop().run_in_executor(
                    None, self.store.create, episode, files)  # submitted now, not next turn
                stored.add_done_callback(self._tactile_event(episode))
                try:
                    await self._ask_vlm(episode_id, retry=False, fresh=(episode, image),
                                        stored=stored)
                finally:
                    await stored
        except Exception as exc:
            log.exception("episode %s failed", episode_id)
            error = str(exc) if isinstance(exc, EdgeError) else f"{type(exc).__name__}: {exc}"
            try:
                await self._noted(noted)
                await asyncio.to_thread(self.store.create, {
                    "id": episode_id, "status": "failed", "error": error,
                    "candidates": candidates, "source": source}, {})
            except StoreError as store_exc:
                # Not even the failure could be kept: answer for it from memory.
                self._unstored[episode_id] = (
                    error if isinstance(exc, StoreError)
                    else f"{error}; and it could not be stored: {store_exc}")
                while len(self._unstored) > 100:
                    self._unstored.pop(next(iter(self._unstored)))
            except Exception:
                log.exception("episode %s: the failure could not be stored", episode_id)
        finally:
            if self._current == episode_id:
                self._current = None
            if not done.done():
                done.set_result(None)
            self.publish({"type": "episode", "episode": episode_id, "status": "finished"})

    @staticmethod
    async def _noted(noted: asyncio.Future) -> None:
        """Wait for the acceptance note before the episode is written (else the note could
        land after it, and outlive it until the next start)."""
        try:
            await noted
        except StoreError as exc:
            log.warning("%s: a crash before this episode is kept would lose it", exc)

    async def _analyse(self, episode_id: str, candidates: list[str], image: bytes | None,
                       source: str, outcome: PressOutcome, timings: dict[str, float]
                       ) -> tuple[dict[str, Any], dict[str, bytes]]:
        """The episode (``failed``, or ``pending`` for the VLM) and its files, not yet
        stored."""
        episode: dict[str, Any] = {
            "id": episode_id, "source": source, "candidates": candidates,
            "press": outcome.summary(), "software_version": __version__,
            "x_th": self.cfg.press.x_th, "timings": timings,
            "vlm_mode": getattr(self.vlm, "mode", None),
        }
        files: dict[str, bytes] = {}
        if image is not None:
            files["image" + (".png" if image.startswith(b"\x89PNG") else ".jpg")] = image
        if not outcome.contact or outcome.window is None or len(outcome.window.raw) < 2:
            episode.update(status="failed", error=outcome.message or outcome.result)
            return episode, files
        t = time.monotonic()
        rec = None
        try:
            # The crop, the encoder and the serialisation run in the compute process.
            rec = outcome_recording(outcome, self.cfg)
            analysed = await self.compute.run(analyse_press, self.model, rec)
        except EdgeError as exc:
            # E.g. the stream died before the window after the stop was complete: the press
            # is still kept, raw, with why it could not be recognised.
            log.error("episode %s: press not usable for recognition: %s", episode_id, exc)
            why = ("its analysis failed" if isinstance(exc, ComputeError | ModelError)
                   else "its tactile window is unusable")
            episode.update(status="failed", error=f"the press worked but {why}: {exc}")
            if rec is not None:  # (none when the window itself is unusable)
                with contextlib.suppress(EdgeError):
                    files["press.press.npz"] = recording.to_bytes(rec)
            return episode, files
        timings["encode_s"] = time.monotonic() - t
        z, code, topk, description, press_npz, model_io_npz = analysed
        files["press.press.npz"] = press_npz
        files["model_io.npz"] = model_io_npz
        episode.update(
            status="pending", code=int(code),
            z=[float(v) for v in z],
            topk=[{"label": label, "distance": float(d)} for label, d in topk],
            description=description, attempts=0, next_retry_at=0.0,
        )
        return episode, files

    async def run_cpu(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in the compute process (CPU work that must not hold the GIL here)."""
        return await self.compute.run(fn, *args)

    def _tactile_event(self, episode: dict[str, Any]):
        """Publishes the tactile result once the episode is stored (a done-callback)."""
        def done(stored: asyncio.Future) -> None:
            if not stored.cancelled() and stored.exception() is None:
                self.publish({"type": "tactile", "episode": episode["id"],
                              "description": episode["description"],
                              "topk": episode["topk"]})
        return done

    async def _ask_vlm(self, episode_id: str, retry: bool,
                       fresh: tuple[dict[str, Any], bytes | None] | None = None,
                       stored: asyncio.Future | None = None) -> None:
        # A new pending episode is due for the retry task at once, while its first question
        # may still be in flight: two answers for one episode, the last write winning.
        if episode_id in self._asking:
            return
        self._asking.add(episode_id)
        try:
            await self._ask_vlm_once(episode_id, fresh, stored)
        finally:
            self._asking.discard(episode_id)

    async def _ask_vlm_once(self, episode_id: str,
                            fresh: tuple[dict[str, Any], bytes | None] | None,
                            stored: asyncio.Future | None) -> None:
        """Ask about a stored episode, or about ``fresh`` (the episode and its image, in
        memory) whose write ``stored`` is still under way: awaited before any update."""
        if fresh is not None:
            episode, image = fresh
        else:
            episode = await asyncio.to_thread(self.store.get, episode_id)
            image = None
            for name in ("image.jpg", "image.png"):
                with contextlib.suppress(NotFoundError):
                    path = self.store.file(episode_id, name)
                    image = await asyncio.to_thread(path.read_bytes)
        t = time.monotonic()
        attempts = episode.get("attempts", 0) + 1
        try:
            answer = await self.vlm.ask(image, episode["description"], episode["candidates"])
        except EdgeError as exc:
            if stored is not None:
                await stored
            self.metrics.vlm_errors += 1
            if not isinstance(exc, VLMUnavailableError):
                # Refused (4xx), a broken answer or a bad image: asking again will not help.
                log.error("episode %s: VLM error: %s", episode_id, exc)
                await asyncio.to_thread(self.store.update, episode_id, status="vlm_error",
                                        attempts=attempts, last_error=str(exc))
                self.publish({"type": "result", "episode": episode_id, "status": "vlm_error",
                              "error": str(exc)})
                return
            delay = min(self.cfg.runtime.vlm_retry_base_s * 2 ** (attempts - 1),
                        self.cfg.runtime.vlm_retry_max_s)
            log.warning("episode %s: VLM unavailable (%s); retry in %.0f s", episode_id, exc,
                        delay)
            await asyncio.to_thread(self.store.update, episode_id, attempts=attempts,
                                    last_error=str(exc), next_retry_at=time.time() + delay)
            self._retry_wakeup.set()  # the retry task plans from the new due time
            self.publish({"type": "episode", "episode": episode_id, "status": "pending",
                          "error": str(exc)})
            return
        latency = time.monotonic() - t
        if stored is not None:
            await stored
        self.metrics.observe_vlm(latency)
        answer_dict = answer.to_dict() if hasattr(answer, "to_dict") else asdict(answer)
        status = {"ok": "done"}.get(answer.status, answer.status)
        timings = {**episode.get("timings", {}), "vlm_s": latency}
        await asyncio.to_thread(self.store.update, episode_id, status=status,
                                label=answer.label, vlm=answer_dict, attempts=attempts,
                                timings=timings)
        self.publish({"type": "result", "episode": episode_id, "status": status,
                      "label": answer.label})
        log.info("episode %s: %s%s", episode_id, status,
                 f" -> {answer.label}" if answer.label else "")

    async def episode(self, episode_id: str) -> dict[str, Any]:
        try:
            return await asyncio.to_thread(self.store.get, episode_id)
        except NotFoundError:
            if episode_id in self._unstored:
                raise StoreError(self._unstored[episode_id]) from None
            raise

    async def abort(self) -> bool:
        return self.press.request_abort()

    def health(self) -> dict[str, Any]:
        age = time.monotonic() - self.ring.latest_time()
        fresh = age < 1.0 and not self.press.sensor_is_stale
        bus_error = getattr(self.devices.bus, "fault", None)
        store_error = self.store.space_error()
        return {"ok": self.ready.is_set() and fresh and bus_error is None and not store_error,
                "ready": self.ready.is_set(), "sensor_fresh": fresh, "bus_error": bus_error,
                "store_error": store_error,
                "state": self.press.state, "episode": self._current,
                "last_frame_age_s": None if not np.isfinite(age) else round(age, 4),
                "version": __version__}

    def metrics_text(self) -> str:
        return self.metrics.render(self)

    # --- lifecycle --------------------------------------------------------------------
    async def run(self, api: Any | None = None) -> None:
        """Run until SIGTERM/SIGINT (or :meth:`stop`)."""
        loop = asyncio.get_running_loop()
        installed = []
        with contextlib.suppress(NotImplementedError, RuntimeError):
            for sig, handler in ((signal.SIGTERM, self.stop), (signal.SIGINT, self.stop),
                                 (signal.SIGHUP, self._sighup), (signal.SIGUSR1, self._sigusr1)):
                loop.add_signal_handler(sig, handler)
                installed.append(sig)
        removed = await asyncio.to_thread(self.store.recover)
        if removed:
            self.metrics.discarded_partial = removed
        try:
            async with asyncio.TaskGroup() as tg:
                self._tg = tg
                tg.create_task(self._sensor(), name="sensor")
                tg.create_task(self.sampler.run(), name="sampler")
                tg.create_task(self._watchdog(), name="watchdog")
                tg.create_task(self._button(), name="button")
                tg.create_task(self._vlm_retry(), name="vlm-retry")
                # Optional services (issue 12): live MCAP recording, MQTT bridge.
                for name, service in optional_services(self):
                    tg.create_task(service, name=name)
                if api is not None:
                    await api.start()
                # The model loaded and run once in the compute process: the first press
                # pays nothing for it.
                await self.compute.run(warm_up, self.model)
                await self._wait_first_frame()
                self.ready.set()
                self.notifier.ready(f"ready: {self.cfg.mode} mode")
                log.info("ready (%s mode) in %.2f s", self.cfg.mode,
                         time.monotonic() - self.started_at)
                await self._stopping.wait()
                await self._shutdown(api)
                raise _Stop
        except* _Stop:
            pass
        finally:
            for sig in installed:
                loop.remove_signal_handler(sig)

    async def _wait_first_frame(self) -> None:
        deadline = time.monotonic() + FIRST_FRAME_TIMEOUT_S
        while self.ring.count == 0 and time.monotonic() < deadline:  # noqa: ASYNC110
            await asyncio.sleep(0.01)  # polled: the sensor task must stay allocation-free
        if self.ring.count == 0:
            log.warning("no tactile frame within 5 s; serving anyway (presses are refused)")

    def stop(self) -> None:
        if not self._stopping.is_set():
            log.info("stopping: no new work; making the arm safe")
            self._stopping.set()

    def _sigusr1(self) -> None:
        asyncio.get_running_loop().create_task(self._trigger_default("SIGUSR1"),
                                               name="sigusr1")

    def _sighup(self) -> None:
        if self._reload is None:
            log.warning("SIGHUP: nothing to reload")
            return
        asyncio.get_running_loop().create_task(self._do_reload(), name="reload")

    async def _do_reload(self) -> None:
        try:
            cfg, model, vlm = await asyncio.to_thread(self._reload)
        except EdgeError as exc:
            log.error("reload refused, keeping the running configuration: %s", exc)
            return
        async with self._press_lock:  # never swap under a press in progress
            try:
                await self.compute.run(warm_up, model)
            except EdgeError as exc:
                log.error("reload refused, keeping the running model: %s", exc)
                return
            self.cfg = replace(self.cfg, press=cfg.press, api=replace(
                self.cfg.api, default_candidates=cfg.api.default_candidates))
            self.press.cfg = self.cfg
            self.model = model
            self.vlm = vlm
        log.info("reloaded model, database and press settings")

    async def _shutdown(self, api: Any | None) -> None:
        self.notifier.stopping()
        if api is not None:
            await api.close()
        if self.press.state not in ("idle",):
            self.press.request_abort()
        # Let a running press open the gripper; the press controller always does.
        for task in list(self._work):
            with contextlib.suppress(asyncio.TimeoutError, Exception):
                await asyncio.wait_for(asyncio.shield(task), 10.0)
        with contextlib.suppress(Exception):
            await self.devices.gripper.open()
        if self.devices.bus is not None:
            try:
                await self.devices.bus.close(
                    safe_pose=lambda: self.devices.arm.move_to("rest", 5.0))
            except Exception as exc:
                log.error("bus shutdown: %s", exc)
        with contextlib.suppress(Exception):
            await self.devices.tactile.close()
        if self.devices.button is not None:
            await self.devices.button.close()
        log.info("stopped")


class _Stop(Exception):
    """Ends the root TaskGroup after an orderly shutdown."""
