"""The optional services beside the press, started as named tasks of the daemon's root
TaskGroup: the live MCAP recording (``[runtime] record_mcap_dir``) and the MQTT bridge
(``[mqtt]``). Each talks to the runtime only through the API's ``Runtime`` contract."""

from __future__ import annotations

import logging
from collections.abc import Coroutine
from typing import Any

log = logging.getLogger(__name__)


def optional_services(runtime: Any) -> list[tuple[str, Coroutine[Any, Any, None]]]:
    """(task name, coroutine) of each service the configuration turns on."""
    cfg = runtime.cfg
    services: list[tuple[str, Coroutine[Any, Any, None]]] = []
    if cfg.runtime.record_mcap_dir:
        from edge.daemon.mcap_live import McapRecorder

        recorder = McapRecorder(runtime, cfg.runtime.record_mcap_dir,
                                cfg.runtime.record_mcap_segment_s,
                                record_format=cfg.runtime.record_format,
                                sensor_model=cfg.sensor.model)
        services.append(("mcap-record", recorder.run()))
    if cfg.mqtt.enabled:
        from edge.daemon.mqtt import MqttBridge

        services.append(("mqtt", MqttBridge(runtime, cfg.mqtt).run()))
    return [(name, _guarded(name, coro)) for name, coro in services]


async def _guarded(name: str, service: Coroutine[Any, Any, None]) -> None:
    """A service that fails is logged and ends: the press never depends on it."""
    try:
        await service
    except Exception:
        log.exception("%s failed; the daemon goes on without it", name)
