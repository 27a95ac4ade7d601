"""The daemon's lifecycle: one asyncio loop, one root TaskGroup, every task named.

Tasks: ``sensor`` (frames -> ring buffer + the threshold on every frame), ``sampler``
(125 Hz), ``watchdog`` (sd_notify only while frames keep arriving, or while torque is off),
``button``, ``vlm-retry`` (pending episodes), ``store`` (retention; a store that could not
write, tried again), one ``recognize`` task per request, ``teach LABEL`` while a teaching
runs (:mod:`edge.runtime.teaching`: ended on every path out), and, after
a start without the sensor stream, ``power-on`` (torque on when the stream arrives). The bus
has its own owner thread (:mod:`edge.hw.dynamixel`). Signals set events: SIGTERM/SIGINT
stop taking work and make the arm safe; SIGHUP reloads configuration, model, database and
VLM client between presses (deferred until the daemon serves); SIGUSR1 triggers a
recognition with the default candidates. Those held while the daemon started
(:mod:`edge.runtime.signals`) are acted on when it runs.

Whatever makes the arm safe runs in ``finally`` on every path out of :meth:`Runtime.run`,
including a task that died: the running press is aborted (its controller opens the
gripper), the gripper is opened once more, and the caller (:mod:`edge.app`) then
moves the arm to rest, turns torque off and closes the bus.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import signal
import time
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from edge import __version__
from edge.core import preprocess
from edge.core.config import Config, PressConfig, SensorConfig
from edge.core.errors import BusyError, EdgeError, StoreError
from edge.core.model import ModelRef
from edge.hw.contracts import Devices
from edge.runtime import signals, taps
from edge.runtime.compute import ComputeWorker, reload_model, warm_up
from edge.runtime.domain import Episode, Health, Hello, PressState, StateChanged, TeachRun
from edge.runtime.events import EventBus, Subscription
from edge.runtime.metrics import Metrics
from edge.runtime.press import PressController
from edge.runtime.recognition import Presses, Recognition, Recognizer
from edge.runtime.references import Source, TaughtReference
from edge.runtime.ring import FrameRing
from edge.runtime.sensor import Sampler, SensorTask
from edge.runtime.store import EpisodeStore
from edge.runtime.systemd import Notifier, watchdog_period_s
from edge.runtime.taps import Rows
from edge.runtime.teaching import PAUSE_S, Teacher
from edge.vlm.client import VLMClient

log = logging.getLogger(__name__)
T = TypeVar("T")

SAMPLE_RATE_HZ = 125.0
RING_SECONDS = 30.0
FIRST_FRAME_TIMEOUT_S = 5.0
# How long of the stream the start measures its rate over (once; a warning if it is off the
# model's grid).
RATE_CHECK_S = 2.0
# On SIGTERM: how long a recognition in flight (its press, the VLM question) may take to
# finish before the daemon goes on without it.
DRAIN_TIMEOUT_S = 10.0
# The stream counts as fresh for /healthz while its last frame is younger than this.
HEALTH_FRAME_AGE_S = 1.0
# After a start without the sensor stream: how often the power-on task looks for a frame.
STREAM_POLL_S = 0.02
# While the episode store cannot write: how often it is tried again (a small write and
# fsync), the episodes held in memory written once it can.
STORE_RETRY_S = 1.0
# How often the store's retention runs besides after each new episode: the live recording
# adds segments without any press.
RETAIN_PERIOD_S = 60.0
# Before a teaching presses: how long of the stream its rate is measured over, against the
# rate the class's references were pressed at (the ring holds 30 s). Long, and not measured
# on a younger stream: the emulated server's first seconds after a busy start read 139 and
# 193 frames/s for its 125 (it catches up on late ticks).
TEACH_RATE_S = 10.0


# Returns the new (configuration, model, VLM client) on SIGHUP; raises EdgeError to refuse.
Reloader = Callable[[], tuple[Config, ModelRef, VLMClient]]
# Makes the daemon's one press controller from PressController's arguments: PressController
# itself, or a benchmark's controller (edge/bench/controllers.py).
ControllerFactory = Callable[..., PressController]
# (task name, coroutine) of each service the composition root runs beside the press.
Services = Callable[["Runtime"], list[tuple[str, Coroutine[Any, Any, None]]]]


class Runtime:
    def __init__(self, cfg: Config, devices: Devices, model: ModelRef, vlm: VLMClient,
                 store: EpisodeStore, compute: ComputeWorker,
                 notifier: Notifier | None = None, reload: Reloader | None = None,
                 controller_factory: ControllerFactory = PressController,
                 services: Services | None = None) -> None:
        self.devices = devices
        # What the composition root starts beside the press (live MCAP, MQTT): named
        # coroutines run in the daemon's TaskGroup; the runtime knows none of them.
        self._services = services
        self.store = store
        self.compute = compute
        self.notifier = notifier or Notifier("")
        self.reloader = reload
        self.events = EventBus()
        self.metrics = Metrics()
        self.ring = FrameRing(cfg.sensor.channels, int(RING_SECONDS * SAMPLE_RATE_HZ * 1.5))
        self.sampler = Sampler(self.ring, SAMPLE_RATE_HZ)
        # One press controller for the daemon's life: the sensor task checks every frame
        # with it, the recognizer presses with it.
        self.press = controller_factory(
            cfg, devices.gripper, devices.arm, self.ring, on_state=self._on_press_state,
            recover=devices.recover, window=model.window, model_x_th=model.x_th)
        self.recognizer = Recognizer(Recognition(cfg, model, vlm), self.press, compute, store,
                                     self.events, self.metrics, devices.camera)
        self.sensor = SensorTask(devices.tactile, self.ring, self.press,
                                 on_unusable=self.notifier.status)
        self.teacher = Teacher(self.recognizer, self.events, self.stream_rate)
        self._stopping = asyncio.Event()
        self.ready = asyncio.Event()
        self.started_at = time.monotonic()
        # Set by power_on_with_stream: the start had no sensor stream, torque is still off.
        self._power_on: Callable[[], Awaitable[None]] | None = None
        self._no_stream: str | None = None  # why, until the stream arrives
        # Why torque stayed off when the stream arrived: the bus's trouble then, not the sensor's.
        self._torque_error: str | None = None
        # Serving (ready, or degraded with torque off); until then a SIGHUP is deferred.
        self._serving = False
        self._reload_due = False

    # The configuration, model and VLM client in force (replaced together on reload).
    @property
    def cfg(self) -> Config:
        return self.recognizer.setup.cfg

    @property
    def model(self) -> ModelRef:
        return self.recognizer.setup.model

    @property
    def vlm(self) -> VLMClient:
        return self.recognizer.setup.vlm

    # --- the interfaces' seams (edge.interfaces.contracts): recognitions ------------------
    # One object behind both seams: an interface asks the runtime, which hands a
    # recognition to its recognizer and answers for the press, the store and the health.
    async def recognize(self, candidates: list[str], image: bytes | None, wait: bool,
                        timeout_s: float | None, source: str, presses: Presses = 1,
                        pause_s: float = PAUSE_S) -> Episode:
        if self.teacher.active:
            # Its presses are of the object being taught, with pauses between them.
            raise BusyError("a teaching is under way (GET /v1/teach); one at a time")
        return await self.recognizer.recognize(candidates, image, wait, timeout_s, source,
                                               presses=presses, pause_s=pause_s)

    async def episode(self, episode_id: str) -> Episode:
        return await self.recognizer.episode(episode_id)

    async def retry(self, episode_id: str) -> Episode:
        return await self.recognizer.retry(episode_id)

    async def abort(self) -> bool:
        return self.press.request_abort()

    def episodes(self, limit: int) -> list[Episode]:
        return self.store.list(limit=limit)

    def episode_file(self, episode_id: str, name: str) -> Path:
        return self.store.file(episode_id, name)

    # --- ... teaching (edge.interfaces.contracts.Teaching) ---------------------------------
    async def teach(self, label: str, description: str | None, presses: int, append: bool,
                    source: Source, *, pause_s: float = PAUSE_S, wait: bool = True
                    ) -> TeachRun:
        return await self.teacher.teach(label, description, presses, append, source,
                                        pause_s=pause_s, wait=wait)

    async def teach_episode(self, episode_id: str, label: str, description: str | None,
                            source: Source) -> TaughtReference:
        if self.teacher.active:
            raise BusyError("a teaching is under way (GET /v1/teach); one at a time")
        return await self.teacher.teach_episode(episode_id, label, description, source)

    def teaching(self) -> TeachRun | None:
        return self.teacher.current

    async def references(self) -> dict[str, Any]:
        return await self.teacher.references()

    async def remove_references(self, ref_id: str | None = None, label: str | None = None
                                ) -> list[TaughtReference]:
        return await self.teacher.remove(ref_id, label)

    def stream_rate(self) -> float | None:
        """The tactile stream's rate over the last ``TEACH_RATE_S`` (frames/s); None where
        the stream is younger (each press's own rate is checked as it is taught)."""
        now = time.monotonic()
        if now - self.ring.oldest_time() < TEACH_RATE_S:
            return None
        frames = self.ring.window(now - TEACH_RATE_S, now)
        return preprocess.fresh_rate(frames.recv_time, frames.sensor_time, frames.seq)

    # --- ... and live taps (edge.runtime.taps.LiveTaps) -----------------------------------
    def subscribe(self) -> contextlib.AbstractContextManager[Subscription]:
        return self.events.subscribe(Hello(self.press.state, self.recognizer.current))

    @property
    def frame_count(self) -> int:
        return self.ring.count

    def rows_since(self, after: int, limit: int | None = None) -> Rows:
        return taps.rows_since(self.ring, after, limit)

    def sensor_settings(self) -> SensorConfig:
        return self.cfg.sensor

    def press_settings(self) -> PressConfig:
        return self.cfg.press

    def power_on_with_stream(self, why: str, power_on: Callable[[], Awaitable[None]]) -> None:
        """Start with torque off and presses refused (``why``: the sensor server is absent);
        :meth:`run` awaits ``power_on`` (torque on) once the stream's first frame arrived."""
        self._no_stream = why
        self._power_on = power_on
        self.recognizer.refusal = f"not pressing, torque off: {why}"

    @property
    def sensor_error(self) -> str | None:
        """What keeps the sensor path from serving presses, beyond a stale stream: a layout
        the configuration does not match, or no stream since the start."""
        fatal = self.sensor.fatal
        return str(fatal) if fatal is not None else self._no_stream

    def health(self) -> Health:
        age = time.monotonic() - self.ring.latest_time()
        fresh = age < HEALTH_FRAME_AGE_S and not self.press.sensor_is_stale
        bus = self.devices.bus
        bus_error = (bus.fault if bus is not None else None) or self._torque_error
        store_error = self.store.error()
        vlm_error = self.vlm.unreachable
        sensor_error = self.sensor_error
        return Health(ok=(self.ready.is_set() and fresh and bus_error is None and not store_error
                          and sensor_error is None and vlm_error is None),
                      ready=self.ready.is_set(), sensor_fresh=fresh, bus_error=bus_error,
                      store_error=store_error, sensor_error=sensor_error,
                      vlm_error=vlm_error,
                      torque_on=bus.torque_on if bus is not None else None,
                      state=self.press.state, episode=self.recognizer.current,
                      last_frame_age_s=None if not np.isfinite(age) else round(age, 4),
                      # Which model answers: changes when a reload took a new model or
                      # database.
                      model_digest=self.model.digest,
                      version=__version__,
                      stale_references=len(self.teacher.stale),
                      stale_reference_labels=tuple(sorted({r.label
                                                           for r in self.teacher.stale})))

    def metrics_text(self) -> str:
        return self.metrics.render(self.sampler.stats, self.sensor, self.devices.bus, self.vlm,
                                   self.store)

    async def run_cpu(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in the compute process (CPU work that must not hold the GIL here)."""
        return await self.compute.run(fn, *args)

    def _on_press_state(self, state: PressState) -> None:
        self.events.publish(StateChanged(state, self.recognizer.current))

    # --- lifecycle ----------------------------------------------------------------------
    async def run(self) -> None:
        """Run until SIGTERM/SIGINT (or :meth:`stop`); the arm is made safe on every path
        out. A task that dies takes the daemon down (after that), with its error."""
        loop = asyncio.get_running_loop()
        installed = []
        with contextlib.suppress(NotImplementedError, RuntimeError):
            for sig, handler in ((signal.SIGTERM, self.stop), (signal.SIGINT, self.stop),
                                 (signal.SIGHUP, self._sighup),
                                 (signal.SIGUSR1, self._sigusr1)):
                previous = signal.getsignal(sig)
                loop.add_signal_handler(sig, handler)
                installed.append((sig, previous))
        # Sent while the daemon started, held until now (edge/runtime/signals.py).
        early = signals.take_pending()
        if signal.SIGHUP in early:
            self._sighup()
        if signal.SIGTERM in early:
            log.info("SIGTERM during the start")
            self.stop()
        try:
            removed = await asyncio.to_thread(self.store.recover)
            self.metrics.discarded_partial = removed
            async with asyncio.TaskGroup() as tg:
                self.recognizer.spawn_in(tg)
                tg.create_task(self.sensor.run(), name="sensor")
                tg.create_task(self.sampler.run(), name="sampler")
                tg.create_task(self._watchdog(), name="watchdog")
                tg.create_task(self._button(), name="button")
                tg.create_task(self._check_stream_rate(), name="rate-check")
                tg.create_task(self.recognizer.retry_pending(), name="vlm-retry")
                tg.create_task(self._store_upkeep(), name="store")
                # What the configuration turns on besides (edge.app: live MCAP, MQTT).
                for name, service in self._services(self) if self._services else ():
                    tg.create_task(service, name=name)
                # The model loaded and run once in the compute process: the first press
                # pays nothing for it.
                await self.compute.run(warm_up, self.model)
                await self.teacher.check_references()
                if self._power_on is None:
                    await self._wait_first_frame()
                    self._set_ready()
                else:
                    tg.create_task(self._power_on_with_stream(), name="power-on")
                    # READY=1 all the same: the daemon serves (/healthz says why not ok),
                    # and a start that systemd timed out would only begin the same wait.
                    self.notifier.ready(f"degraded: {self._no_stream}; torque off until "
                                        "its stream arrives")
                    log.warning("%s: serving with torque off; presses are refused until its "
                                "stream arrives", self._no_stream)
                self._serving = True
                if self._reload_due:
                    self._reload_due = False
                    self._sighup()
                await self._stopping.wait()
                await self._drain()
                raise _Stop
        except* _Stop:
            pass
        finally:
            for sig, previous in installed:
                loop.remove_signal_handler(sig)
                if previous is not None:
                    # Held again (or as they were): a signal now must not cut the arm's
                    # way to safety short.
                    signal.signal(sig, previous)
            await _unless_cancelled_twice(self._make_safe())
            # Then a teaching under way ends (it could start no press: none is accepted).
            await self.teacher.stop()

    def _set_ready(self) -> None:
        self.ready.set()
        self.notifier.ready(f"ready: {self.cfg.mode} mode")
        log.info("ready (%s mode) in %.2f s", self.cfg.mode, time.monotonic() - self.started_at)

    async def _power_on_with_stream(self) -> None:
        """Torque on with the stream's first frame (whose layout the client checked); a
        layout refused keeps torque off, as does a motor refusing it."""
        assert self._power_on is not None
        while self.ring.count == 0 and self.sensor.fatal is None:  # noqa: ASYNC110
            await asyncio.sleep(STREAM_POLL_S)  # polled: the sensor task stays as it is
        if self.sensor.fatal is not None:
            self._no_stream = None  # (the layout says it now)
            self.recognizer.refusal = f"not pressing, torque off: {self.sensor.fatal}"
            return  # (the sensor task has logged it, once)
        try:
            await self._power_on()
        except EdgeError as exc:
            log.error("torque could not be turned on: %s", exc)
            self._no_stream = None  # the stream is here: what is wrong now is the bus
            self._torque_error = f"torque could not be turned on: {exc}"
            self.recognizer.refusal = f"not pressing: {self._torque_error}"
            self.notifier.status(f"degraded: {self._torque_error}")  # no longer the sensor
            return
        self._no_stream = None
        self._power_on = None
        self.recognizer.refusal = None
        log.info("tactile stream arrived: torque on, presses accepted")
        self._set_ready()

    async def _wait_first_frame(self) -> None:
        deadline = time.monotonic() + FIRST_FRAME_TIMEOUT_S
        while self.ring.count == 0 and time.monotonic() < deadline:  # noqa: ASYNC110
            await asyncio.sleep(0.01)  # polled: the sensor task must stay allocation-free
        if self.ring.count == 0:
            log.warning("no tactile frame within %.0f s; serving anyway (presses are "
                        "refused)", FIRST_FRAME_TIMEOUT_S)

    async def _check_stream_rate(self) -> None:
        """Once, ``RATE_CHECK_S`` into the stream: a warning where its rate is off the
        model's grid (doctor's xela rate check says the same)."""
        while self.ring.count == 0:  # noqa: ASYNC110
            await asyncio.sleep(STREAM_POLL_S)  # polled: the sensor task stays as it is
        t0 = time.monotonic()
        await asyncio.sleep(RATE_CHECK_S)
        frames = self.ring.window(t0, time.monotonic())
        off = preprocess.rate_problem(
            preprocess.fresh_rate(frames.recv_time, frames.sensor_time, frames.seq),
            self.model.window.rate_hz)
        if off is not None:
            log.warning("the tactile stream at %s, the model's grid, the rate its references "
                        "were pressed at: %s; or build a model from presses at this rate", off,
                        preprocess.RATE_SETTING)

    def stop(self) -> None:
        if not self._stopping.is_set():
            log.info("stopping: no new work; making the arm safe")
            self._stopping.set()

    async def _drain(self) -> None:
        """An orderly stop: no new work, the press aborted, recognitions in flight given
        time to finish (and be stored)."""
        self.notifier.stopping()
        self.recognizer.accepting = False
        self.press.request_abort()
        for task in list(self.recognizer.work):
            with contextlib.suppress(TimeoutError, Exception):
                await asyncio.wait_for(asyncio.shield(task), DRAIN_TIMEOUT_S)
        if self.store.held:
            # Held in memory while the store could not write: one last try.
            with contextlib.suppress(StoreError):
                await asyncio.to_thread(self.store.flush)
            if self.store.held:
                log.error("%d episode(s) held in memory could not be written before the "
                          "stop: the next start keeps them as interrupted (their acceptance "
                          "notes); the store: %s", self.store.held, self.store.write_error)

    async def _make_safe(self) -> None:
        """On every path out: no press left running, the gripper open. (The caller then
        moves the arm to rest, turns torque off and closes the devices.)"""
        self.recognizer.accepting = False
        self.press.request_abort()
        if self._power_on is not None:
            return  # torque never went on: the gripper holds nothing, and cannot move
        try:
            failed = await self.press.open_gripper_retrying()
        except Exception as exc:  # a bug here must not skip the torque-off that follows
            log.exception("opening the gripper at shutdown failed")
            failed = exc
        if failed is not None:
            log.error("the gripper may still be closed at shutdown: %s", failed)

    async def _watchdog(self) -> None:
        period = watchdog_period_s()
        if period is None:
            return
        while True:
            await asyncio.sleep(period)
            # WATCHDOG=1 while the sensor path makes progress: a stream that died under a
            # powered arm gets the daemon restarted. Also while torque is off for want of
            # the stream (none since the start, or a layout refused): the daemon holds
            # nothing, says why on /healthz, and a restart would only repeat the wait.
            if (time.monotonic() - self.ring.latest_time() < max(1.0, period)
                    or self._power_on is not None):
                self.notifier.watchdog()

    async def _store_upkeep(self) -> None:
        """The store's retention now and every ``RETAIN_PERIOD_S``; and while it cannot
        write (or holds episodes in memory), a try every ``STORE_RETRY_S``, what it holds
        written once it can."""
        retained = -math.inf
        while True:
            if time.monotonic() - retained >= RETAIN_PERIOD_S:
                retained = time.monotonic()
                await asyncio.to_thread(self.store.retain)
            await asyncio.sleep(STORE_RETRY_S)
            if self.store.write_error is None and not self.store.held:
                continue
            with contextlib.suppress(StoreError):  # (the store has said why, once)
                await asyncio.to_thread(self.store.check_writable)
                await asyncio.to_thread(self.store.flush)

    async def _button(self) -> None:
        button = self.devices.button
        if button is None:
            return
        async for _ in button.presses():
            await self._trigger("button")

    def _sigusr1(self) -> None:
        asyncio.get_running_loop().create_task(self._trigger("SIGUSR1"), name="sigusr1")

    async def _trigger(self, source: str) -> None:
        """A button or a signal: a recognition, unless a teaching is under way (its presses
        are the operator's object, one after another; a recognition between two would
        press it as something else)."""
        if self.teacher.active:
            log.warning("%s trigger ignored: a teaching is under way", source)
            return
        await self.recognizer.trigger_default(source)

    def _sighup(self) -> None:
        if self.reloader is None:
            log.warning("SIGHUP: nothing to reload")
            return
        if not self._serving:
            # The start loads the same files: reloading under it would race it.
            if not self._reload_due:
                log.info("SIGHUP while the daemon starts: the reload follows once it serves")
            self._reload_due = True
            return
        asyncio.get_running_loop().create_task(self.reload(), name="reload")

    async def reload(self) -> bool:
        """Load the configuration, model, database and VLM client again and use them from
        the next press on (never under a running press). False if refused: the running
        ones stay."""
        assert self.reloader is not None
        try:
            cfg, model, vlm = await asyncio.to_thread(self.reloader)
        except EdgeError as exc:
            log.error("reload refused, keeping the running configuration: %s", exc)
            return False
        async with self.recognizer.lock:  # never swap under a press in progress
            try:
                # Every file re-hashed, not only the manifest's digest compared.
                await self.compute.run(reload_model, model)
            except EdgeError as exc:
                log.error("reload refused, keeping the running model: %s", exc)
                if vlm is not self.vlm:
                    await vlm.close()
                return False
            # What the devices were opened with (ports, motor IDs, poses) stays; every
            # setting read per press (press, timeouts, gripper widths and current, VLM,
            # default candidates) takes effect now.
            old = self.recognizer.setup
            cfg = _reloadable(old.cfg, cfg)
            self.recognizer.setup = Recognition(cfg, model, vlm)
            self.press.cfg = cfg
            self.press.window = model.window
            self.press.model_x_th = model.x_th
        if old.vlm is not vlm:
            await old.vlm.close()
        log.info("reloaded configuration, model, database and VLM client")
        with contextlib.suppress(EdgeError):  # (the compute process has just read them)
            await self.teacher.check_references()
        return True


def _reloadable(running: Config, new: Config) -> Config:
    """``new`` where a setting can change under a running daemon; ``running`` where it is
    bound to an open device or socket."""
    return replace(
        new, mode=running.mode, sensor=running.sensor, sim=running.sim, camera=running.camera,
        button=running.button, poses=running.poses,
        api=replace(running.api, default_candidates=new.api.default_candidates),
        bus=replace(running.bus, gripper_goal_current=new.bus.gripper_goal_current),
        runtime=replace(new.runtime, state_dir=running.runtime.state_dir,
                        move_time_s=running.runtime.move_time_s,
                        realtime=running.runtime.realtime,
                        realtime_priority=running.runtime.realtime_priority,
                        realtime_cpu=running.runtime.realtime_cpu))


async def _unless_cancelled_twice(coro: Any) -> None:
    """Run ``coro`` to its end even if the caller is cancelled once more meanwhile."""
    task = asyncio.ensure_future(coro)
    try:
        await asyncio.shield(task)
    except asyncio.CancelledError:
        await task
        raise


class _Stop(Exception):
    """Ends the root TaskGroup after an orderly stop."""
