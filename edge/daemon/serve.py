"""``vt-edge run``: assemble the daemon from a configuration file and run it."""

from __future__ import annotations

import asyncio
import logging
import os
import resource
import selectors
import time
from dataclasses import replace
from pathlib import Path

from edge.core.config import Config, load_config
from edge.core.model import ModelRef
from edge.core.model import model_ref as _model_ref
from edge.daemon.api import Api, load_token
from edge.daemon.compute import ComputeWorker, warm_up
from edge.daemon.mqtt import check_config as check_mqtt
from edge.daemon.runtime import Devices, Runtime
from edge.daemon.store import EpisodeStore
from edge.daemon.systemd import Notifier

log = logging.getLogger(__name__)

# select(2) handles file descriptors below FD_SETSIZE only.
FD_SETSIZE = 1024


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
    return asyncio.SelectorEventLoop(selectors.SelectSelector())


def state_dir(cfg: Config) -> Path:
    # Under systemd, StateDirectory= gives the daemon its writable place.
    return Path(os.environ.get("VTZERO_STATE_DIR") or cfg.runtime.state_dir)


def model_ref(cfg: Config) -> ModelRef:
    """The configured model by its manifest; the compute process loads and verifies it."""
    return _model_ref(cfg.runtime.models_dir)


def vlm_config(cfg: Config):
    """The ``[vlm]`` section with ``$VTZERO_VLM_URL`` / ``$VTZERO_VLM_MODEL`` applied, and
    the prompt templates of the configured models directory."""
    vlm = cfg.vlm
    url = os.environ.get("VTZERO_VLM_URL", "").strip()
    model = os.environ.get("VTZERO_VLM_MODEL", "").strip()
    if url:
        vlm = replace(vlm, base_url=url.rstrip("/"))
    if model:
        vlm = replace(vlm, model=model)
    if vlm.prompt_dir is None:
        vlm = replace(vlm, prompt_dir=Path(cfg.runtime.models_dir) / "prompts")
    vlm.validate("vlm (with $VTZERO_VLM_URL/$VTZERO_VLM_MODEL)")
    return vlm


def make_vlm(cfg: Config, compute: ComputeWorker | None = None):
    """The configured VLM client; with ``compute``, images are prepared in that process."""
    from edge.core.vlm import make_vlm as _make

    return _make(vlm_config(cfg), **({"offload": compute.run} if compute else {}))


async def serve(cfg: Config, config_path: str | None = None,
                devices: Devices | None = None) -> None:
    """Run the daemon until SIGTERM; ``devices`` overrides the configured ones (tests)."""
    started = time.monotonic()
    # A configuration the API refuses (exposed without a token) is refused before any
    # device is touched: no torque on an arm the daemon will not run.
    load_token(cfg.api)
    check_mqtt(cfg.mqtt)  # (issue 12: the MQTT bridge's client, password and CA files)
    notifier = Notifier()
    notifier.status("starting: loading model")
    model = await asyncio.to_thread(model_ref, cfg)
    async with ComputeWorker() as compute:
        # Every model file verified and the encoder run once, before any device is touched:
        # no torque on an arm the daemon could not recognise with.
        await compute.run(warm_up, model)
        vlm = make_vlm(cfg, compute)
        store = EpisodeStore(state_dir(cfg) / "episodes")
        if devices is None:
            from edge.daemon.devices import open_devices

            notifier.status("starting: connecting devices")
            devices = await open_devices(cfg)

        def reload():
            new = load_config(config_path) if config_path else cfg
            return new, model_ref(new), make_vlm(new, compute)

        runtime = Runtime(cfg, devices, model, vlm, store, compute, notifier, reload=reload)
        runtime.started_at = started
        api = Api(runtime, cfg.api)
        try:
            await runtime.run(api)
        finally:
            await vlm.close()
            notifier.close()


def run(config_path: str) -> int:
    cfg = load_config(config_path)
    with asyncio.Runner(loop_factory=new_event_loop) as runner:
        runner.run(serve(cfg, config_path))
    log.info("exit")
    return 0
