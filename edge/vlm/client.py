"""The VLM client (docs/method.md, 'The VLM answer'): ask an OpenAI-compatible server
for one label.

``OpenAIVLM.ask(image, description, candidates)`` renders the prompt, prepares the image off
the loop, POSTs ``{base_url}/chat/completions`` (:mod:`edge.vlm.chat`) with the image as a
base64 data URL, ``temperature: 0``, ``seed`` and the configured structured output
(``vlm.structured_output``: a strict ``json_schema`` whose enum is the candidates,
``json_object``, or ``none``), and reads the answer with :func:`edge.vlm.answer.read_answer`:
a candidate (or a case/spacing variant of one) is ``ok``; anything else gets one corrective
retry, then an explicit ``invalid_answer``. A label is never invented. With
``vlm.ask_reason`` the schema and the prompt's answer line ask for a short ``reason`` before
the ``label`` and the answer carries it (``VLMAnswer.reason``); without it the request is
the label-only one, byte for byte.

Transport failures (408, 409, 429, 5xx, connection errors, timeouts) are retried with capped
exponential backoff and jitter, honouring ``Retry-After`` (:mod:`edge.vlm.transport`); other
statuses are never retried. When retries run out the error is a :class:`VLMUnavailableError`:
the episode should wait in the store and be asked again later; after
:data:`~edge.vlm.transport.UNREACHABLE_AFTER_ATTEMPTS` attempts in a row without any HTTP
answer the client reports the server as unreachable (``unreachable``).

A server that refuses the structured-output mode (400, 422, or an old llama.cpp's 500, whose
body names ``response_format`` or an equivalent) makes the client step down one mode at a
time (:mod:`edge.vlm.structured`), json_schema -> json_object -> none, log it once and keep
the lower mode for the rest of its life (a client made after SIGHUP starts again from the
configured mode). So does a server that ignores the mode: a 200 whose answer is not the
requested JSON (prose) is asked again one mode down, so free text is only ever read where
the prompt asked for the label alone. Every answer records the mode that answered.
``list_models()`` and ``probe()`` check an endpoint before anything is pressed (``vt-edge
doctor``). The API key is read from the environment or a file, sent as a Bearer token, and
never logged, stored or put in an exception.

``NoVLM`` stands in when no VLM is configured: it answers ``not_configured`` with the exact
prompt that would have been sent.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import random
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import aiohttp

from edge.core.config import VLMConfig
from edge.core.errors import ConfigError, ImageError, VLMFormatRefusedError, VLMResponseError
from edge.vlm.answer import ask_for, correction_message, read_answer
from edge.vlm.chat import elided, encode_json, request_head, user_message
from edge.vlm.images import PreparedImage, VLMImage, prepare_for_vlm
from edge.vlm.prompt import PromptMode, PromptTemplate, check_candidates, load_template
from edge.vlm.structured import PROBE_CANDIDATES, PROBE_DESCRIPTION, StructuredOutput, probe_image
from edge.vlm.transport import EXCERPT_CHARS, Trace, Transport

log = logging.getLogger(__name__)

# The most of a bad answer echoed back in the corrective retry.
MAX_ECHO_CHARS = 2_000

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
    # The VLM's short reason for its label, as read (edge.vlm.answer.read_answer): None when
    # vlm.ask_reason is off, or none usable came. What episodes, the page and MQTT show.
    reason: str | None = None

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
        self._http = Transport(config, session=session, sleep=sleep, rng=rng)
        # Where the image is prepared: a worker thread, or the daemon's compute process.
        self._offload = offload
        # The structured-output mode sent now: the configured one until a server refuses it.
        self._structured = StructuredOutput(config.structured_output, self.url)

    def __repr__(self) -> str:
        key = "set" if self._http.has_api_key else "none"
        return (f"OpenAIVLM(url={self.url!r}, model={self.config.model!r}, "
                f"mode={self.template.mode!r}, api_key={key})")

    async def __aenter__(self) -> OpenAIVLM:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        await self._http.close()

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
        return self._structured.mode

    @property
    def unreachable(self) -> str | None:
        return self._http.unreachable

    async def list_models(self) -> list[str] | None:
        """The model ids ``GET {base_url}/models`` lists; None where the server does not
        serve that route (404, 405). Raises the :class:`VLMError` of :meth:`ask`."""
        url = self.config.base_url.rstrip("/") + "/models"
        trace = Trace()
        status, body = await self._http.send("GET", url, None, trace, 0)
        if status in (404, 405):
            return None
        if not 200 <= status < 300:
            raise self._http.http_error(status, body, url)
        data = self._http.decode(body, status).get("data")
        if not isinstance(data, list):
            raise VLMResponseError(f"GET {url} answered without a 'data' list: "
                                   f"{self._http.excerpt(body)!r}")
        return [m["id"] for m in data if isinstance(m, dict) and isinstance(m.get("id"), str)]

    async def probe(self) -> VLMProbe:
        """One tiny question (two made-up candidates, a 64 px photo only when the prompt
        mode sends one) with this client's structured-output mode and its fallback, no
        transport retry. Raises :class:`VLMError`: unreachable, a refused key (401/403), an
        unknown model (404), ..."""
        image = probe_image() if self.template.uses_image else None
        answer, trace = await self._ask(image, PROBE_DESCRIPTION, PROBE_CANDIDATES, 0)
        return VLMProbe(structured_output=answer.structured_output or self._structured.mode,
                        latency_s=answer.elapsed_s, label=answer.label,
                        fallbacks=tuple(trace.stepped_down), reasons=tuple(trace.reasons),
                        raw=answer.raw)

    async def ask(self, image: bytes | VLMImage | None, description: str,
                  candidates: Sequence[str]) -> VLMAnswer:
        answer, _ = await self._ask(image, description, candidates, self.config.max_retries)
        return answer

    async def _ask(self, image: bytes | VLMImage | None, description: str,
                   candidates: Sequence[str], max_retries: int) -> tuple[VLMAnswer, Trace]:
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
            stored_url = elided(prepared)
            splice = (stored_url, data_url)
        elif image is not None:
            log.debug("VLM mode %s: image not sent", self.template.mode)

        trace = Trace()
        ask_reason = self.config.ask_reason
        while True:
            mode = self._structured.mode
            head = request_head(self.config.model, self.config.seed, mode, labels, ask_reason)
            prompt = ask_for(rendered, mode, ask_reason)
            # Both name the image; encode_json puts the data URL in what goes on the wire.
            wire = [user_message(prompt, stored_url)]
            stored = [user_message(prompt, stored_url)]
            try:
                response, raw = await self._complete({**head, "messages": wire}, trace,
                                                     splice, max_retries, mode != "none")
            except VLMFormatRefusedError as exc:
                self._structured.step_down(mode, trace, "refused",
                                           f"HTTP {exc.status}: {exc.excerpt}")
                continue
            # Read as stored: a reason never shows the API key, even cut short.
            reading = read_answer(self._http.redact(raw), labels, mode, ask_reason)
            if reading.honoured:
                break
            # A 200 that is not the requested JSON: the server took the mode and ignored it.
            self._structured.step_down(mode, trace, "ignored",
                                       f"answered {self._http.excerpt(raw.encode())!r}, not JSON")
        if reading.label is None:
            log.warning("VLM answer %r is not a candidate; asking once more",
                        self._http.redact(raw[:EXCERPT_CHARS]))
            correction = {"role": "user", "content": correction_message(labels, mode, ask_reason)}
            echo = raw[:MAX_ECHO_CHARS] or "(no answer)"
            wire += [{"role": "assistant", "content": echo}, correction]
            stored += [{"role": "assistant", "content": self._http.redact(echo)}, correction]
            response, raw = await self._complete({**head, "messages": wire}, trace, splice,
                                                 max_retries, False)
            reading = read_answer(self._http.redact(raw), labels, mode, ask_reason)
        label = reading.label
        if reading.reason_note:
            log.warning("VLM answer %r: %s", self._http.redact(raw[:EXCERPT_CHARS]),
                        reading.reason_note)
        status: Status = "ok" if label is not None else "invalid_answer"
        elapsed = time.monotonic() - started
        if label is None:
            log.warning("VLM gave no valid label after a corrective retry: %r",
                        self._http.redact(raw[:EXCERPT_CHARS]))
        else:
            log.info("VLM answered %r in %.2f s (%d attempt(s), %s)", label, elapsed,
                     len(trace.outcomes), mode)
        return VLMAnswer(
            status=status, label=label, raw=self._http.redact(raw), prompt=rendered,
            candidates=tuple(labels), model=self.config.model,
            request={**head, "messages": stored}, response=self._http.redact_json(response),
            image=prepared.info() if prepared else None, attempts=len(trace.outcomes),
            latency_s=tuple(trace.latency_s), outcomes=tuple(trace.outcomes),
            elapsed_s=elapsed, structured_output=mode,
            reason=reading.reason,
        ), trace

    # -- one round: POST with transport retries, then the answer text --

    async def _complete(self, body: dict[str, Any], trace: Trace,
                        splice: tuple[str, bytes] | None, max_retries: int,
                        structured: bool) -> tuple[dict, str]:
        payload = encode_json(body, splice)
        status, raw = await self._http.send("POST", self.url, payload, trace, max_retries,
                                            structured)
        if not 200 <= status < 300:
            raise self._http.http_error(status, raw, self.url, structured)
        data = self._http.decode(raw, status)
        return data, self._content(data)

    def _content(self, data: dict[str, Any]) -> str:
        choices = data.get("choices")
        if not isinstance(choices, list) or not choices or not isinstance(choices[0], dict):
            raise VLMResponseError(
                f"VLM answer has no choices: {self._http.excerpt(json.dumps(data).encode())!r}")
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

