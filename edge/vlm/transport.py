"""The VLM client's HTTP transport: one request to the server, retried with capped
exponential backoff and jitter where another try is worth it (408, 409, 429, 5xx, no answer
at all), honouring ``Retry-After``, never for a refusal of the structured-output mode; the
answer read within ``vlm.max_response_bytes``; an error that names the status and what to
do; how long the server has gone without answering. The API key is read from the
environment or a file, sent as a Bearer token, and never logged, stored or put in an
exception.
"""

from __future__ import annotations

import email.utils
import json
import logging
import math
import os
import random
import re
import time
from collections.abc import Awaitable, Callable
from datetime import UTC
from typing import Any
from urllib.parse import urlsplit

import aiohttp

from edge.core.backoff import Backoff
from edge.core.config import VLMConfig
from edge.core.errors import (
    ConfigError,
    VLMConnectionError,
    VLMError,
    VLMFormatRefusedError,
    VLMRejectedError,
    VLMResponseError,
    VLMResponseTooLargeError,
    VLMServerError,
    VLMTimeoutError,
)

log = logging.getLogger(__name__)

# Statuses worth another try: the server was busy, timed out, or conflicted.
RETRYABLE_STATUSES = frozenset({408, 409, 429, *range(500, 600)})
# The most of an error body quoted in an exception or a log line.
EXCERPT_CHARS = 200
# A refusal of the mode: these statuses (old llama.cpp builds answer 500) with a body naming
# response_format or what real servers say instead: vLLM ("loc": ("body", "response_format")),
# TGI (422 "response_format: unknown variant `json_schema`"), llama.cpp ("response_format type
# must be one of ..."), LM Studio ("'response_format.type' must be 'json_schema'"), Ollama
# ("invalid JSON schema in format", a 500), hosted APIs ("json mode is not supported",
# "structured outputs", "guided_json", "grammar").
FORMAT_REFUSAL_STATUSES = frozenset({400, 422, 500})
_FORMAT_REFUSAL = re.compile(
    r"response[_ .-]?format|json[_ ]?schema|json[_ ]?object|structured[_ ]outputs?|"
    r"guided[_ ](?:json|decoding)|grammar|json mode", re.I)
# Attempts in a row that got no HTTP answer at all (refused, DNS, timeout) after which the
# server counts as unreachable: one question's worth with the default vlm.max_retries = 3.
UNREACHABLE_AFTER_ATTEMPTS = 4
# Each transport retry waits half to all of the backoff (edge.core.backoff).
BACKOFF_SPREAD = (0.5, 1.0)


def parse_retry_after(value: str | None, now: float | None = None) -> float | None:
    """Seconds to wait from a ``Retry-After`` value (delta seconds or an HTTP date)."""
    if not value:
        return None
    value = value.strip()
    try:
        seconds = float(value)
    except ValueError:
        try:
            when = email.utils.parsedate_to_datetime(value)
        except (TypeError, ValueError, IndexError, OverflowError):
            return None
        if when.tzinfo is None:
            when = when.replace(tzinfo=UTC)
        seconds = when.timestamp() - (time.time() if now is None else now)
    if not math.isfinite(seconds):
        return None
    return max(0.0, seconds)


def load_api_key(config: VLMConfig) -> str | None:
    """The API key from ``api_key_file`` if set, else ``api_key_env``; None if neither."""
    if config.api_key_file is not None:
        path = config.api_key_file
        try:
            mode = path.stat().st_mode
            key = path.read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"vlm.api_key_file = {str(path)!r}: cannot be read "
                              f"({type(exc).__name__})") from None
        if mode & 0o077:
            log.warning("vlm.api_key_file %s is readable by group or others (mode %o): "
                        "chmod 600 it", path, mode & 0o777)
        source = f"vlm.api_key_file = {str(path)!r}"
        if not key:
            raise ConfigError(f"{source}: the file is empty")
    elif config.api_key_env and os.environ.get(config.api_key_env, "").strip():
        key = os.environ[config.api_key_env].strip()
        source = f"environment variable {config.api_key_env}"
    else:
        return None
    if not key.isascii() or not key.isprintable() or " " in key:
        raise ConfigError(f"{source}: the API key holds characters not allowed in a header")
    return key


class Trace:
    """Per-attempt bookkeeping of one ask()."""

    def __init__(self) -> None:
        self.latency_s: list[float] = []
        self.outcomes: list[str] = []
        # Structured-output modes the server refused or ignored, and why for each.
        self.stepped_down: list[str] = []
        self.reasons: list[str] = []

    def add(self, started: float, outcome: str) -> None:
        self.latency_s.append(time.monotonic() - started)
        self.outcomes.append(outcome)


class Transport:
    """Requests to one VLM server with one API key: ``send`` with its retries, the
    errors it raises, excerpts of what the server said with the key redacted.

    ``sleep`` and ``rng`` are injectable (tests record or scale the backoff). A ``session``
    passed in is used and left open; otherwise one is created on first use and closed by
    :meth:`close`.
    """

    def __init__(self, config: VLMConfig, *, session: aiohttp.ClientSession | None = None,
                 sleep: Callable[[float], Awaitable[None]],
                 rng: random.Random | None = None) -> None:
        self.config = config
        self._api_key = load_api_key(config)
        self._session = session
        self._own_session = session is None
        self._sleep = sleep
        self._rng = rng or random.Random()
        # Attempts in a row that got no HTTP answer, and the last one's error.
        self._unanswered = 0
        self._unanswered_why = ""
        host = urlsplit(config.base_url).hostname or ""
        if self._api_key and config.base_url.startswith("http://") and not is_loopback(host):
            log.warning("the VLM API key will cross the network in clear text to %s: "
                        "use https://", host)

    @property
    def has_api_key(self) -> bool:
        return bool(self._api_key)

    async def close(self) -> None:
        if self._own_session and self._session is not None:
            await self._session.close()
            self._session = None

    @property
    def unreachable(self) -> str | None:
        """Why the server counts as unreachable (no HTTP answer to the last
        :data:`UNREACHABLE_AFTER_ATTEMPTS` attempts), else None."""
        if self._unanswered < UNREACHABLE_AFTER_ATTEMPTS:
            return None
        return (f"VLM at {self.config.base_url} unreachable: {self._unanswered} attempts in a "
                f"row without an answer, the last: {self._unanswered_why}")

    async def send(self, method: str, url: str, payload: bytes | None, trace: Trace,
                   max_retries: int, structured: bool = False) -> tuple[int, bytes]:
        """The (status, body) of the last attempt, retrying what is worth it (not a
        refusal of the structured-output mode); :class:`VLMError` when no answer came or
        the server stayed busy."""
        cfg = self.config
        timeout = aiohttp.ClientTimeout(total=cfg.total_timeout_s,
                                        connect=cfg.connect_timeout_s,
                                        sock_connect=cfg.connect_timeout_s)
        headers = {"Accept": "application/json"}
        if payload is not None:
            headers["Content-Type"] = "application/json"
        if self._api_key:
            headers["Authorization"] = f"Bearer {self._api_key}"
        session = self._get_session()
        backoff = Backoff(cfg.backoff_base_s, cfg.backoff_cap_s, BACKOFF_SPREAD, self._rng)
        while True:
            started = time.monotonic()
            wait_s: float | None = None
            try:
                async with session.request(method, url, data=payload, headers=headers,
                                           timeout=timeout, allow_redirects=False) as resp:
                    self._answered()
                    status = resp.status
                    wait_s = parse_retry_after(resp.headers.get("Retry-After"))
                    body = await self._read_body(resp)
            except VLMResponseTooLargeError:
                trace.add(started, "too_large")
                raise
            except TimeoutError:
                trace.add(started, "timeout")
                failure: VLMError = VLMTimeoutError(
                    f"no complete answer from {url} within total_timeout_s="
                    f"{cfg.total_timeout_s} (connect_timeout_s={cfg.connect_timeout_s})")
                self._unanswered_attempt(failure)
            except (aiohttp.ClientConnectionError, aiohttp.ClientPayloadError) as exc:
                trace.add(started, "connection")
                failure = VLMConnectionError(
                    f"connection to {url} failed: {type(exc).__name__}: "
                    f"{self.redact(str(exc))[:EXCERPT_CHARS]}")
                self._unanswered_attempt(failure)
            except aiohttp.ClientError as exc:
                trace.add(started, "protocol")
                raise VLMResponseError(
                    f"unusable HTTP answer from {url}: {type(exc).__name__}: "
                    f"{self.redact(str(exc))[:EXCERPT_CHARS]}") from None
            else:
                trace.add(started, str(status))
                if (status not in RETRYABLE_STATUSES
                        or (structured and refuses_format(status, body))):
                    return status, body
                failure = self.http_error(status, body, url)
            attempts = len(trace.outcomes)
            if backoff.failures >= max_retries:
                log.warning("VLM unavailable after %d attempt(s): %s", attempts, failure)
                raise failure
            delay = backoff.next_s()
            if wait_s is not None:
                delay = max(delay, min(wait_s, cfg.retry_after_cap_s))
            log.warning("VLM attempt %d failed (%s); retrying in %.2f s", attempts,
                        trace.outcomes[-1], delay)
            await self._sleep(delay)

    def _answered(self) -> None:
        if self._unanswered >= UNREACHABLE_AFTER_ATTEMPTS:
            log.info("VLM at %s answers again", self.config.base_url)
        self._unanswered = 0

    def _unanswered_attempt(self, failure: VLMError) -> None:
        self._unanswered += 1
        self._unanswered_why = str(failure)
        if self._unanswered == UNREACHABLE_AFTER_ATTEMPTS:
            log.error("%s", self.unreachable)

    def _get_session(self) -> aiohttp.ClientSession:
        if self._session is None or self._session.closed:
            self._session = aiohttp.ClientSession(
                connector=aiohttp.TCPConnector(limit=4), trust_env=False)
            self._own_session = True
        return self._session

    async def _read_body(self, resp: aiohttp.ClientResponse) -> bytes:
        limit = self.config.max_response_bytes
        declared = resp.content_length
        if declared is not None and declared > limit:
            raise VLMResponseTooLargeError(
                f"VLM response of {declared} bytes refused: more than max_response_bytes="
                f"{limit}")
        chunks: list[bytes] = []
        size = 0
        async for chunk in resp.content.iter_chunked(64 * 1024):
            size += len(chunk)
            if size > limit:
                raise VLMResponseTooLargeError(
                    f"VLM response refused after {size} bytes: more than "
                    f"max_response_bytes={limit}")
            chunks.append(chunk)
        return b"".join(chunks)

    def decode(self, body: bytes, status: int) -> dict[str, Any]:
        try:
            data = json.loads(body)
        except (ValueError, RecursionError):
            raise VLMResponseError(
                f"VLM answered HTTP {status} with a body that is not JSON: "
                f"{self.excerpt(body)!r}") from None
        if not isinstance(data, dict):
            raise VLMResponseError(f"VLM answered HTTP {status} with JSON that is not an "
                                   f"object: {self.excerpt(body)!r}")
        return data

    def http_error(self, status: int, body: bytes, url: str, structured: bool = False
                   ) -> VLMError:
        excerpt = self.excerpt(body)
        if structured and refuses_format(status, body):
            return VLMFormatRefusedError(
                f"VLM at {url} refused the structured-output mode (HTTP {status}): {excerpt}",
                status, excerpt)
        if status in RETRYABLE_STATUSES:
            return VLMServerError(f"VLM at {url} answered HTTP {status}: {excerpt}",
                                  status, excerpt)
        hint = {
            400: "the request was refused as malformed",
            401: "check the API key (vlm.api_key_env / vlm.api_key_file)",
            403: "the API key is not allowed to use this model or endpoint",
            404: f"check vlm.base_url and that vlm.model = {self.config.model!r} is served",
            413: "the request is too large: lower vlm.max_image_bytes / max_image_side_px",
        }.get(status, "not retried")
        if 300 <= status < 400:
            hint = "redirect not followed: set vlm.base_url to the final address"
        return VLMRejectedError(
            f"VLM at {url} answered HTTP {status} ({hint}): {excerpt}", status, excerpt)

    def excerpt(self, body: bytes) -> str:
        """A short, secret-free, single-line excerpt of a response body."""
        text = body[:4096].decode("utf-8", "replace")
        try:
            data = json.loads(body)
            err = data.get("error")
            if isinstance(err, dict) and isinstance(err.get("message"), str):
                text = err["message"]
            elif isinstance(err, str):
                text = err
            elif isinstance(data.get("message"), str):  # vLLM: {"object": "error", ...}
                text = data["message"]
        except (ValueError, RecursionError, AttributeError):
            pass
        text = " ".join(self.redact(text).split())
        text = "".join(ch if ch.isprintable() else "?" for ch in text)
        return text[:EXCERPT_CHARS] + ("..." if len(text) > EXCERPT_CHARS else "")

    def redact(self, text: str) -> str:
        if self._api_key and self._api_key in text:
            text = text.replace(self._api_key, "<redacted>")
        return text

    def redact_json(self, data: dict[str, Any]) -> dict[str, Any]:
        if not self._api_key:
            return data
        dumped = json.dumps(data, ensure_ascii=False)
        if self._api_key not in dumped:
            return data
        return json.loads(self.redact(dumped))


def refuses_format(status: int, body: bytes) -> bool:
    """Whether an error answer refuses the structured-output mode (response_format)."""
    return (status in FORMAT_REFUSAL_STATUSES
            and _FORMAT_REFUSAL.search(body[:4096].decode("utf-8", "replace")) is not None)


def is_loopback(host: str) -> bool:
    """Whether ``host`` names this machine (a key sent there over plain HTTP stays here)."""
    return host in ("localhost", "::1") or host.startswith("127.")

