"""The HTTP API (aiohttp): trigger recognitions, read episodes, follow events.

Routes: ``POST /v1/recognize``, ``GET /v1/episodes/{id}``, ``GET /v1/events`` (server-sent
events), ``POST /v1/abort``, ``GET /healthz``, ``GET /metrics`` (Prometheus text); teaching
(:mod:`edge.runtime.teaching`): ``POST /v1/teach`` (``GET`` its progress),
``POST /v1/episodes/{id}/teach``, ``GET /v1/references``, ``DELETE /v1/references/{id}`` and
``DELETE /v1/references?label=L``; the operator page at ``/`` and its data routes
(:mod:`edge.interfaces.http.webui`).
Loopback only by default; bound anywhere else it refuses to start without a bearer token,
and then every route but ``/healthz`` requires it. Bad input gets a 4xx with a message a
person can act on, and nothing is half-done: validation happens before any arm motion.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextlib
import hmac
import json
import logging
import socket
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aiohttp import BodyPartReader, web
from aiohttp.http_exceptions import HttpProcessingError

from edge.core.config import ApiConfig
from edge.core.errors import (
    BadRequest,
    BusyError,
    ConfigError,
    EdgeError,
    NotFoundError,
    StateError,
)
from edge.interfaces.contracts import Serving
from edge.interfaces.http.webui import UI_HEADER, OperatorPage
from edge.interfaces.requests import (
    validate_candidates,
    validate_presses,
    validate_taught,
    validate_teach,
)
from edge.runtime.recognition import Presses
from edge.runtime.references import Source
from edge.runtime.teaching import listed

log = logging.getLogger(__name__)
# Bound beyond loopback, the API asks for a bearer token at least this long.
MIN_TOKEN_CHARS = 16
# Connections the listening socket queues until they are accepted (aiohttp's own default).
LISTEN_BACKLOG = 128
SSE_KEEPALIVE_S = 15.0
_RECOGNIZE_FIELDS = {"candidates", "wait", "image", "timeout_s", "presses", "pause_s"}
_IMAGE_MAGIC = (b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n")
_ROUTES = ("POST /v1/recognize, GET /v1/episodes/{id}, POST /v1/episodes/{id}/retry, "
           "GET /v1/events, POST /v1/abort, "
           "GET /healthz, GET /metrics, GET / (operator page), GET /v1/episodes?limit=N, "
           "GET /v1/episodes/{id}/image, GET /v1/episodes/{id}/trace, GET /v1/tactile, "
           "POST /v1/teach, GET /v1/teach, POST /v1/episodes/{id}/teach, GET /v1/references, "
           "DELETE /v1/references/{id}, DELETE /v1/references?label=L")


def load_token(cfg: ApiConfig) -> str:
    """The bearer token from the config (``$VTZERO_API_TOKEN`` applied) or its file."""
    token = cfg.token
    if cfg.token_file:
        try:
            token = Path(cfg.token_file).read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise ConfigError(f"api.token_file {cfg.token_file}: cannot read: {exc}") from None
    if not cfg.loopback_only and len(token) < MIN_TOKEN_CHARS:
        raise ConfigError(
            f"api.host = {cfg.host!r} exposes the API beyond this machine: set a bearer token "
            f"of at least {MIN_TOKEN_CHARS} characters (api.token_file or $VTZERO_API_TOKEN), "
            "or bind "
            "127.0.0.1")
    return token


def listen(cfg: ApiConfig) -> list[socket.socket]:
    """The API's listening sockets, bound now: the daemon binds its port before it opens any
    device (a taken port fails the start before any motor has torque) and serves on them
    once it has its runtime (:meth:`Api.start`). One per address of ``cfg.host``, as
    asyncio's ``create_server`` binds them; raises :class:`OSError`."""
    sockets: list[socket.socket] = []
    try:
        for family, kind, proto, _, address in socket.getaddrinfo(
                cfg.host or None, cfg.port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE):
            sock = socket.socket(family, kind, proto)
            sockets.append(sock)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            sock.bind(address)
            sock.listen(LISTEN_BACKLOG)
            sock.setblocking(False)
    except OSError:
        for sock in sockets:
            sock.close()
        raise
    return sockets


def _error(status: int, message: str, **extra: Any) -> web.Response:
    return web.json_response({"error": message, **extra}, status=status)


async def _json_object(request: web.Request) -> dict[str, Any]:
    if request.content_type != "application/json":
        raise BadRequest("send application/json")
    try:
        body = await request.json()
    except (ValueError, RecursionError, LookupError):  # LookupError: bad charset
        raise BadRequest("body is not valid JSON (or nested too deep, or not in its "
                         "charset)") from None
    if not isinstance(body, dict):
        raise BadRequest("body must be a JSON object")
    return body


def _source(request: web.Request) -> Source:
    """Who teaches: the operator page (its header) or another API client."""
    return "page" if request.headers.get(UI_HEADER) == "1" else "api"


def validate_image(data: bytes, max_bytes: int) -> bytes:
    if not data:
        raise BadRequest("image is empty")
    if len(data) > max_bytes:
        raise BadRequest(f"image has {len(data)} bytes (at most {max_bytes})")
    if not data.startswith(_IMAGE_MAGIC):
        raise BadRequest("image must be a JPEG or PNG file")
    return data


@dataclass
class _Parsed:
    candidates: list[str]
    image: bytes | None
    wait: bool
    timeout_s: float | None
    presses: Presses
    pause_s: float


class Api:
    def __init__(self, runtime: Serving, cfg: ApiConfig) -> None:
        self.runtime = runtime
        self.cfg = cfg
        self.token = load_token(cfg)
        self.app = web.Application(client_max_size=cfg.max_body_bytes,
                                   middlewares=[self._errors, self._auth])
        self.app.add_routes([
            web.post("/v1/recognize", self.recognize),
            web.get("/v1/episodes/{id}", self.episode),
            web.post("/v1/episodes/{id}/retry", self.retry),
            web.get("/v1/events", self.events),
            web.post("/v1/abort", self.abort),
            web.get("/healthz", self.healthz),
            web.get("/metrics", self.metrics),
            web.post("/v1/teach", self.teach),
            web.get("/v1/teach", self.teaching),
            web.post("/v1/episodes/{id}/teach", self.teach_episode),
            web.get("/v1/references", self.references),
            web.delete("/v1/references", self.remove_references),
            web.delete("/v1/references/{id}", self.remove_references),
        ])
        # The operator page at / and its data: edge/interfaces/http/webui.py.
        self.ui = OperatorPage(runtime, runtime, self.token)
        self.ui.install(self.app)
        # /v1/events streams never end by themselves: the server's shutdown ends them.
        self._event_streams: weakref.WeakSet[asyncio.Task] = weakref.WeakSet()
        self.app.on_shutdown.append(self._end_event_streams)
        self._runner: web.AppRunner | None = None
        self.port: int | None = None

    @web.middleware
    async def _errors(self, request: web.Request, handler):
        try:
            return await handler(request)
        except BadRequest as exc:
            return _error(400, str(exc))
        except NotFoundError as exc:
            return _error(404, str(exc).strip("'\""))
        except web.HTTPRequestEntityTooLarge:
            return _error(413, f"request body too large (at most {self.cfg.max_body_bytes} "
                               "bytes)")
        except web.HTTPException as exc:
            if exc.status < 400:
                raise
            # aiohttp's own refusals (no such route, wrong method) are JSON like ours.
            message = f"{exc.reason}: {request.method} {request.path}"
            if exc.status == 404:
                message += f"; the routes are {_ROUTES}"
            headers = {k: v for k, v in exc.headers.items() if k in ("Allow",)}
            return web.json_response({"error": message}, status=exc.status, headers=headers)
        except EdgeError as exc:
            log.warning("%s %s failed: %s", request.method, request.path, exc)
            return _error(503, str(exc))
        except Exception as exc:
            log.exception("%s %s: unexpected error", request.method, request.path)
            return _error(500, f"internal error ({type(exc).__name__}); see the daemon's log")

    @web.middleware
    async def _auth(self, request: web.Request, handler):
        if self.token and request.path != "/healthz":
            given = request.headers.get("Authorization", "")
            expected = f"Bearer {self.token}"
            if not hmac.compare_digest(given.encode(), expected.encode()):
                # The operator page: a browser's session cookie, or the login.
                verdict = self.ui.check(request)
                if verdict == "login":
                    return await self.ui.login(request)
                if verdict != "ok":
                    return web.json_response({"error": "missing or wrong bearer token"},
                                             status=401,
                                             headers={"WWW-Authenticate": "Bearer"})
        return await handler(request)

    async def start(self, sockets: list[socket.socket]) -> int:
        """Serve on ``sockets`` (bound by :func:`listen`)."""
        self._runner = web.AppRunner(self.app, access_log=None, handle_signals=False)
        await self._runner.setup()
        for sock in sockets:
            await web.SockSite(self._runner, sock).start()
        port: int = sockets[0].getsockname()[1]
        self.port = port
        log.info("API listening on http://%s:%s%s", self.cfg.host, port,
                 " (bearer token required)" if self.token else "")
        return port

    async def _end_event_streams(self, app: web.Application) -> None:
        for task in list(self._event_streams):
            task.cancel()

    async def close(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def _parse_recognize(self, request: web.Request) -> _Parsed:
        image: bytes | None = None
        if request.content_type == "multipart/form-data":
            try:
                fields, image = await self._read_multipart(request)
            except BadRequest:
                raise
            except (ValueError, LookupError, AssertionError, HttpProcessingError) as exc:
                # aiohttp's reader on a broken stream (no or a wrong boundary, a cut body,
                # a bad part header), an unknown charset, text that is not in its charset.
                raise BadRequest(f"malformed multipart/form-data body: "
                                 f"{type(exc).__name__}: {str(exc)[:200]}") from None
        elif request.content_type == "application/json":
            fields = await _json_object(request)
            unknown = sorted(set(fields) - _RECOGNIZE_FIELDS)
            if unknown:
                raise BadRequest(f"unknown field {unknown[0]!r}; known: "
                                 + ", ".join(sorted(_RECOGNIZE_FIELDS)))
            if "image" in fields:
                if not isinstance(fields["image"], str):
                    raise BadRequest("image must be a base64 string")
                try:
                    raw = base64.b64decode(fields["image"], validate=True)
                except (binascii.Error, ValueError):
                    raise BadRequest("image is not valid base64") from None
                image = validate_image(raw, self.cfg.max_body_bytes)
        else:
            raise BadRequest("send application/json or multipart/form-data")
        wait = fields.get("wait", False)
        if not isinstance(wait, bool):
            raise BadRequest("wait must be true or false")
        timeout = fields.get("timeout_s")
        if timeout is not None and (isinstance(timeout, bool)
                                    or not isinstance(timeout, int | float)
                                    or not 0 < timeout <= 600):
            raise BadRequest("timeout_s must be a number of seconds in (0, 600]")
        candidates = validate_candidates(fields.get("candidates"), self.cfg.max_candidates)
        presses, pause_s = validate_presses(fields)
        # (Decoded once, by the recognizer, before the arm moves: one that does not decode
        # is refused there with a BadRequest.)
        return _Parsed(candidates, image, wait, timeout, presses, pause_s)

    async def _read_multipart(self, request: web.Request) -> tuple[dict[str, Any],
                                                                   bytes | None]:
        # aiohttp's client_max_size covers read()/post(), not a streamed multipart body:
        # count the bytes here, so no body is held in memory past max_body_bytes.
        fields: dict[str, Any] = {}
        image: bytes | None = None
        left = self.cfg.max_body_bytes
        reader = await request.multipart()
        async for part in reader:
            if not isinstance(part, BodyPartReader):
                raise BadRequest("nested multipart bodies are not accepted")
            name = part.name or ""
            if name not in _RECOGNIZE_FIELDS:
                raise BadRequest(f"unknown field {name!r}; known: "
                                 + ", ".join(sorted(_RECOGNIZE_FIELDS)))
            chunks = []
            while chunk := await part.read_chunk():
                left -= len(chunk)
                if left < 0:
                    raise web.HTTPRequestEntityTooLarge(max_size=self.cfg.max_body_bytes,
                                                        actual_size=self.cfg.max_body_bytes
                                                        - left)
                chunks.append(chunk)
            data = b"".join(chunks)  # not decoded: no Content-Encoding bomb either
            if name == "image":
                image = validate_image(data, self.cfg.max_body_bytes)
            else:
                text = data.decode(part.get_charset(default="utf-8"))
                try:
                    fields[name] = json.loads(text)
                except (ValueError, RecursionError):
                    fields[name] = text
        return fields, image

    async def recognize(self, request: web.Request) -> web.Response:
        parsed = await self._parse_recognize(request)
        try:
            episode = await self.runtime.recognize(parsed.candidates, parsed.image,
                                                   parsed.wait, parsed.timeout_s, "api",
                                                   parsed.presses, parsed.pause_s)
        except BusyError as exc:
            return _error(409, str(exc), episode=exc.episode_id)
        status = 200 if parsed.wait else 202
        return web.json_response(episode.to_json(), status=status)

    async def episode(self, request: web.Request) -> web.Response:
        episode = await self.runtime.episode(request.match_info["id"])
        return web.json_response(episode.to_json())

    async def retry(self, request: web.Request) -> web.Response:
        """Ask the VLM again about a vlm_error or invalid_answer episode; its new state."""
        try:
            episode = await self.runtime.retry(request.match_info["id"])
        except StateError as exc:
            return _error(409, str(exc))
        return web.json_response(episode.to_json())

    # --- teaching ---------------------------------------------------------------------------
    async def teach(self, request: web.Request) -> web.Response:
        """Press the object N times and teach it: 202 as it started (follow ``teach`` events
        or ``GET /v1/teach``), or with ``"wait": true`` 200 once it ended."""
        body = await _json_object(request)
        wait = body.pop("wait", False)
        if not isinstance(wait, bool):
            raise BadRequest("wait must be true or false")
        req = validate_teach(body, frozenset({"wait"}))
        try:
            run = await self.runtime.teach(req.label, req.description, req.presses,
                                           req.append, _source(request), pause_s=req.pause_s,
                                           wait=wait)
        except BusyError as exc:
            return _error(409, str(exc), episode=exc.episode_id)
        return web.json_response(run.to_json(), status=200 if wait else 202)

    async def teaching(self, request: web.Request) -> web.Response:
        run = self.runtime.teaching()
        if run is None:
            raise NotFoundError("nothing was taught since the daemon started")
        return web.json_response(run.to_json())

    async def teach_episode(self, request: web.Request) -> web.Response:
        """What the episode's object really was: its press joins the references."""
        label, description = validate_taught(await _json_object(request))
        try:
            ref = await self.runtime.teach_episode(request.match_info["id"], label,
                                                   description, _source(request))
        except (BusyError, StateError) as exc:
            return _error(409, str(exc))
        return web.json_response(listed(ref))

    async def references(self, request: web.Request) -> web.Response:
        return web.json_response(await self.runtime.references())

    async def remove_references(self, request: web.Request) -> web.Response:
        """``/v1/references/{id}``, or ``/v1/references?label=L``: every one of a label."""
        ref_id = request.match_info.get("id")
        label = request.query.get("label")
        if ref_id is None and not label:
            raise BadRequest("say which references to remove: DELETE /v1/references/{id}, or "
                             "/v1/references?label=L")
        removed = await self.runtime.remove_references(ref_id, None if ref_id else label)
        return web.json_response({"removed": [listed(r) for r in removed]})

    async def abort(self, request: web.Request) -> web.Response:
        aborted = await self.runtime.abort()
        return web.json_response({"aborted": aborted})

    async def healthz(self, request: web.Request) -> web.Response:
        health = self.runtime.health()
        return web.json_response(health.to_json(), status=200 if health.ok else 503)

    async def metrics(self, request: web.Request) -> web.Response:
        return web.Response(text=self.runtime.metrics_text(),
                            content_type="text/plain", charset="utf-8",
                            headers={"X-Content-Type-Options": "nosniff"})

    async def events(self, request: web.Request) -> web.StreamResponse:
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                           "Cache-Control": "no-cache"})
        await resp.prepare(request)
        self._event_streams.add(asyncio.current_task())
        with contextlib.suppress(ConnectionResetError), self.runtime.subscribe() as events:
            while True:
                try:
                    # A timeout cancels only this wait; the subscription goes on.
                    event = await asyncio.wait_for(events.get(), SSE_KEEPALIVE_S)
                except TimeoutError:
                    await resp.write(b": keepalive\n\n")
                    continue
                await resp.write(f"event: {event.kind}\n"
                                 f"data: {json.dumps(event.to_json())}\n\n".encode())
        return resp
