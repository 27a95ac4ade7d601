"""The operator page at ``/`` and the data it reads, on the API's own aiohttp app.

Plain HTML, CSS and JavaScript shipped in ``edge/interfaces/http/static`` (no build step, nothing
fetched from elsewhere: it works offline). It shows the daemon's state and health, a live
view of both pads (``GET /v1/tactile``: server-sent events at 30 Hz from
:mod:`edge.interfaces.http.tactile_feed`), a Recognize control and an Abort button, a Teach
panel with the taught references (the API's own routes; "this was..." on each episode), and
the last episodes (``GET /v1/episodes?limit=N``) with their photo
(``/v1/episodes/{id}/image``) and press trace (``/v1/episodes/{id}/trace``, computed in the
compute process by :mod:`edge.interfaces.http.trace`).

Authentication: behind the same middleware as the API. Where the API needs a bearer token
(bound beyond loopback, or a token configured), a browser, which cannot put a header on a
page load or an EventSource, logs in once: the login form (or ``/?token=...``, which is
exchanged at once and the token dropped from the address) sets an HttpOnly, SameSite=Strict
cookie holding an HMAC of the token, not the token. A cookie only authorises a state-changing
request that also carries the ``X-Vtzero-UI`` header (which a cross-site form cannot send).
"""

from __future__ import annotations

import asyncio
import collections
import hashlib
import hmac
import html
import importlib.resources
import logging
from pathlib import Path
from typing import Any

from aiohttp import web

from edge.core.errors import NotFoundError
from edge.interfaces.contracts import Recognitions
from edge.interfaces.http.tactile_feed import TactileFeed
from edge.interfaces.http.trace import press_trace
from edge.runtime.domain import PressSummary
from edge.runtime.taps import LiveTaps

log = logging.getLogger(__name__)

COOKIE = "vtzero_ui"
UI_HEADER = "X-Vtzero-UI"
EPISODES_DEFAULT = 10
EPISODES_MAX = 200
TRACE_CACHE = 64
# What of the press the episode list carries (the page reads stop_latency_ms).
LISTED_PRESS = PressSummary.keys("result", "message", "stop_latency_ms", "peak_level")
# A wrong token at the login form waits this long (slows guessing a 16+ character token
# further, and costs a browser nothing).
LOGIN_DELAY_S = 0.5
_STATIC = {"app.js": "text/javascript", "app.css": "text/css", "index.html": "text/html"}
_SAFE_METHODS = ("GET", "HEAD", "OPTIONS")
_PAGE_HEADERS = {
    "Cache-Control": "no-cache",
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; "
                               "style-src 'self'; script-src 'self'; connect-src 'self'; "
                               "frame-ancestors 'none'; form-action 'self'",
}
_LOGIN_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>vtzero: log in</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><link rel="icon" href="data:,">
<link rel="stylesheet" href="/static/app.css"></head>
<body class="login"><form method="post" action="/login" id="login">
<h1>vtzero operator page</h1>
<p>This daemon's API needs its bearer token (<code>api.token_file</code> or
<code>$VTZERO_API_TOKEN</code>).</p>
<label>Token <input type="password" name="token" id="token" autocomplete="current-password"
 required autofocus></label> <button type="submit">Log in</button>
<p class="error" id="login-error">{error}</p></form></body></html>
"""


class OperatorPage:
    def __init__(self, recognitions: Recognitions, taps: LiveTaps, token: str) -> None:
        self.recognitions = recognitions
        self.token = token
        self.feed = TactileFeed(taps)
        self._static: dict[str, bytes] = {}
        self._traces: collections.OrderedDict[str, dict[str, Any]] = collections.OrderedDict()

    def install(self, app: web.Application) -> None:
        """The routes, and the end of the live feed when the server stops (its streams
        would otherwise hold the API's shutdown)."""
        app.add_routes(self.routes())
        app.on_shutdown.append(self._end_streams)

    async def _end_streams(self, app: web.Application) -> None:
        self.feed.close()

    def routes(self) -> list[web.RouteDef]:
        return [
            web.get("/", self.page),
            web.get("/login", self.login),
            web.post("/login", self.login),
            web.post("/logout", self.login),
            web.get("/static/{name}", self.static),
            web.get("/v1/episodes", self.episodes),
            web.get("/v1/episodes/{id}/image", self.image),
            web.get("/v1/episodes/{id}/trace", self.trace),
            web.get("/v1/tactile", self.tactile),
            web.post("/v1/tactile/tare", self.tare),
        ]

    # --- authentication ----------------------------------------------------------------
    def _session(self) -> str:
        return hmac.new(self.token.encode(), b"vtzero operator page session",
                        hashlib.sha256).hexdigest()

    def _cookie_ok(self, request: web.Request) -> bool:
        given = request.cookies.get(COOKIE, "")
        return bool(self.token and given) and hmac.compare_digest(given.encode(),
                                                                  self._session().encode())

    def check(self, request: web.Request) -> str:
        """For a request without the bearer header: ``ok`` (the session cookie, or a
        static file), ``login`` (a page load to answer with the login), else ``refuse``."""
        if request.path.startswith("/static/") and request.method in _SAFE_METHODS:
            return "ok"
        if request.path in ("/login", "/logout") or (request.path == "/"
                                                       and "token" in request.query):
            return "login"
        if self._cookie_ok(request):
            if request.method in _SAFE_METHODS or request.headers.get(UI_HEADER) == "1":
                return "ok"
            return "refuse"
        return "login" if request.path == "/" and request.method in _SAFE_METHODS else "refuse"

    async def login(self, request: web.Request) -> web.StreamResponse:
        """The login form, the token exchanged for the session cookie, or the logout."""
        if request.path == "/logout":
            resp = _see_other("/login" if self.token else "/")
            resp.del_cookie(COOKIE, path="/")
            return resp
        if not self.token:
            return _see_other("/")
        given = request.query.get("token")
        if request.method == "POST":
            form = await request.post()
            value = form.get("token")
            given = value if isinstance(value, str) else None
        if given is not None:
            if hmac.compare_digest(given.strip().encode(), self.token.encode()):
                resp = _see_other("/")
                resp.set_cookie(COOKIE, self._session(), path="/", httponly=True,
                                samesite="Strict", secure=_https(request))
                log.info("operator page: logged in from %s", request.remote)
                return resp
            log.warning("operator page: wrong token from %s", request.remote)
            await asyncio.sleep(LOGIN_DELAY_S)
            return self._login_form("wrong token", 401)
        if self._cookie_ok(request):
            return _see_other("/")
        return self._login_form("", 401)

    def _login_form(self, error: str, status: int) -> web.Response:
        return web.Response(text=_LOGIN_PAGE.replace("{error}", html.escape(error)),
                            status=status, content_type="text/html", headers=_PAGE_HEADERS)

    # --- the page -------------------------------------------------------------------------
    async def _file(self, name: str) -> bytes:
        if name not in self._static:
            ref = importlib.resources.files("edge.interfaces.http") / "static" / name
            self._static[name] = await asyncio.to_thread(ref.read_bytes)
        return self._static[name]

    async def page(self, request: web.Request) -> web.StreamResponse:
        if "token" in request.query:  # (no token needed here) keep it out of the address
            return _see_other("/")
        return web.Response(body=await self._file("index.html"), content_type="text/html",
                            charset="utf-8", headers=_PAGE_HEADERS)

    async def static(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in _STATIC or name == "index.html":
            raise NotFoundError(f"no static file {name!r}")
        return web.Response(body=await self._file(name), content_type=_STATIC[name],
                            charset="utf-8", headers=_PAGE_HEADERS)

    # --- episodes -------------------------------------------------------------------------
    async def episodes(self, request: web.Request) -> web.Response:
        raw = request.query.get("limit", str(EPISODES_DEFAULT))
        if not raw.isdigit() or not 1 <= int(raw) <= EPISODES_MAX:
            return web.json_response({"error": f"limit must be an integer 1..{EPISODES_MAX}, "
                                               f"got {raw[:20]!r}"}, status=400)
        listed = await asyncio.to_thread(self._list, int(raw))
        return web.json_response({"episodes": listed})

    def _list(self, limit: int) -> list[dict[str, Any]]:
        out = []
        for episode in self.recognitions.episodes(limit):
            eid = episode.id
            files = {name for name in ("image.jpg", "image.png", "press.press.npz")
                     if self._find(eid, name) is not None}
            out.append({
                "id": eid, "status": episode.status.value, "created": episode.created,
                "updated": episode.updated, "source": episode.source,
                "candidates": episode.candidates, "label": episode.label,
                "reason": episode.reason, "error": episode.why, "topk": episode.topk_json(),
                "description": episode.description, "familiarity": episode.familiarity,
                "unfamiliar": episode.unfamiliar, "presses": episode.presses,
                "fusion": episode.fusion, "timings": episode.timings,
                "vlm_mode": episode.vlm_mode, "press": episode.press_json(LISTED_PRESS),
                "image": f"/v1/episodes/{eid}/image" if files & {"image.jpg", "image.png"}
                else None,
                "trace": f"/v1/episodes/{eid}/trace" if "press.press.npz" in files else None,
            })
        return out

    async def image(self, request: web.Request) -> web.StreamResponse:
        eid = request.match_info["id"]
        for name, mime in (("image.jpg", "image/jpeg"), ("image.png", "image/png")):
            path = await asyncio.to_thread(self._find, eid, name)
            if path is not None:
                return web.FileResponse(path, headers={
                    "Content-Type": mime, "Cache-Control": "private, max-age=86400",
                    "X-Content-Type-Options": "nosniff"})
        raise NotFoundError(f"episode {eid} has no image")

    async def trace(self, request: web.Request) -> web.Response:
        eid = request.match_info["id"]
        trace = self._traces.get(eid)
        if trace is None:
            path = await asyncio.to_thread(self.recognitions.episode_file, eid,
                                           "press.press.npz")
            trace = await self.recognitions.run_cpu(press_trace, str(path))
            self._traces[eid] = trace
            while len(self._traces) > TRACE_CACHE:
                self._traces.popitem(last=False)
        return web.json_response({"episode": eid, **trace},
                                 headers={"Cache-Control": "private, max-age=86400"})

    # --- the live view --------------------------------------------------------------------
    async def tactile(self, request: web.Request) -> web.StreamResponse:
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                           "Cache-Control": "no-cache",
                                           "X-Accel-Buffering": "no"})
        await resp.prepare(request)
        frames = self.feed.frames()
        try:
            async for payload in frames:
                await resp.write(b"data: " + payload + b"\n\n")
        except ConnectionResetError:
            pass
        finally:
            await frames.aclose()
        return resp

    async def tare(self, request: web.Request) -> web.Response:
        return web.json_response({"tared": self.feed.tare()})

    def _find(self, episode_id: str, name: str) -> Path | None:
        try:
            return self.recognitions.episode_file(episode_id, name)
        except NotFoundError:
            return None


def _see_other(location: str) -> web.Response:
    return web.Response(status=303, headers={"Location": location})


def _https(request: web.Request) -> bool:
    return request.secure or request.headers.get("X-Forwarded-Proto", "") == "https"
