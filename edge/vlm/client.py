"""The VLM client (docs/method.md, 'The VLM answer'): ask an OpenAI-compatible server
for one label.

``OpenAIVLM.ask(image, description, candidates)`` renders the prompt, prepares the image off
the loop, POSTs ``{base_url}/chat/completions`` with the image as a base64 data URL,
``temperature: 0``, ``seed`` and the configured structured output (``vlm.structured_output``:
a strict ``json_schema`` whose enum is the candidates, ``json_object``, or ``none``), and
reads the answer with :func:`edge.vlm.answer.read_answer`: a candidate (or a case/spacing
variant of one) is ``ok``; anything else gets one corrective retry, then an explicit
``invalid_answer``. A label is never invented.

Transport failures (408, 409, 429, 5xx, connection errors, timeouts) are retried with capped
exponential backoff and jitter, honouring ``Retry-After``; other statuses are never retried.
When retries run out the error is a :class:`VLMUnavailableError`: the episode should wait in
the store and be asked again later; after :data:`UNREACHABLE_AFTER_ATTEMPTS` attempts in a row
without any HTTP answer the client reports the server as unreachable (``unreachable``).

A server that refuses the structured-output mode (400, 422, or an old llama.cpp's 500, whose
body names ``response_format`` or an equivalent) makes the client step down one mode at a
time, json_schema -> json_object -> none, log it once and keep the lower mode for the rest
of its life (a client made after SIGHUP starts again from the configured mode). So does a
server that ignores the mode: a 200 whose answer is not the requested JSON (prose) is asked
again one mode down, so free text is only ever read where the prompt asked for the label
alone. Every answer records the mode that answered. ``list_models()`` and ``probe()`` check
an endpoint before anything is pressed (``vt-edge doctor``). The API key is read from the
environment or a file, sent as a Bearer token, and never logged, stored or put in an
exception.

``NoVLM`` stands in when no VLM is configured: it answers ``not_configured`` with the exact
prompt that would have been sent.
"""

from __future__ import annotations

import asyncio
import dataclasses
import email.utils
import io
import json
import logging
import math
import os
import random
import re
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from datetime import UTC
from functools import cache
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable
from urllib.parse import urlsplit

import aiohttp

from edge.core.backoff import Backoff
from edge.core.config import VLMConfig
from edge.core.errors import (
    ConfigError,
    ImageError,
    VLMConnectionError,
    VLMError,
    VLMFormatRefusedError,
    VLMHTTPError,
    VLMRejectedError,
    VLMResponseError,
    VLMResponseTooLargeError,
    VLMServerError,
    VLMTimeoutError,
    VLMUnavailableError,
)
from edge.vlm.answer import ask_for, correction_message, read_answer
from edge.vlm.images import PreparedImage, VLMImage, prepare_for_vlm
from edge.vlm.prompt import PromptMode, PromptTemplate, check_candidates, load_template

log = logging.getLogger(__name__)

# Statuses worth another try: the server was busy, timed out, or conflicted.
RETRYABLE_STATUSES = frozenset({408, 409, 429, *range(500, 600)})
# The most of an error body quoted in an exception or a log line.
EXCERPT_CHARS = 200
# The most of a bad answer echoed back in the corrective retry.
MAX_ECHO_CHARS = 2_000
SCHEMA_NAME = "label"
# Structured-output modes, strictest first: a server that refuses one is sent the next.
STRUCTURED_MODES = ("json_schema", "json_object", "none")
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
# The probe's question: two made-up candidates and, where the prompt needs one, a tiny photo.
PROBE_CANDIDATES = ("red_cube", "blue_ball")
PROBE_DESCRIPTION = "wood cube"
PROBE_IMAGE_SIDE_PX = 64
# Each transport retry waits half to all of the backoff (edge.core.backoff).
BACKOFF_SPREAD = (0.5, 1.0)

Status = Literal["ok", "invalid_answer", "not_configured"]


# --- the answer --------------------------------------------------------------------------

@dataclass(frozen=True)
class VLMAnswer:
    """One recognition question and its answer, everything needed to store and audit it."""

    status: Status
    label: str | None
    # The text content of the last answer ("" when none came).
    raw: str
    # The rendered template (the mode's answer line, edge.vlm.answer.ask_for, is in
    # ``request``).
    prompt: str
    candidates: tuple[str, ...]
    model: str
    # The last request body sent (the whole conversation), image data elided.
    request: dict[str, Any] | None
    # The last response body (JSON).
    response: dict[str, Any] | None
    # PreparedImage.info() of the image sent: mime, bytes, sha256, sizes; None if none.
    image: dict[str, Any] | None
    # HTTP attempts, transport retries and the corrective retry included.
    attempts: int
    latency_s: tuple[float, ...]
    # Per attempt: the HTTP status ("200", "503") or "timeout", "connection", "too_large".
    outcomes: tuple[str, ...]
    # From ask() to the answer, image preparation and backoff waits included.
    elapsed_s: float
    # The structured-output mode of the request that answered (None: no request).
    structured_output: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class VLMProbe:
    """What :meth:`OpenAIVLM.probe` found: the mode that answered, how fast, the label it
    gave (None: no candidate, as a recognition would end ``invalid_answer``) and its last
    answer, and the modes the server refused or ignored on the way (``reasons``: "refused
    (the server's words)" or "ignored (what it answered)")."""

    structured_output: str
    latency_s: float
    label: str | None
    fallbacks: tuple[str, ...]
    reasons: tuple[str, ...] = ()
    raw: str = ""


@runtime_checkable
class VLMClient(Protocol):
    """What the runtime needs from a VLM."""

    async def ask(self, image: bytes | VLMImage | None, description: str,
                  candidates: Sequence[str]) -> VLMAnswer:
        """``image`` as taken, or already prepared within :meth:`image_limits`."""
        ...

    @property
    def mode(self) -> str:
        """The prompt mode (vision_tactile, vision_only, tactile_only)."""
        ...

    def image_limits(self) -> tuple[int, int] | None:
        """(longest side in px, bytes) an image is prepared to before it is sent, or None
        when no image is sent."""
        ...

    @property
    def unreachable(self) -> str | None:
        """Why the server counts as unreachable now (``/healthz``, ``/metrics``), else None
        (always None without a server)."""
        ...

    async def close(self) -> None: ...


# --- request pieces ----------------------------------------------------------------------

def request_head(model: str, seed: int, mode: str, candidates: Sequence[str]
                 ) -> dict[str, Any]:
    """The request's settings: deterministic sampling and the ``mode``'s response format
    (none for ``"none"``)."""
    head: dict[str, Any] = {"model": model, "temperature": 0, "seed": seed, "stream": False}
    if mode == "json_schema":
        head["response_format"] = response_format(candidates)
    elif mode == "json_object":
        head["response_format"] = {"type": "json_object"}
    return head


def response_format(candidates: Sequence[str]) -> dict[str, Any]:
    """The strict ``json_schema`` response format: one ``label`` from the candidates."""
    return {
        "type": "json_schema",
        "json_schema": {
            "name": SCHEMA_NAME,
            "strict": True,
            "schema": {
                "type": "object",
                "properties": {"label": {"type": "string", "enum": list(candidates)}},
                "required": ["label"],
                "additionalProperties": False,
            },
        },
    }


def _user_message(prompt: str, image_url: str | None) -> dict[str, Any]:
    if image_url is None:
        return {"role": "user", "content": prompt}
    return {"role": "user", "content": [
        {"type": "text", "text": prompt},
        {"type": "image_url", "image_url": {"url": image_url}},
    ]}


def _elided(image: PreparedImage) -> str:
    return f"<elided {image.mime} image, {len(image.data)} bytes, sha256:{image.sha256}>"


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


class _Trace:
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


# --- the real client ---------------------------------------------------------------------

class OpenAIVLM:
    """:class:`VLMClient` for an OpenAI-compatible ``/chat/completions`` endpoint (aiohttp).

    ``sleep`` and ``rng`` are injectable (tests record or scale the backoff). A ``session``
    passed in is used and left open; otherwise one is created on first use and closed by
    :meth:`close` (or ``async with``).
    """

    def __init__(
        self,
        config: VLMConfig,
        *,
        template: PromptTemplate | None = None,
        session: aiohttp.ClientSession | None = None,
        sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
        rng: random.Random | None = None,
        offload: Callable[..., Awaitable[Any]] = asyncio.to_thread,
    ) -> None:
        config.validate("vlm")
        if not config.configured:
            raise ConfigError("vlm.base_url = '': no VLM configured (use NoVLM)")
        self.config = config
        self.template = template or load_template(config.mode, config.prompt_dir)
        self.url = config.base_url.rstrip("/") + "/chat/completions"
        self._api_key = load_api_key(config)
        self._session = session
        self._own_session = session is None
        self._sleep = sleep
        self._rng = rng or random.Random()
        # Where the image is prepared: a worker thread, or the daemon's compute process.
        self._offload = offload
        # The structured-output mode sent now: the configured one until a server refuses it.
        self._structured: str = config.structured_output
        # Attempts in a row that got no HTTP answer, and the last one's error.
        self._unanswered = 0
        self._unanswered_why = ""
        host = urlsplit(self.url).hostname or ""
        if self._api_key and self.url.startswith("http://") and not is_loopback(host):
            log.warning("the VLM API key will cross the network in clear text to %s: "
                        "use https://", host)

    def __repr__(self) -> str:
        return (f"OpenAIVLM(url={self.url!r}, model={self.config.model!r}, "
                f"mode={self.template.mode!r}, api_key={'set' if self._api_key else 'none'})")

    async def __aenter__(self) -> OpenAIVLM:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        if self._own_session and self._session is not None:
            await self._session.close()
            self._session = None

    @property
    def mode(self) -> str:
        return self.template.mode

    def image_limits(self) -> tuple[int, int] | None:
        if not self.template.uses_image:
            return None
        return self.config.max_image_side_px, self.config.max_image_bytes

    @property
    def structured_output(self) -> str:
        """The structured-output mode the next question is sent with."""
        return self._structured

    @property
    def unreachable(self) -> str | None:
        """Why the server counts as unreachable (no HTTP answer to the last
        :data:`UNREACHABLE_AFTER_ATTEMPTS` attempts), else None."""
        if self._unanswered < UNREACHABLE_AFTER_ATTEMPTS:
            return None
        return (f"VLM at {self.config.base_url} unreachable: {self._unanswered} attempts in a "
                f"row without an answer, the last: {self._unanswered_why}")

    async def list_models(self) -> list[str] | None:
        """The model ids ``GET {base_url}/models`` lists; None where the server does not
        serve that route (404, 405). Raises the :class:`VLMError` of :meth:`ask`."""
        url = self.config.base_url.rstrip("/") + "/models"
        trace = _Trace()
        status, body = await self._send("GET", url, None, trace, 0)
        if status in (404, 405):
            return None
        if not 200 <= status < 300:
            raise self._http_error(status, body, url=url)
        data = self._decode(body, status).get("data")
        if not isinstance(data, list):
            raise VLMResponseError(f"GET {url} answered without a 'data' list: "
                                   f"{self._excerpt(body)!r}")
        return [m["id"] for m in data if isinstance(m, dict) and isinstance(m.get("id"), str)]

    async def probe(self) -> VLMProbe:
        """One tiny question (two made-up candidates, a 64 px photo only when the prompt
        mode sends one) with this client's structured-output mode and its fallback, no
        transport retry. Raises :class:`VLMError`: unreachable, a refused key (401/403), an
        unknown model (404), ..."""
        image = _probe_image() if self.template.uses_image else None
        answer, trace = await self._ask(image, PROBE_DESCRIPTION, PROBE_CANDIDATES, 0)
        return VLMProbe(structured_output=answer.structured_output or self._structured,
                        latency_s=answer.elapsed_s, label=answer.label,
                        fallbacks=tuple(trace.stepped_down), reasons=tuple(trace.reasons),
                        raw=answer.raw)

    async def ask(self, image: bytes | VLMImage | None, description: str,
                  candidates: Sequence[str]) -> VLMAnswer:
        answer, _ = await self._ask(image, description, candidates, self.config.max_retries)
        return answer

    async def _ask(self, image: bytes | VLMImage | None, description: str,
                   candidates: Sequence[str], max_retries: int) -> tuple[VLMAnswer, _Trace]:
        started = time.monotonic()
        labels = check_candidates(candidates)
        rendered = self.template.render(description, labels)
        prepared: PreparedImage | None = None
        stored_url = None
        splice: tuple[str, bytes] | None = None
        if self.template.uses_image:
            if image is None:
                raise ImageError(f"VLM mode {self.template.mode} needs an image; none given")
            if isinstance(image, tuple):  # prepared by the caller within image_limits()
                prepared, data_url = image
            else:
                cfg = self.config
                prepared, data_url = await self._offload(
                    prepare_for_vlm, image, cfg.max_image_side_px, cfg.max_image_bytes)
            # The stored request names the image; the one sent has its data URL there.
            stored_url = _elided(prepared)
            splice = (stored_url, data_url)
        elif image is not None:
            log.debug("VLM mode %s: image not sent", self.template.mode)

        trace = _Trace()
        while True:
            mode = self._structured
            head = request_head(self.config.model, self.config.seed, mode, labels)
            prompt = ask_for(rendered, mode)
            # Both name the image; _encode_json puts the data URL in what goes on the wire.
            wire = [_user_message(prompt, stored_url)]
            stored = [_user_message(prompt, stored_url)]
            try:
                response, raw = await self._complete({**head, "messages": wire}, trace,
                                                     splice, max_retries, mode != "none")
            except VLMFormatRefusedError as exc:
                self._step_down(mode, trace, "refused", f"HTTP {exc.status}: {exc.excerpt}")
                continue
            reading = read_answer(raw, labels, mode)
            if reading.honoured:
                break
            # A 200 that is not the requested JSON: the server took the mode and ignored it.
            self._step_down(mode, trace, "ignored",
                            f"answered {self._excerpt(raw.encode())!r}, not JSON")
        label = reading.label
        if label is None:
            log.warning("VLM answer %r is not a candidate; asking once more",
                        self._redact(raw[:EXCERPT_CHARS]))
            correction = {"role": "user", "content": correction_message(labels, mode)}
            echo = raw[:MAX_ECHO_CHARS] or "(no answer)"
            wire += [{"role": "assistant", "content": echo}, correction]
            stored += [{"role": "assistant", "content": self._redact(echo)}, correction]
            response, raw = await self._complete({**head, "messages": wire}, trace, splice,
                                                 max_retries, False)
            label = read_answer(raw, labels, mode).label
        status: Status = "ok" if label is not None else "invalid_answer"
        elapsed = time.monotonic() - started
        if label is None:
            log.warning("VLM gave no valid label after a corrective retry: %r",
                        self._redact(raw[:EXCERPT_CHARS]))
        else:
            log.info("VLM answered %r in %.2f s (%d attempt(s), %s)", label, elapsed,
                     len(trace.outcomes), mode)
        return VLMAnswer(
            status=status, label=label, raw=self._redact(raw), prompt=rendered,
            candidates=tuple(labels), model=self.config.model,
            request={**head, "messages": stored}, response=self._redact_json(response),
            image=prepared.info() if prepared else None, attempts=len(trace.outcomes),
            latency_s=tuple(trace.latency_s), outcomes=tuple(trace.outcomes),
            elapsed_s=elapsed, structured_output=mode,
        ), trace

    def _step_down(self, mode: str, trace: _Trace, verb: str, why: str) -> None:
        """The next mode after the server ``verb`` ("refused" or "ignored") ``mode``, for
        this client's life; logged once (questions in flight together may each meet it)."""
        trace.stepped_down.append(mode)
        trace.reasons.append(f"{verb} ({why})")
        lower = STRUCTURED_MODES[STRUCTURED_MODES.index(mode) + 1]
        if self._structured == mode:
            self._structured = lower
            log.warning("VLM at %s %s structured output %s (%s); asking with %s from now on "
                        "(set vlm.structured_output = %r to start there)", self.url, verb,
                        mode, why, lower, lower)

    # -- one round: POST with transport retries, then the answer text --

    async def _complete(self, body: dict[str, Any], trace: _Trace,
                        splice: tuple[str, bytes] | None, max_retries: int,
                        structured: bool) -> tuple[dict, str]:
        payload = _encode_json(body, splice)
        status, raw = await self._send("POST", self.url, payload, trace, max_retries,
                                       structured)
        if not 200 <= status < 300:
            raise self._http_error(status, raw, structured)
        data = self._decode(raw, status)
        return data, self._content(data)

    async def _send(self, method: str, url: str, payload: bytes | None, trace: _Trace,
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
                    f"{self._redact(str(exc))[:EXCERPT_CHARS]}")
                self._unanswered_attempt(failure)
            except aiohttp.ClientError as exc:
                trace.add(started, "protocol")
                raise VLMResponseError(
                    f"unusable HTTP answer from {url}: {type(exc).__name__}: "
                    f"{self._redact(str(exc))[:EXCERPT_CHARS]}") from None
            else:
                trace.add(started, str(status))
                if (status not in RETRYABLE_STATUSES
                        or (structured and _refuses_format(status, body))):
                    return status, body
                failure = self._http_error(status, body, url=url)
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

    def _decode(self, body: bytes, status: int) -> dict[str, Any]:
        try:
            data = json.loads(body)
        except (ValueError, RecursionError):
            raise VLMResponseError(
                f"VLM answered HTTP {status} with a body that is not JSON: "
                f"{self._excerpt(body)!r}") from None
        if not isinstance(data, dict):
            raise VLMResponseError(f"VLM answered HTTP {status} with JSON that is not an "
                                   f"object: {self._excerpt(body)!r}")
        return data

    def _content(self, data: dict[str, Any]) -> str:
        choices = data.get("choices")
        if not isinstance(choices, list) or not choices or not isinstance(choices[0], dict):
            raise VLMResponseError(
                f"VLM answer has no choices: {self._excerpt(json.dumps(data).encode())!r}")
        message = choices[0].get("message")
        if not isinstance(message, dict):
            return ""
        content = message.get("content")
        if isinstance(content, list):  # some servers answer with content parts
            content = "".join(p.get("text", "") for p in content
                              if isinstance(p, dict) and isinstance(p.get("text"), str))
        if not isinstance(content, str) or not content:
            refusal = message.get("refusal")
            content = refusal if isinstance(refusal, str) else ""
        return content

    def _http_error(self, status: int, body: bytes, structured: bool = False,
                    url: str | None = None) -> VLMError:
        url = url or self.url
        excerpt = self._excerpt(body)
        if structured and _refuses_format(status, body):
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

    def _excerpt(self, body: bytes) -> str:
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
        text = " ".join(self._redact(text).split())
        text = "".join(ch if ch.isprintable() else "?" for ch in text)
        return text[:EXCERPT_CHARS] + ("..." if len(text) > EXCERPT_CHARS else "")

    def _redact(self, text: str) -> str:
        if self._api_key and self._api_key in text:
            text = text.replace(self._api_key, "<redacted>")
        return text

    def _redact_json(self, data: dict[str, Any]) -> dict[str, Any]:
        if not self._api_key:
            return data
        dumped = json.dumps(data, ensure_ascii=False)
        if self._api_key not in dumped:
            return data
        return json.loads(self._redact(dumped))


def _encode_json(body: dict[str, Any], splice: tuple[str, bytes] | None = None) -> bytes:
    """The request body, with ``splice``'s data URL put where its placeholder stands.

    Megabytes of base64 never pass through ``json.dumps``: base64 and the ``data:`` prefix
    need no JSON escaping, and joining bytes is one copy, cheap enough for the event loop
    (for a 1.33 MB data URL here: json.dumps 4.7 ms holding the GIL, the splice 0.05 ms,
    up to 1.2 ms when its memory is freshly mapped).
    """
    payload = json.dumps(body, ensure_ascii=False).encode("utf-8")
    if splice is None:
        return payload
    placeholder, data_url = splice
    head, found, tail = payload.partition(placeholder.encode("utf-8"))
    if not found:
        raise AssertionError("the image placeholder is missing from the request body")
    return b"".join((head, data_url, tail))


def _refuses_format(status: int, body: bytes) -> bool:
    """Whether an error answer refuses the structured-output mode (response_format)."""
    return (status in FORMAT_REFUSAL_STATUSES
            and _FORMAT_REFUSAL.search(body[:4096].decode("utf-8", "replace")) is not None)


@cache
def _probe_image() -> bytes:
    """A small grey JPEG: enough for a server to accept an image, cheap to send."""
    from PIL import Image

    out = io.BytesIO()
    Image.new("RGB", (PROBE_IMAGE_SIDE_PX, PROBE_IMAGE_SIDE_PX), (128, 128, 128)).save(
        out, "JPEG", quality=80)
    return out.getvalue()


def is_loopback(host: str) -> bool:
    """Whether ``host`` names this machine (a key sent there over plain HTTP stays here)."""
    return host in ("localhost", "::1") or host.startswith("127.")


# --- no VLM ------------------------------------------------------------------------------

class NoVLM:
    """:class:`VLMClient` when no VLM is configured: the prompt it would send, no label."""

    def __init__(self, template: PromptTemplate | None = None, *,
                 mode: PromptMode = "vision_tactile", prompt_dir: Path | None = None) -> None:
        self.template = template or load_template(mode, prompt_dir)

    def __repr__(self) -> str:
        return f"NoVLM(mode={self.template.mode!r})"

    @property
    def mode(self) -> str:
        return self.template.mode

    def image_limits(self) -> tuple[int, int] | None:
        return None

    @property
    def unreachable(self) -> str | None:
        return None  # no server to reach

    async def ask(self, image: bytes | VLMImage | None, description: str,
                  candidates: Sequence[str]) -> VLMAnswer:
        labels = check_candidates(candidates)
        prompt = self.template.render(description, labels)
        return VLMAnswer(
            status="not_configured", label=None, raw="", prompt=prompt,
            candidates=tuple(labels), model="", request=None, response=None, image=None,
            attempts=0, latency_s=(), outcomes=(), elapsed_s=0.0,
        )

    async def close(self) -> None:
        return None


def make_vlm(config: VLMConfig, **kwargs: Any) -> VLMClient:
    """``OpenAIVLM`` when ``config.base_url`` is set, else ``NoVLM`` (same prompt mode)."""
    if config.configured:
        return OpenAIVLM(config, **kwargs)
    return NoVLM(kwargs.get("template"), mode=config.mode, prompt_dir=config.prompt_dir)


__all__ = [
    "STRUCTURED_MODES", "NoVLM", "OpenAIVLM", "VLMAnswer", "VLMClient", "VLMConfig",
    "VLMConnectionError", "VLMFormatRefusedError", "VLMHTTPError", "VLMProbe",
    "VLMRejectedError", "VLMResponseError",
    "VLMResponseTooLargeError", "VLMServerError", "VLMTimeoutError", "VLMUnavailableError",
    "make_vlm", "parse_retry_after", "request_head", "response_format",
]
