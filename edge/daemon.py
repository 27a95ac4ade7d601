"""``vt-edge run``: assemble the daemon from a configuration file and run it."""

from __future__ import annotations

import asyncio
import logging
import os
import time
from pathlib import Path

from edge.api import Api
from edge.config import Config, load_config
from edge.runtime import Devices, Runtime
from edge.store import EpisodeStore
from edge.systemd import Notifier

log = logging.getLogger(__name__)


def state_dir(cfg: Config) -> Path:
    # Under systemd, StateDirectory= gives the daemon its writable place.
    return Path(os.environ.get("VTZERO_STATE_DIR") or cfg.runtime.state_dir)


def load_model(cfg: Config):
    from edge.model import load_model as _load

    return _load(cfg.runtime.models_dir)


def make_vlm(cfg: Config):
    from edge.vlm import make_client

    return make_client(cfg.vlm, Path(cfg.runtime.models_dir) / "prompts")


async def serve(cfg: Config, config_path: str | None = None,
                devices: Devices | None = None) -> None:
    """Run the daemon until SIGTERM; ``devices`` overrides the configured ones (tests)."""
    started = time.monotonic()
    notifier = Notifier()
    notifier.status("starting: loading model")
    model = await asyncio.to_thread(load_model, cfg)
    vlm = make_vlm(cfg)
    store = EpisodeStore(state_dir(cfg) / "episodes")
    if devices is None:
        from edge.devices import open_devices

        notifier.status("starting: connecting devices")
        devices = await open_devices(cfg)

    def reload():
        new = load_config(config_path) if config_path else cfg
        return new, load_model(new), make_vlm(new)

    runtime = Runtime(cfg, devices, model, vlm, store, notifier, reload=reload)
    runtime.started_at = started
    api = Api(runtime, cfg.api)
    try:
        await runtime.run(api)
    finally:
        await vlm.close()
        notifier.close()


def run(config_path: str) -> int:
    cfg = load_config(config_path)
    asyncio.run(serve(cfg, config_path))
    log.info("exit")
    return 0
