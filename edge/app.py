"""The composition root of ``vt-edge run``: assemble the daemon from a configuration file
(devices, model, compute process, store, runtime, API and the optional services beside the
press: live MCAP recording, the MQTT bridge) and run it."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import resource
import selectors
import sys
import threading
import time
from collections.abc import AsyncIterator, Callable, Coroutine
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from edge.core.config import Config, load_config
from edge.core.errors import StartError, StoreError
from edge.core.model import ModelRef, x_th_mismatch
from edge.core.model import model_ref as _model_ref
from edge.hw.contracts import Devices
from edge.interfaces.http.api import Api, listen, load_token
from edge.interfaces.mqtt import check_config as check_mqtt
from edge.runtime.compute import ComputeWorker, warm_up
from edge.runtime.devices import close_devices, enable_torque, open_devices
from edge.runtime.lifecycle import ControllerFactory, Runtime
from edge.runtime.press import PressController
from edge.runtime.realtime import Realtime, unpin_thread
from edge.runtime.references import references_dir
from edge.runtime.startcheck import check_devices, check_model
from edge.runtime.store import EpisodeStore
from edge.runtime.systemd import Notifier

log = logging.getLogger(__name__)

# select(2) handles file descriptors below FD_SETSIZE only.
FD_SETSIZE = 1024
# Leaving running(): how long the runtime may take to stop (its drain gives each
# recognition in flight DRAIN_TIMEOUT_S) and make the arm safe.
STOP_TIMEOUT_S = 30.0


def new_event_loop() -> asyncio.AbstractEventLoop:
    """The daemon's event loop: asyncio's selector loop on ``select(2)``, not epoll.

    ``EpollSelector`` rounds every timeout up to a whole millisecond (``epoll_wait`` takes
    milliseconds), so every timer, the 125 Hz sampler's included, fires up to 1 ms late:
    0.8 ms at the median on an idle box. ``select(2)`` takes microseconds. It refuses file
    descriptors from FD_SETSIZE (1024) up, so the process's soft RLIMIT_NOFILE is lowered
    to 1024 (systemd's default for services anyway): past it, opening a socket fails with
    EMFILE, which the API answers per request, instead of the loop dying. A daemon talking
    to a sensor, a bus, a camera and a few HTTP clients needs a few dozen.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft > FD_SETSIZE:
        resource.setrlimit(resource.RLIMIT_NOFILE, (FD_SETSIZE, hard))
        log.info("open files limited to %d (was %s): the event loop uses select(2) for "
                 "microsecond timers", FD_SETSIZE, soft)
    loop = asyncio.SelectorEventLoop(selectors.SelectSelector())
    # Its threads start from the loop's thread and would inherit its one CPU when that is
    # held for real-time scheduling ([runtime] realtime): they get every CPU back.
    loop.set_default_executor(ThreadPoolExecutor(thread_name_prefix="asyncio",
                                                 initializer=unpin_thread))
    return loop


def model_ref(cfg: Config, state_dir: str | None = None) -> ModelRef:
    """The configured model by its manifest, with the references taught beside it in the
    state directory (``state_dir``, else the configuration's: a reload keeps the running
    one); the compute process loads and verifies both."""
    return _model_ref(cfg.runtime.models_dir,
                      references_dir(state_dir or cfg.runtime.state_dir))


def vlm_config(cfg: Config):
    """The ``[vlm]`` section with the prompt templates of the configured models directory."""
    vlm = cfg.vlm
    if vlm.prompt_dir is None:
        vlm = replace(vlm, prompt_dir=Path(cfg.runtime.models_dir) / "prompts")
    return vlm


def make_vlm(cfg: Config, compute: ComputeWorker | None = None):
    """The configured VLM client; with ``compute``, images are prepared in that process."""
    from edge.vlm.client import make_vlm as _make

    return _make(vlm_config(cfg), **({"offload": compute.run} if compute else {}))


@dataclass
class Daemon:
    """The assembled daemon: what :func:`assemble` started, for ``vt-edge run``, tests and
    the benchmark alike."""

    cfg: Config
    runtime: Runtime
    api: Api
    devices: Devices
    store: EpisodeStore
    compute: ComputeWorker
    # Real-time scheduling of the loop and bus threads; enabled at start when configured.
    realtime: Realtime


@contextlib.asynccontextmanager
async def assemble(cfg: Config, config_path: str | None = None, *,
                   devices: Devices | None = None, button: Any = None,
                   notifier: Notifier | None = None,
                   controller_factory: ControllerFactory = PressController
                   ) -> AsyncIterator[Daemon]:
    """Start everything in the order that keeps a failed start harmless, and make the arm
    safe on every way out.

    Checked before any device is opened: the API's token, the model (every file verified and the
    encoder run once in the compute process), the episode store, and the API's port (bound).
    Then the devices are connected, torque still off, and checked
    (:mod:`edge.runtime.startcheck`: the pad layout on the first frames, the camera's photo, the
    model's input channels against the pads'); torque is turned on last. Whatever fails raises
    :class:`StartError` naming what to fix. An absent sensor server is no failure: torque stays
    off until its stream arrives (:meth:`Runtime.power_on_with_stream`). On exit the API closes,
    the arm goes to rest, torque goes off and the devices close, whether the daemon ran, failed
    to start or died. ``devices`` overrides the configured ones (their bus is still closed on
    exit); ``button`` is added to them. ``controller_factory`` makes the daemon's press
    controller (a benchmark's; :class:`PressController` by default). :func:`running` runs it.
    """
    started = time.monotonic()
    notifier = notifier or Notifier()
    async with contextlib.AsyncExitStack() as stack:
        stack.callback(notifier.close)
        # A configuration the API refuses (exposed without a token) is refused before any
        # device is touched: no torque on an arm the daemon will not run.
        load_token(cfg.api)
        check_mqtt(cfg.mqtt)  # the MQTT bridge's client library, password and CA files
        notifier.status("starting: loading model")
        model = await asyncio.to_thread(model_ref, cfg)
        compute = await stack.enter_async_context(ComputeWorker())
        # Every model file verified and the encoder run once, before any device is touched:
        # no torque on an arm the daemon could not recognise with.
        await compute.run(warm_up, model)
        vlm = make_vlm(cfg, compute)
        runtime: Runtime | None = None
        # The client in use at the end (a reload replaces it, and closes the old one).
        stack.push_async_callback(_close_vlm, lambda: runtime.vlm if runtime else vlm)
        store = EpisodeStore(Path(cfg.runtime.state_dir) / "episodes",
                             max_bytes=round(cfg.runtime.store_max_mb * 1e6),
                             keep_free_bytes=round(cfg.runtime.keep_free_mb * 1e6),
                             segments=cfg.runtime.record_mcap_dir or None)
        # Written and fsynced before torque goes on. A store that cannot write leaves the
        # daemon serving with presses refused (/healthz store_error) until it can (the store
        # has logged why).
        with contextlib.suppress(StoreError):
            await asyncio.to_thread(store.check_writable)
        try:
            sockets = listen(cfg.api)
        except OSError as exc:
            raise StartError(f"cannot listen on {cfg.api.host}:{cfg.api.port}: "
                             f"{_os_reason(exc)}") from None
        for sock in sockets:
            stack.callback(sock.close)
        api: Api | None = None
        # Closed after the devices (the arm safe first), as its port is bound before them.
        stack.push_async_callback(_close_api, lambda: api)
        if devices is None:
            notifier.status("starting: connecting devices")
            devices = await open_devices(cfg)
        stack.push_async_callback(close_devices, devices, cfg.runtime.move_timeout_s)
        if button is not None:
            devices.button = button
        notifier.status("starting: checking the pads' layout and the camera")
        no_stream = await check_devices(cfg, devices, vlm.mode)
        # After the pads are checked against the server, not before: a [sensor] layout
        # unlike the hardware is the cause to name, not the model that follows from it.
        check_model(cfg.sensor, model)
        _warn_x_th(cfg, model)

        def reload() -> tuple[Config, ModelRef, Any]:
            new = load_config(config_path) if config_path else cfg
            new_model = model_ref(new, cfg.runtime.state_dir)
            check_model(cfg.sensor, new_model)  # the pads stay the ones opened at start
            _warn_x_th(new, new_model)
            return new, new_model, make_vlm(new, compute)

        runtime = Runtime(cfg, devices, model, vlm, store, compute, notifier, reload=reload,
                          controller_factory=controller_factory, services=optional_services)
        runtime.started_at = started
        api = Api(runtime, cfg.api)
        await api.start(sockets)
        realtime = make_realtime(cfg, devices)
        stack.callback(realtime.disable)
        if cfg.runtime.realtime:
            realtime.enable()  # where refused, it says why and the daemon runs as before
        if no_stream is None:
            await enable_torque(devices)
        else:
            runtime.power_on_with_stream(no_stream, lambda: enable_torque(devices))
        # Everything started so far lives as long as the daemon: out of the collector's
        # way, so that its full collections (which stop the loop) walk only what came after.
        gc.freeze()
        yield Daemon(cfg, runtime, api, devices, store, compute, realtime)


def _warn_x_th(cfg: Config, model: ModelRef) -> None:
    """A warning where the configured x_th is far from the model's (presses embed elsewhere;
    the daemon runs all the same: a lab may be trying a threshold on purpose)."""
    problem = x_th_mismatch(cfg.press.x_th, model.x_th)
    if problem is not None:
        log.warning("%s", problem)


def make_realtime(cfg: Config, devices: Devices) -> Realtime:
    """Real-time scheduling for the threads the stop goes through: this one (the event
    loop's) and the bus thread."""
    loop_thread = threading.get_native_id()

    def threads() -> list[int]:
        bus = devices.bus
        bus_thread = bus.native_thread_id if bus is not None else None
        return [loop_thread, *([bus_thread] if bus_thread else [])]

    return Realtime(cfg.runtime.realtime_priority, cfg.runtime.realtime_cpu, threads)


async def _close_vlm(current: Callable[[], Any]) -> None:
    await current().close()


async def _close_api(current: Callable[[], Api | None]) -> None:
    api = current()
    if api is not None:
        await api.close()


@contextlib.asynccontextmanager
async def running(daemon: Daemon, ready_within_s: float | None = None
                  ) -> AsyncIterator[asyncio.Task[None]]:
    """The assembled daemon's runtime running in a task of this loop, for ``vt-edge run``,
    tests and the benchmark alike; yields that task, which ends after SIGTERM/SIGINT (or
    :meth:`Runtime.stop`) or with the error of a task that died.

    With ``ready_within_s``, entered once the runtime is ready (raises :class:`TimeoutError`
    if it is not by then, or the runtime's error if it ended first); without, at once (the
    API serves, ready or not). On exit the runtime is stopped as by SIGTERM and awaited: its
    drain, the arm made safe, and the error of a task that died raised.
    """
    runtime = daemon.runtime
    task = asyncio.create_task(runtime.run(), name="runtime")
    try:
        if ready_within_s is not None:
            await _until_ready(runtime, task, ready_within_s)
        yield task
    finally:
        runtime.stop()
        await asyncio.wait_for(task, STOP_TIMEOUT_S)


async def _until_ready(runtime: Runtime, task: asyncio.Task[None], timeout_s: float) -> None:
    ready = asyncio.create_task(runtime.ready.wait(), name="runtime-ready")
    try:
        await asyncio.wait({task, ready}, timeout=timeout_s,
                           return_when=asyncio.FIRST_COMPLETED)
    finally:
        ready.cancel()
    if task.done():
        await task  # its error
        raise StartError("the daemon stopped before it was ready")
    if not runtime.ready.is_set():
        raise TimeoutError(f"the daemon was not ready within {timeout_s:g} s")


async def serve(cfg: Config, config_path: str | None = None,
                devices: Devices | None = None) -> None:
    """Run the daemon until SIGTERM; ``devices`` overrides the configured ones (tests)."""
    async with assemble(cfg, config_path, devices=devices) as daemon, \
            running(daemon) as task:
        await task  # until SIGTERM/SIGINT, or the error of a task that died


def run(config_path: str) -> int:
    """``vt-edge run``: 0 after SIGTERM; 2 with one line saying why if it cannot start."""
    cfg = load_config(config_path)
    try:
        with asyncio.Runner(loop_factory=new_event_loop) as runner:
            runner.run(serve(cfg, config_path))
    except StartError as exc:
        print(f"vt-edge: {exc}", file=sys.stderr)
        return 2
    log.info("exit")
    return 0


def _os_reason(exc: OSError) -> str:
    return os.strerror(exc.errno).lower() if exc.errno else str(exc)


def optional_services(runtime: Runtime) -> list[tuple[str, Coroutine[Any, Any, None]]]:
    """(task name, coroutine) of each service the configuration turns on."""
    cfg = runtime.cfg
    services: list[tuple[str, Coroutine[Any, Any, None]]] = []
    if cfg.runtime.record_mcap_dir:
        from edge.recordings.mcap_live import McapRecorder

        recorder = McapRecorder(runtime, cfg.runtime.record_mcap_dir,
                                cfg.runtime.record_mcap_segment_s,
                                record_format=cfg.runtime.record_format)
        services.append(("mcap-record", recorder.run()))
    if cfg.mqtt.enabled:
        from edge.interfaces.mqtt import MqttBridge

        services.append(("mqtt", MqttBridge(runtime, cfg.mqtt,
                                            cfg.api.max_candidates).run()))
    return [(name, _guarded(name, coro)) for name, coro in services]


async def _guarded(name: str, service: Coroutine[Any, Any, None]) -> None:
    """A service that fails is logged and ends: the press never depends on it."""
    try:
        await service
    except Exception:
        log.exception("%s failed; the daemon goes on without it", name)
