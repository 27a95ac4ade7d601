"""A fake OpenAI-compatible VLM server on loopback, for tests and demos.

It checks requests the way the real servers do and a little more strictly (the shape the
runtime promises: ``model``, ``messages`` with a data-URL image that decodes, ``temperature``
0, and a response format that is a strict ``json_schema`` with an enum of candidates (and
optionally a ``reason`` string before the ``label``),
``json_object`` with a prompt that asks for JSON, or none; without a schema the candidates
are read from the prompt's "Candidates:" line), answers 400 to a malformed one, 401 to a
wrong key, 404 to an unknown model, 413 to an oversized body, and records every request
it received (``fake.requests``, each with the monotonic time it arrived) for assertions;
``on_request`` is called with each once it is answered.

What it answers is scriptable: queue :class:`Reply` objects with :meth:`FakeVLM.script`
(a label, raw content, a status with ``Retry-After``, a non-JSON or huge body, a slow
trickle, a dropped connection, latency); when the queue is empty it answers the label that
``choose`` picks (default: the first candidate), as a model that follows the prompt would:
``{"label": ...}`` to a request with a ``response_format`` or whose last message asks for
JSON, else the label alone. A request that asks for a reason (a schema with ``reason``, or a
last message asking for ``{"reason": ...}`` or a ``"Reason:"`` line) gets the one ``explain``
gives first: ``{"reason": ..., "label": ...}``, or ``Reason: ...`` then ``Label: ...``.
The simulated VLM
(:mod:`edge.sim.standin_vlm`, a chooser that knows only what a VLM would know) is served by
this same class.

    async with FakeVLM(model="fake") as fake:
        fake.script(Reply.error(503), Reply(label="wood_cube"))
        client = OpenAIVLM(VLMConfig(base_url=fake.base_url, model="fake"))

``structured`` makes it act like servers that do not support every structured-output mode,
answering as they do (:data:`REFUSALS`): ``"json_object_only"`` refuses ``json_schema`` (an
older llama.cpp server), ``"none_only"`` refuses any ``response_format`` (vLLM without it,
TGI, ...), ``"ignored"`` takes any ``response_format`` without looking and answers ``prose``
whatever it is asked (default "The object is most likely the <label> because ...";
``{label}`` stands for the chosen label).

Standalone, for demos: ``python -m edge.sim.fake_vlm --port 8011``.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import binascii
import collections
import contextlib
import io
import json
import logging
import re
import signal
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from aiohttp import web
from PIL import Image, UnidentifiedImageError

log = logging.getLogger(__name__)

DATA_URL = re.compile(r"data:(image/(?:jpeg|png|webp|gif));base64,(.*)", re.S)
DEFAULT_MAX_REQUEST_BYTES = 20 * 1024 * 1024
STRUCTURED = ("any", "json_object_only", "none_only", "ignored")
# How real servers refuse a response_format they do not support: (status, content type,
# body with {mode} for the refused type). Quoted from their answers.
REFUSALS: dict[str, tuple[int, str, str]] = {
    # vLLM built without the field: its request model forbids extra inputs (pydantic).
    "vllm": (400, "application/json", json.dumps({
        "object": "error", "type": "BadRequestError", "param": None, "code": 400,
        "message": "[{'type': 'extra_forbidden', 'loc': ('body', 'response_format'), "
                   "'msg': 'Extra inputs are not permitted', 'input': {'type': '{mode}'}}]"})),
    # TGI: axum's rejection of a body it cannot deserialise, as plain text.
    "tgi": (422, "text/plain; charset=utf-8",
            "Failed to deserialize the JSON body into the target type: response_format: "
            "unknown variant `{mode}`, expected `json` or `regex` at line 1 column 97"),
    # llama.cpp server before json_schema support (a build that answers 400).
    "llamacpp": (400, "application/json", json.dumps({"error": {
        "code": 400, "type": "invalid_request_error",
        "message": 'response_format type must be one of "text" or "json_object", but got: '
                   "{mode}"}})),
    # Older llama.cpp builds answered the same refusal as a 500 server_error.
    "llamacpp_500": (500, "application/json", json.dumps({"error": {
        "code": 500, "type": "server_error",
        "message": 'response_format type must be one of "text" or "json_object", but got: '
                   "{mode}"}})),
    # Ollama (0.5) when it cannot turn the schema into its own "format".
    "ollama": (500, "application/json", json.dumps({"error": "invalid JSON schema in format"})),
    # LM Studio 0.3: only json_schema or text.
    "lmstudio": (400, "application/json",
                 json.dumps({"error": "'response_format.type' must be 'json_schema' or "
                                      "'text'"})),
}
# What a chatty model behind a server that ignores response_format says.
PROSE = "The object is most likely the {label} because the photo and the touch both fit it."
# How a request asks for JSON in its text (the shipped templates, the corrective retry).
ASKS_JSON = '{"label"'
# How a request asks for a reason before the label: in JSON, or on a "Reason:" line.
ASKS_REASON_JSON = '{"reason"'
ASKS_REASON_LINE = '"Reason:"'


@dataclass(frozen=True)
class Reply:
    """One scripted answer; the defaults answer 200 with the chosen label."""

    status: int = 200
    # The label answered as {"label": ...}; None = the one ``choose`` picks.
    label: str | None = None
    # The message content verbatim (overrides label): bad JSON, prose, a code fence...
    content: str | None = None
    # The HTTP body verbatim (overrides everything above): non-JSON, huge...
    body: bytes | None = None
    headers: Mapping[str, str] = field(default_factory=dict)
    # Wait this long before answering.
    delay_s: float = 0.0
    # Trickle: send the body in ``chunk_bytes`` pieces this far apart.
    chunk_delay_s: float = 0.0
    chunk_bytes: int = 16
    # Send without Content-Length (chunked transfer encoding).
    chunked: bool = False
    # Close the connection without any answer.
    drop: bool = False

    @classmethod
    def error(cls, status: int, message: str = "fake error", *,
              retry_after: str | float | None = None) -> Reply:
        headers = {} if retry_after is None else {"Retry-After": str(retry_after)}
        body = json.dumps({"error": {"message": message, "type": "fake_error",
                                     "code": status}}).encode()
        return cls(status=status, body=body, headers=headers)

    @classmethod
    def huge(cls, n_bytes: int, *, chunked: bool = False) -> Reply:
        """A JSON-looking 200 body of ``n_bytes`` (with or without Content-Length)."""
        head = b'{"choices":[{"message":{"role":"assistant","content":"'
        tail = b'"}}]}'
        pad = max(0, n_bytes - len(head) - len(tail))
        return cls(body=head + b"x" * pad + tail, chunked=chunked)

    @classmethod
    def dropped(cls) -> Reply:
        return cls(drop=True)


@dataclass
class FakeRequest:
    """One request as received, parsed as far as it goes."""

    method: str
    path: str
    headers: dict[str, str]
    raw: bytes
    body: dict[str, Any] | None = None
    # Why it was refused (None if it was well formed) and the status answered.
    error: str | None = None
    status: int = 0
    candidates: list[str] = field(default_factory=list)
    # The text parts of the first user message, joined; and every decoded image.
    prompt: str = ""
    images: list[bytes] = field(default_factory=list)
    image_mimes: list[str] = field(default_factory=list)
    received_at: float = 0.0  # time.monotonic() when the server began handling it

    @property
    def description(self) -> str:
        """The tactile description, if the prompt says "... similar to <it>." (shipped)."""
        m = re.search(r"similar to (.+?)\.?\s*$", self.prompt, re.M)
        return m.group(1) if m else ""


Chooser = Callable[[FakeRequest], str]
# The reason given for a chosen label, when a request asks for one.
Explainer = Callable[[FakeRequest, str], str]


def first_candidate(req: FakeRequest) -> str:
    return req.candidates[0]


def plain_reason(req: FakeRequest, label: str) -> str:
    return f"{label} is the candidate that fits the question best."


def choose_by_description(req: FakeRequest) -> str:
    """The candidate sharing the most words with the tactile description (ties: first)."""
    words = set(re.findall(r"[a-z]+", req.description.lower()))

    def score(label: str) -> int:
        return len(set(re.findall(r"[a-z]+", label.lower())) & words)

    return max(req.candidates, key=score)


def validate_chat_request(body: Any, check_format: bool = True
                          ) -> tuple[str | None, dict[str, Any]]:
    """(error or None, parsed pieces) for a /chat/completions body, as the runtime sends;
    ``check_format=False``: the response format is not looked at, like a server that
    ignores it."""
    got: dict[str, Any] = {"candidates": [], "prompt": "", "images": [], "mimes": []}
    if not isinstance(body, dict):
        return "request body must be a JSON object", got
    if not isinstance(body.get("model"), str) or not body["model"]:
        return "model: required string", got
    messages = body.get("messages")
    if not isinstance(messages, list) or not messages:
        return "messages: required non-empty array", got
    prompt_done = False
    for i, msg in enumerate(messages):
        if not isinstance(msg, dict) or msg.get("role") not in ("system", "user", "assistant"):
            return f"messages[{i}]: needs a role of system, user or assistant", got
        content = msg.get("content")
        if isinstance(content, str):
            parts: list[Any] = [{"type": "text", "text": content}]
        elif isinstance(content, list) and content:
            parts = content
        else:
            return f"messages[{i}].content: must be a string or a non-empty array", got
        texts = []
        for j, part in enumerate(parts):
            where = f"messages[{i}].content[{j}]"
            kind = part.get("type") if isinstance(part, dict) else None
            if kind == "text":
                if not isinstance(part.get("text"), str):
                    return f"{where}.text: required string", got
                texts.append(part["text"])
            elif kind == "image_url":
                url = part.get("image_url")
                url = url.get("url") if isinstance(url, dict) else None
                if not isinstance(url, str):
                    return f"{where}.image_url.url: required string", got
                err, mime, data = _decode_data_url(url)
                if err:
                    return f"{where}.image_url.url: {err}", got
                got["images"].append(data)
                got["mimes"].append(mime)
            else:
                return f"{where}: unknown content type {kind!r}", got
        if msg["role"] == "user" and not prompt_done:
            got["prompt"] = "\n".join(texts)
            prompt_done = True
    temperature = body.get("temperature")
    if isinstance(temperature, bool) or not isinstance(temperature, int | float):
        return "temperature: required number (the runtime always sends 0)", got
    if temperature != 0:
        return f"temperature: must be 0 for recognition, got {temperature!r}", got
    seed = body.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        return "seed: must be an integer", got
    if body.get("stream") not in (None, False):
        return "stream: this fake does not stream", got
    rf = body.get("response_format")
    kind = rf.get("type") if isinstance(rf, dict) else None
    if check_format and kind == "json_schema":
        err, candidates = _check_response_format(rf)
        if err:
            return f"response_format: {err}", got
        got["candidates"] = candidates
        return None, got
    if check_format and rf is not None and kind not in ("json_object", "text"):
        return "response_format.type: must be 'json_schema', 'json_object' or 'text'", got
    if check_format and kind == "json_object" and "json" not in json.dumps(messages).lower():
        # OpenAI's own rule for JSON mode.
        return ("'messages' must contain the word 'json' in some form, to use "
                "'response_format' of type 'json_object'."), got
    got["candidates"] = prompt_candidates(got["prompt"])
    if not got["candidates"]:
        return "no schema and no 'Candidates:' line in the prompt to choose from", got
    return None, got


def prompt_candidates(prompt: str) -> list[str]:
    """The labels of the prompt's "Candidates: ..." line (the shipped templates'), or []."""
    m = re.search(r"^Candidates: (.+)$", prompt, re.M)
    try:
        labels = json.loads(f"[{m.group(1)}]") if m else []
    except ValueError:
        return []
    return [x for x in labels if isinstance(x, str) and x]


def _asks(body: Any) -> tuple[bool, bool]:
    """What a request checked by :func:`validate_chat_request` asks for, as a model that
    follows it reads it: (JSON, a reason first). JSON: a response_format, or its last
    message says so (free-text mode asks for the label alone); a reason: a schema with one,
    or the last message asks for it."""
    content = body["messages"][-1]["content"]
    if isinstance(content, list):
        content = " ".join(p["text"] for p in content if p["type"] == "text")
    rf = body.get("response_format")
    if rf is not None and rf["type"] == "json_schema":
        return True, "reason" in rf["json_schema"]["schema"]["properties"]
    if rf is not None or ASKS_JSON in content or ASKS_REASON_JSON in content:
        return True, ASKS_REASON_JSON in content
    return False, ASKS_REASON_LINE in content


def _decode_data_url(url: str) -> tuple[str | None, str, bytes]:
    if url.startswith(("http://", "https://")):
        return "only data: URLs are accepted (like Ollama), not http(s) URLs", "", b""
    m = DATA_URL.fullmatch(url)
    if not m:
        return "must be data:image/<jpeg|png|webp|gif>;base64,<data>", "", b""
    try:
        data = base64.b64decode(m.group(2), validate=True)
    except (binascii.Error, ValueError):
        return "base64 data does not decode", "", b""
    try:
        with Image.open(io.BytesIO(data)) as img:
            img.verify()
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError):
        return "data is not a decodable image", "", b""
    return None, m.group(1), data


def _check_response_format(rf: Any) -> tuple[str | None, list[str]]:
    if not isinstance(rf, dict) or rf.get("type") != "json_schema":
        return 'must be {"type": "json_schema", ...}', []
    js = rf.get("json_schema")
    if not isinstance(js, dict) or not isinstance(js.get("name"), str) or not js["name"]:
        return "json_schema.name: required string", []
    if js.get("strict") is not True:
        return "json_schema.strict: must be true", []
    schema = js.get("schema")
    if not isinstance(schema, dict) or schema.get("type") != "object":
        return "json_schema.schema.type: must be object", []
    props = schema.get("properties")
    if isinstance(props, dict) and list(props) not in (["label"], ["reason", "label"]):
        return "json_schema.schema.properties: only label, or reason then label", []
    if isinstance(props, dict) and "reason" in props and props["reason"] != {"type": "string"}:
        return "json_schema.schema.properties.reason: must be a string property", []
    label = props.get("label") if isinstance(props, dict) else None
    if not isinstance(label, dict) or label.get("type") != "string":
        return "json_schema.schema.properties.label: must be a string property", []
    enum = label.get("enum")
    if (not isinstance(enum, list) or not enum or not all(isinstance(e, str) and e for e in enum)
            or len(set(enum)) != len(enum)):
        return "json_schema.schema.properties.label.enum: non-empty distinct strings", []
    if schema.get("required") != list(props) or schema.get("additionalProperties") is not False:
        return ("json_schema.schema: needs every property required in order, "
                "additionalProperties false"), []
    return None, list(enum)


class FakeVLM:
    """The fake server; an async context manager exposing ``base_url``."""

    def __init__(
        self,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        model: str | Sequence[str] | None = "fake-vlm",
        api_key: str | None = None,
        choose: Chooser = first_candidate,
        explain: Explainer = plain_reason,
        latency_s: float = 0.0,
        max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
        echo_key_in_errors: bool = False,
        on_request: Callable[[FakeRequest], None] | None = None,
        title: str = "fake VLM",
        fingerprint: str = "fake-vlm",
        structured: str = "any",
        refusal: str | None = None,
        prose: str = PROSE,
    ) -> None:
        if structured not in STRUCTURED:
            raise ValueError(f"structured={structured!r}: one of {', '.join(STRUCTURED)}")
        self.host = host
        self.port = port
        # None accepts any model name; several names are several models of one server.
        self.models: tuple[str, ...] | None = (
            None if model is None else (model,) if isinstance(model, str) else tuple(model))
        self.model = None if self.models is None else self.models[0]
        # What it calls itself in its log lines, and its answers' system_fingerprint.
        self.title = title
        self.fingerprint = fingerprint
        self.api_key = api_key
        self.choose = choose
        self.explain = explain
        self.latency_s = latency_s
        self.max_request_bytes = max_request_bytes
        # A careless server that quotes the key it got (to test that the client redacts it).
        self.echo_key_in_errors = echo_key_in_errors
        # Called with each chat request once it is answered, refused or dropped.
        self.on_request = on_request
        # Which response formats it supports, and whose words it refuses the others with.
        self.structured = structured
        self.refusal = refusal or ("llamacpp" if structured == "json_object_only" else "vllm")
        # What it answers when it ignores response_format.
        self.prose = prose
        if self.refusal not in REFUSALS:
            raise ValueError(f"refusal={self.refusal!r}: one of {', '.join(REFUSALS)}")
        self.requests: list[FakeRequest] = []
        self._replies: collections.deque[Reply] = collections.deque()
        self._runner: web.AppRunner | None = None
        self._count = 0

    @property
    def base_url(self) -> str:
        return f"http://{self.host}:{self.port}/v1"

    @property
    def chat_requests(self) -> list[FakeRequest]:
        return [r for r in self.requests if r.path.endswith("/chat/completions")]

    def script(self, *replies: Reply) -> None:
        """Queue replies, used one per well-formed request, in order."""
        self._replies.extend(replies)

    @property
    def pending(self) -> int:
        return len(self._replies)

    async def start(self) -> FakeVLM:
        app = web.Application(client_max_size=self.max_request_bytes)
        app.router.add_post("/v1/chat/completions", self._chat)
        app.router.add_get("/v1/models", self._models)
        self._runner = web.AppRunner(app, handler_cancellation=True, shutdown_timeout=0.5,
                                     access_log=None)
        await self._runner.setup()
        await web.TCPSite(self._runner, self.host, self.port).start()
        self.port = self._runner.addresses[0][1]  # the bound port when port=0
        log.info("%s listening on %s", self.title, self.base_url)
        return self

    async def stop(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def __aenter__(self) -> FakeVLM:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # -- handlers --

    async def _models(self, request: web.Request) -> web.Response:
        return web.json_response({"object": "list", "data": [
            {"id": name, "object": "model", "owned_by": "vtzero"}
            for name in (self.models or ("fake-vlm",))]})

    async def _chat(self, request: web.Request) -> web.StreamResponse:
        rec = FakeRequest(request.method, request.path, dict(request.headers), b"",
                          received_at=time.monotonic())
        self.requests.append(rec)
        try:
            return await self._answer(request, rec)
        finally:
            if self.on_request is not None:
                self.on_request(rec)

    async def _answer(self, request: web.Request, rec: FakeRequest) -> web.StreamResponse:
        try:
            rec.raw = await request.read()
        except web.HTTPRequestEntityTooLarge:
            return self._error(rec, 413, f"request body larger than {self.max_request_bytes} "
                                         "bytes", "request_too_large")
        if self.api_key is not None:
            auth = request.headers.get("Authorization", "")
            if auth != f"Bearer {self.api_key}":
                message = "Incorrect API key provided"
                if self.echo_key_in_errors:
                    message += f": {auth.removeprefix('Bearer ')}"
                return self._error(rec, 401, message, "invalid_api_key")
        try:
            rec.body = json.loads(rec.raw)
        except (ValueError, RecursionError):
            return self._error(rec, 400, "request body is not valid JSON", "invalid_json")
        refused = self._refused_format(rec.body)
        if refused is not None:
            return self._refuse(rec, refused)
        err, got = validate_chat_request(rec.body, self.structured != "ignored")
        rec.candidates, rec.prompt = got["candidates"], got["prompt"]
        rec.images, rec.image_mimes = got["images"], got["mimes"]
        if err:
            return self._error(rec, 400, err, "invalid_request_error")
        assert isinstance(rec.body, dict)
        if self.models is not None and rec.body["model"] not in self.models:
            return self._error(rec, 404, f"model {rec.body['model']!r} not found, try "
                                         "pulling it first", "model_not_found")
        reply = self._replies.popleft() if self._replies else Reply()
        rec.status = reply.status
        if self.latency_s or reply.delay_s:
            await asyncio.sleep(self.latency_s + reply.delay_s)
        if reply.drop:
            rec.status = 0
            assert request.transport is not None
            request.transport.abort()
            raise asyncio.CancelledError  # nothing more to say on a dead connection
        return await self._send(request, rec, reply)

    async def _send(self, request: web.Request, rec: FakeRequest,
                    reply: Reply) -> web.StreamResponse:
        if reply.body is not None:
            body = reply.body
        else:
            content = reply.content
            if content is None:
                label = reply.label if reply.label is not None else self.choose(rec)
                if self.structured == "ignored":
                    content = self.prose.replace("{label}", label)
                else:
                    content = self._say(rec, label)
            body = json.dumps(self._completion(rec, content)).encode()
        headers = {"Content-Type": "application/json", **reply.headers}
        if not reply.chunked and not reply.chunk_delay_s:
            return web.Response(status=reply.status, body=body, headers=headers)
        resp = web.StreamResponse(status=reply.status, headers=headers)
        if reply.chunked:
            resp.enable_chunked_encoding()
        else:
            resp.content_length = len(body)
        await resp.prepare(request)
        step = max(1, reply.chunk_bytes if reply.chunk_delay_s else 64 * 1024)
        for i in range(0, len(body), step):
            await resp.write(body[i:i + step])
            if reply.chunk_delay_s:
                await asyncio.sleep(reply.chunk_delay_s)
        await resp.write_eof()
        return resp

    def _say(self, rec: FakeRequest, label: str) -> str:
        """``label`` in the form the request asks for, with a reason first if it asks."""
        json_form, reason = _asks(rec.body)
        if json_form:
            return json.dumps({"reason": self.explain(rec, label), "label": label} if reason
                              else {"label": label})
        return f"Reason: {self.explain(rec, label)}\nLabel: {label}" if reason else label

    def _completion(self, rec: FakeRequest, content: str) -> dict[str, Any]:
        self._count += 1
        body = rec.body or {}
        prompt_tokens = len(rec.prompt.split()) + 256 * len(rec.images)
        completion_tokens = max(1, len(content) // 4)
        return {
            "id": f"chatcmpl-fake-{self._count}", "object": "chat.completion",
            "created": int(time.time()), "model": body.get("model", self.model),
            "system_fingerprint": self.fingerprint,
            "choices": [{"index": 0, "finish_reason": "stop",
                         "message": {"role": "assistant", "content": content}}],
            "usage": {"prompt_tokens": prompt_tokens, "completion_tokens": completion_tokens,
                      "total_tokens": prompt_tokens + completion_tokens},
        }

    def _refused_format(self, body: Any) -> str | None:
        """The response_format type this server refuses in ``body``, or None."""
        rf = body.get("response_format") if isinstance(body, dict) else None
        if rf is None or self.structured in ("any", "ignored"):
            return None
        kind = rf.get("type") if isinstance(rf, dict) else None
        if self.structured == "none_only" or kind == "json_schema":
            return str(kind)
        return None

    def _refuse(self, rec: FakeRequest, mode: str) -> web.Response:
        status, content_type, body = REFUSALS[self.refusal]
        rec.error, rec.status = f"response_format {mode} refused ({self.refusal})", status
        log.debug("%s refused response_format %s", self.title, mode)
        return web.Response(status=status, text=body.replace("{mode}", mode),
                            content_type=content_type.split(";")[0])

    def _error(self, rec: FakeRequest, status: int, message: str, code: str) -> web.Response:
        rec.error, rec.status = message, status
        log.debug("%s refused a request: %d %s", self.title, status, message)
        return web.json_response(
            {"error": {"message": message, "type": "invalid_request_error", "code": code}},
            status=status)


async def _serve(args: argparse.Namespace) -> None:
    choose: Chooser = first_candidate
    if args.choose == "description":
        choose = choose_by_description
    elif args.choose.startswith("label:"):
        fixed = args.choose.removeprefix("label:")

        def choose(req: FakeRequest) -> str:
            return fixed
    elif args.choose != "first":
        raise SystemExit(f"fake_vlm: --choose {args.choose!r}: use first, description or "
                         "label:<name> (the simulated VLM is vt-edge sim vlm)")

    fake = FakeVLM(host=args.host, port=args.port, model=args.model or None,
                   choose=choose, latency_s=args.latency_s, structured=args.structured,
                   refusal=args.refusal, prose=args.prose)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    async with fake:
        print(f"fake VLM at {fake.base_url} (model {fake.model or 'any'}); Ctrl-C stops",
              flush=True)
        await stop.wait()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m edge.sim.fake_vlm",
                                     description="A fake OpenAI-compatible VLM on loopback.")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8011)
    parser.add_argument("--model", default="fake-vlm", help="model name to accept ('' = any)")
    parser.add_argument("--choose", default="first",
                        help="first | description | label:<name> (default first; the "
                        "simulated VLM is vt-edge sim vlm)")
    parser.add_argument("--latency-s", type=float, default=0.0)
    parser.add_argument("--structured", choices=STRUCTURED, default="any",
                        help="the response formats it supports, like a real server's "
                        "(default any)")
    parser.add_argument("--refusal", choices=sorted(REFUSALS), default=None,
                        help="whose words it refuses a response format with")
    parser.add_argument("--prose", default=PROSE,
                        help="what it answers with --structured ignored ({label}: the chosen "
                        "label; default %(default)r)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    asyncio.run(_serve(args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
