"""The MQTT bridge: drive the robot and follow its results through a broker (``[mqtt]``).

Topics under the robot's prefix ``P`` (``mqtt.prefix``, default ``vtzero/<hostname>``)::

    in   P/cmd/recognize  {"candidates": [...], "request_id": "...", "presses", "pause_s"}:
                          start a recognition (the configured camera takes the photo);
                          request_id, presses and pause_s (as POST /v1/recognize) optional
    in   P/cmd/abort      empty, or {"request_id": "..."}: abort the running press
    in   P/cmd/teach      {"label", "description", "presses", "append", "pause_s",
                          "request_id"} (as POST /v1/teach): press the object and teach it
    out  P/ack            QoS 1   a command taken: {"command", "request_id", "episode"},
                                  {"command": "abort", "aborted"} or {"command": "teach",
                                  "request_id", "label", "presses", "status": "running"}
    out  P/state          QoS 1, retained  press states: {"state", "episode", "t"}
    out  P/result         QoS 1   each episode once final: {"episode", "request_id",
                                  "status", "label", "reason", "error", "topk", "description",
                                  "familiarity", "unfamiliar", "presses", "fusion", ...};
                                  each teaching once ended: {"command": "teach",
                                  "request_id", "label", "status", "episodes", "references",
                                  "error", ...} (its presses' episodes have their own)
    out  P/error          QoS 1   a command refused, and why: nothing moved
    out  P/health         QoS 1, retained  {"status": "online", ...GET /healthz} on connect
                                  and on change; "offline" as the last will and at shutdown

The press never waits for the broker: the runtime's event stream feeds a bounded outbox
(``mqtt.queue_size``; press states are dropped before results when it is full) that one
task drains while connected. A message leaves the outbox only once the broker acknowledged
it (QoS 1), so results produced while the broker is away are published after the
reconnection (at least once). Reconnection: :mod:`edge.core.reconnect`, its capped exponential
backoff with jitter.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import json
import logging
import re
import socket
import ssl
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from edge.core.backoff import Backoff
from edge.core.config import MqttConfig
from edge.core.errors import BadRequest, BusyError, ConfigError, EdgeError
from edge.core.reconnect import Reconnect
from edge.core.tasks import cancel_and_wait
from edge.interfaces.contracts import Serving
from edge.interfaces.requests import validate_candidates, validate_presses, validate_teach
from edge.runtime.domain import (
    Episode,
    EpisodeFinished,
    Health,
    Hello,
    Label,
    PressSummary,
    StateChanged,
    TeachProgress,
    VLMRefused,
)

log = logging.getLogger(__name__)

# A command larger than this is refused unread.
MAX_COMMAND_BYTES = 64 * 1024
MAX_REQUEST_ID_CHARS = 128
# How often the health is checked for a change worth publishing, and republished anyway.
HEALTH_CHECK_S = 1.0
HEALTH_REFRESH_S = 60.0
# Episodes remembered (request ids, results already published).
REMEMBERED = 1000
# Each reconnect waits 0.8 to 1.2 times the backoff: robots sharing a broker come back apart.
RECONNECT_SPREAD = (0.8, 1.2)
# Reading why a connection ended, after it has (the answer is already there).
_LOSS_READ_S = 0.5
_RECOGNIZE_FIELDS = {"candidates", "request_id", "presses", "pause_s"}
_TEACH_EXTRA = frozenset({"request_id"})
# What of the press a result carries.
_RESULT_PRESS = PressSummary.keys("result", "message", "stop_latency_ms")


class CommandError(EdgeError, ValueError):
    """A command from the broker that is malformed; the message says what is wrong."""


@dataclass
class Outgoing:
    topic: str
    payload: bytes
    retain: bool = False
    result: bool = False  # a result (kept before press states when the outbox is full)


def _health_key(health: Health) -> tuple[object, ...]:
    """The part of the health published as soon as it changes: the verdict and its reasons
    (not the frame's age, which changes at every check)."""
    return (health.ok, health.ready, health.sensor_fresh, health.bus_error, health.store_error,
            health.sensor_error, health.vlm_error)


def topic_safe(name: str) -> str:
    """A host name as one topic level (no wildcard, no separator)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name) or "robot"


def read_password(cfg: MqttConfig) -> str | None:
    if not cfg.password_file:
        return None
    try:
        return Path(cfg.password_file).read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise ConfigError(f"mqtt.password_file {cfg.password_file}: cannot read: "
                          f"{exc.strerror or exc}") from None


def tls_context(cfg: MqttConfig) -> ssl.SSLContext | None:
    if not cfg.tls:
        return None
    try:
        return ssl.create_default_context(cafile=cfg.ca_file or None)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(f"mqtt.ca_file {cfg.ca_file}: cannot load: {exc}") from None


def check_config(cfg: MqttConfig) -> None:
    """What can fail at start, checked before any device is touched: the client library,
    the password file, the CA bundle."""
    if not cfg.enabled:
        return
    try:
        import aiomqtt  # noqa: F401
    except ImportError:
        raise ConfigError("mqtt.enabled = true needs the MQTT client: pip install "
                          "'vtzero[mqtt]'") from None
    read_password(cfg)
    tls_context(cfg)


class MqttBridge:
    """The ``mqtt`` task: ``await MqttBridge(runtime, cfg.mqtt,
    cfg.api.max_candidates).run()``."""

    def __init__(self, runtime: Serving, cfg: MqttConfig, max_candidates: int,
                 hostname: str | None = None) -> None:
        self.runtime = runtime
        self.cfg = cfg
        self.max_candidates = max_candidates
        host = topic_safe(hostname or socket.gethostname())
        self.prefix = cfg.prefix or f"vtzero/{host}"
        self.client_id = cfg.client_id or f"vtzero-{host}"
        self._outbox: collections.deque[Outgoing] = collections.deque()
        self._wakeup = asyncio.Event()
        self._requests: collections.OrderedDict[str, str | None] = collections.OrderedDict()
        self._published: collections.OrderedDict[str, None] = collections.OrderedDict()
        # The request id of the teaching under way (one at a time), for its result.
        self._teach_request: str | None = None
        self.connected = asyncio.Event()
        self._link = Reconnect(f"MQTT broker {cfg.host}:{cfg.port}",
                               Backoff(cfg.reconnect_base_s, cfg.reconnect_max_backoff_s,
                                       RECONNECT_SPREAD),
                               log, on_up=self.connected.set, on_loss=self.connected.clear)
        self.dropped = 0

    def topic(self, name: str) -> str:
        return f"{self.prefix}/{name}"

    # --- the connection ------------------------------------------------------------------
    async def run(self) -> None:
        import aiomqtt

        password = await asyncio.to_thread(read_password, self.cfg)
        tls = tls_context(self.cfg)
        pump = asyncio.create_task(self._pump(), name="mqtt-events")
        try:
            await self._link.run(functools.partial(self._session, password, tls),
                                 (aiomqtt.MqttError,))
        finally:
            await cancel_and_wait(pump)

    async def _session(self, password: str | None, tls: ssl.SSLContext | None) -> bool:
        """One connection, from dialling to its loss; raises when it never came up."""
        import aiomqtt

        health = self.topic("health")
        client = aiomqtt.Client(
            self.cfg.host, self.cfg.port, identifier=self.client_id,
            username=self.cfg.username or None, password=password,
            will=aiomqtt.Will(health, b"offline", qos=1, retain=True),
            keepalive=self.cfg.keepalive_s, timeout=self.cfg.connect_timeout_s,
            tls_context=tls)
        try:
            await self._connected_session(client)
        except aiomqtt.MqttError as exc:
            if not self._link.connected:
                raise  # a failed try: the reconnect loop says it
            # (The message iterator's error carries the broker's reason as its cause.)
            log.warning("MQTT broker %s:%d: connection lost (%s)", self.cfg.host,
                        self.cfg.port, exc.__cause__ or exc)
        return True

    async def _connected_session(self, client: Any) -> None:
        import aiomqtt

        health = self.topic("health")
        try:
            async with client:
                self._link.up()
                log.info("MQTT: connected to %s:%d as %s; topics %s/#", self.cfg.host,
                         self.cfg.port, self.client_id, self.prefix)
                try:
                    await client.subscribe([(self.topic("cmd/recognize"), 1),
                                            (self.topic("cmd/abort"), 1),
                                            (self.topic("cmd/teach"), 1)],
                                           timeout=self.cfg.publish_timeout_s)
                    tasks = [asyncio.create_task(self._receive(client), name="mqtt-receive"),
                             asyncio.create_task(self._send(client), name="mqtt-send"),
                             asyncio.create_task(self._health(client), name="mqtt-health")]
                    try:
                        done, _ = await asyncio.wait(tasks,
                                                     return_when=asyncio.FIRST_COMPLETED)
                    finally:
                        for task in tasks:
                            task.cancel()
                        await asyncio.gather(*tasks, return_exceptions=True)
                    for task in done:
                        if task.exception() is not None:
                            raise task.exception()  # type: ignore[misc]
                except asyncio.CancelledError:
                    # The daemon stops: say so (the will is for a death, not a shutdown).
                    with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
                        await client.publish(health, b"offline", qos=1, retain=True,
                                             timeout=1.0)
                    raise
        finally:
            if self._link.connected:
                await _read_loss(client)

    async def _send(self, client: Any) -> None:
        while True:
            if not self._outbox:
                self._wakeup.clear()
                await self._wakeup.wait()
                continue
            item = self._outbox[0]
            await client.publish(item.topic, item.payload, qos=1, retain=item.retain,
                                 timeout=self.cfg.publish_timeout_s)
            # Acknowledged: only now is it off the outbox (a lost connection resends it).
            if self._outbox and self._outbox[0] is item:
                self._outbox.popleft()

    async def _health(self, client: Any) -> None:
        last: tuple | None = None
        sent = 0.0
        while True:
            health = self.runtime.health()
            key = _health_key(health)
            if key != last or time.monotonic() - sent >= HEALTH_REFRESH_S:
                payload = json.dumps({"status": "online", "client_id": self.client_id,
                                      **health.to_json()}, default=str).encode()
                await client.publish(self.topic("health"), payload, qos=1, retain=True,
                                     timeout=self.cfg.publish_timeout_s)
                last, sent = key, time.monotonic()
            await asyncio.sleep(HEALTH_CHECK_S)

    # --- outgoing ---------------------------------------------------------------------
    def _enqueue(self, name: str, body: dict[str, Any], *, retain: bool = False,
                 result: bool = False) -> None:
        item = Outgoing(self.topic(name), json.dumps(body, default=str).encode(), retain,
                        result)
        if len(self._outbox) >= self.cfg.queue_size:
            # Full (the broker has been away long): a press state goes before a result.
            victim = next((o for o in self._outbox if not o.result), self._outbox[0])
            self._outbox.remove(victim)
            self.dropped += 1
            log.warning("MQTT outbox full (%d): dropped a message for %s", self.cfg.queue_size,
                        victim.topic)
        self._outbox.append(item)
        self._wakeup.set()

    async def _pump(self) -> None:
        """The runtime's events into the outbox (never waits for the broker)."""
        with self.runtime.subscribe() as stream:
            async for event in stream:
                if isinstance(event, Hello | StateChanged):
                    self._enqueue("state", {
                        "state": event.state, "episode": event.episode,
                        "t": event.t if isinstance(event, StateChanged) else time.time(),
                    }, retain=True)
                elif isinstance(event, Label | VLMRefused | EpisodeFinished):
                    self._result(event.episode)
                elif (isinstance(event, TeachProgress) and event.step in ("done", "failed")
                      and event.run is not None):
                    request_id, self._teach_request = self._teach_request, None
                    self._enqueue("result", {"command": "teach", "request_id": request_id,
                                             **event.run.to_json()}, result=True)

    def _result(self, episode: Episode) -> None:
        """``episode``'s result, once it is final (as the event carries it: the store is
        not read again)."""
        if episode.id in self._published or not episode.status.final:
            return  # (a VLM retry will give its result event)
        _remember(self._published, episode.id, None)
        self._enqueue("result", {
            "episode": episode.id, "request_id": self._requests.pop(episode.id, None),
            "status": episode.status.value, "label": episode.label, "reason": episode.reason,
            "error": episode.why,
            "candidates": episode.candidates, "topk": episode.topk_json(),
            "description": episode.description, "familiarity": episode.familiarity,
            "unfamiliar": episode.unfamiliar, "timings": episode.timings,
            "source": episode.source, "press": episode.press_json(_RESULT_PRESS),
            # A recognition of several presses: each press as it went, and how they were
            # fused (None for one press).
            "presses": episode.presses, "fusion": episode.fusion,
        }, result=True)

    # --- commands ---------------------------------------------------------------------
    async def _receive(self, client: Any) -> None:
        async for message in client.messages:
            payload = message.payload
            data = payload if isinstance(payload, bytes | bytearray) else \
                str(payload if payload is not None else "").encode()
            await self.command(str(message.topic), bytes(data))

    async def command(self, topic: str, payload: bytes) -> None:
        """Handle one command message; a refusal is published to ``P/error``."""
        name = topic.removeprefix(self.prefix + "/cmd/")
        request_id: str | None = None
        try:
            body = _parse(payload)
            request_id = _request_id(body)
            if name == "recognize":
                await self._recognize(body, request_id)
            elif name == "teach":
                await self._teach(body, request_id)
            elif name == "abort":
                unknown = sorted(set(body) - {"request_id"})
                if unknown:
                    raise CommandError(f"unknown field {unknown[0]!r}; abort takes only "
                                       "request_id")
                aborted = await self.runtime.abort()
                self._enqueue("ack", {"command": "abort", "request_id": request_id,
                                      "aborted": aborted})
            else:
                raise CommandError(f"unknown command topic {topic!r}")
        except (CommandError, BadRequest) as exc:
            log.warning("MQTT command %s refused: %s", name, exc)
            self._enqueue("error", {"command": name, "request_id": request_id,
                                    "error": str(exc)})
        except BusyError as exc:
            self._enqueue("error", {"command": name, "request_id": request_id,
                                    "error": str(exc), "episode": exc.episode_id})
        except EdgeError as exc:
            self._enqueue("error", {"command": name, "request_id": request_id,
                                    "error": str(exc)})

    async def _recognize(self, body: dict[str, Any], request_id: str | None) -> None:
        unknown = sorted(set(body) - _RECOGNIZE_FIELDS)
        if unknown:
            raise CommandError(f"unknown field {unknown[0]!r}; known: "
                               + ", ".join(sorted(_RECOGNIZE_FIELDS)))
        candidates = validate_candidates(body.get("candidates"), self.max_candidates)
        presses, pause_s = validate_presses(body)
        episode = await self.runtime.recognize(candidates, None, False, None, "mqtt",
                                               presses, pause_s)
        _remember(self._requests, episode.id, request_id)
        self._enqueue("ack", {"command": "recognize", "request_id": request_id,
                              "episode": episode.id, "status": str(episode.status)})

    async def _teach(self, body: dict[str, Any], request_id: str | None) -> None:
        req = validate_teach(body, _TEACH_EXTRA)
        run = await self.runtime.teach(req.label, req.description, req.presses, req.append,
                                       "mqtt", pause_s=req.pause_s, wait=False)
        self._teach_request = request_id
        self._enqueue("ack", {"command": "teach", "request_id": request_id,
                              "label": run.label, "presses": run.presses,
                              "status": run.status})


async def _read_loss(client: Any) -> None:
    """Read why a connection that was up ended, once the client has left it: aiomqtt says it
    to its message iterator only, and when a publish noticed the loss first nobody asked
    (asyncio would log "Future exception was never retrieved"). Messages still queued go
    with the connection."""
    import aiomqtt

    with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
        async with asyncio.timeout(_LOSS_READ_S):
            async for _ in client.messages:
                pass


def _parse(payload: bytes) -> dict[str, Any]:
    if len(payload) > MAX_COMMAND_BYTES:
        raise CommandError(f"payload of {len(payload)} bytes (at most {MAX_COMMAND_BYTES})")
    if not payload.strip():
        return {}
    try:
        body = json.loads(payload)
    except (ValueError, RecursionError):  # (UnicodeDecodeError is a ValueError)
        raise CommandError("payload is not valid JSON (UTF-8)") from None
    if not isinstance(body, dict):
        raise CommandError(f"payload must be a JSON object, not {type(body).__name__}")
    return body


def _request_id(body: dict[str, Any]) -> str | None:
    value = body.get("request_id")
    if value is None:
        return None
    if (not isinstance(value, str) or not value or len(value) > MAX_REQUEST_ID_CHARS
            or not value.isprintable()):
        raise CommandError(f"request_id must be a printable string of 1..{MAX_REQUEST_ID_CHARS}"
                           f" characters, got {str(value)[:40]!r}")
    return value


def _remember(memory: collections.OrderedDict, key: str, value: Any) -> None:
    memory[key] = value
    while len(memory) > REMEMBERED:
        memory.popitem(last=False)
