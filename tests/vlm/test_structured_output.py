"""Structured output against servers that do not support every mode: the real client, the
fake acting like each kind of server (edge/sim/fake_vlm.py REFUSALS), over loopback HTTP."""

import asyncio
import logging
import time
from dataclasses import replace

import pytest

from edge.core.errors import (
    VLMConnectionError,
    VLMFormatRefusedError,
    VLMRejectedError,
)
from edge.sim.fake_vlm import REFUSALS, FakeVLM, Reply
from edge.vlm.answer import LABEL_ALONE
from edge.vlm.chat import response_format
from edge.vlm.client import OpenAIVLM
from edge.vlm.prompt import format_candidates
from edge.vlm.structured import PROBE_CANDIDATES
from edge.vlm.transport import UNREACHABLE_AFTER_ATTEMPTS
from tests.support.waits import free_port
from tests.vlm.helpers import CANDIDATES, DESCRIPTION, MODEL, vlm_config

# The shipped prompts list the candidates on a "Candidates:" line (the fake reads them there
# when no schema names them) and ask for {"label": ...}.
SECOND = CANDIDATES[1]


def pick_second(req):
    return SECOND


def fallback_warnings(caplog):
    return [r for r in caplog.records
            if r.levelno == logging.WARNING and "refused structured output" in r.getMessage()]


@pytest.mark.asyncio
@pytest.mark.parametrize(("mode", "expected"), [
    ("json_schema", response_format(CANDIDATES)),
    ("json_object", {"type": "json_object"}),
    ("none", None),
])
async def test_each_mode_sends_its_response_format(jpeg, mode, expected):
    async with FakeVLM(model=MODEL, choose=pick_second) as fake, \
            OpenAIVLM(vlm_config(fake.base_url, structured_output=mode)) as vlm:
        answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
    body = fake.chat_requests[0].body
    assert body.get("response_format") == expected
    prompt = fake.chat_requests[0].prompt
    assert f"Candidates: {format_candidates(CANDIDATES)}" in prompt
    # JSON modes ask for JSON; free text for the label alone (and the fake answers so).
    assert ('{"label": "<candidate>"}' in prompt) is (mode != "none")
    assert prompt.endswith(LABEL_ALONE) is (mode == "none")
    assert (answer.raw == SECOND) is (mode == "none")
    assert (answer.status, answer.label, answer.structured_output) == ("ok", SECOND, mode)
    assert answer.request.get("response_format") == expected and answer.attempts == 1


@pytest.mark.asyncio
@pytest.mark.parametrize("refusal", ["vllm", "tgi", "llamacpp_500", "lmstudio", "ollama"])
async def test_a_server_refusing_response_format_is_asked_in_free_text(jpeg, caplog, refusal):
    """(a) Refuses any response_format, in the words (and status) of a real server: the client
    steps down json_schema -> json_object -> none, logs each step once, keeps it."""
    caplog.set_level(logging.WARNING, "edge.vlm.client")
    async with FakeVLM(model=MODEL, choose=pick_second, structured="none_only",
                       refusal=refusal) as fake:
        async with OpenAIVLM(vlm_config(fake.base_url)) as vlm:
            first = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
            second = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
            assert vlm.structured_output == "none"
        status = REFUSALS[refusal][0]
        assert [r.status for r in fake.chat_requests] == [status, status, 200, 200]
        assert [(r.body or {}).get("response_format", {}).get("type")
                for r in fake.chat_requests] == ["json_schema", "json_object", None, None]
        for answer in (first, second):
            assert (answer.status, answer.label, answer.structured_output) == ("ok", SECOND,
                                                                               "none")
        # Not retried as a server error, even where the refusal is a 500.
        assert first.outcomes == (str(status), str(status), "200")
        assert second.outcomes == ("200",)
        warnings = fallback_warnings(caplog)
        print(f"\n{refusal}: {[w.getMessage() for w in warnings]}")
        assert len(warnings) == 2
        assert "json_schema" in warnings[0].getMessage()
        assert "json_object" in warnings[1].getMessage()
        assert f"HTTP {status}" in warnings[0].getMessage()
        if refusal == "vllm":  # its message, not the whole error object
            assert "HTTP 400: [{'type': 'extra_forbidden'" in warnings[0].getMessage()
        # A new client (as after SIGHUP) starts from the configured mode again.
        async with OpenAIVLM(vlm_config(fake.base_url)) as vlm:
            assert vlm.structured_output == "json_schema"
            again = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
        assert again.structured_output == "none" and len(fake.chat_requests) == 7


@pytest.mark.asyncio
async def test_questions_in_flight_together_log_each_step_once(jpeg, caplog):
    caplog.set_level(logging.WARNING, "edge.vlm.client")
    async with FakeVLM(model=MODEL, structured="none_only", latency_s=0.05) as fake, \
            OpenAIVLM(vlm_config(fake.base_url)) as vlm:
        answers = await asyncio.gather(*(vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
                                         for _ in range(3)))
    assert all(a.status == "ok" and a.structured_output == "none" for a in answers)
    assert len(fallback_warnings(caplog)) == 2


def ignored_warnings(caplog):
    return [r for r in caplog.records
            if r.levelno == logging.WARNING and "ignored structured output" in r.getMessage()]


FOOD = ["macaron", "resin_replica_macaron", "melon_pan"]
NEGATION = "This is not a real macaron; it is a resin replica."


@pytest.mark.asyncio
@pytest.mark.parametrize(("prose", "label"), [
    (NEGATION, None),
    ("macaron, resin_replica_macaron", None),  # a list of two candidates
    ("Macarons.", None),  # a candidate inside a longer word
    ("The object is most likely the {label} because it is soft.", None),
    ("Label: {label}.", "macaron"),  # the label alone, as free text asks
])
async def test_a_server_ignoring_response_format_is_asked_in_free_text(jpeg, caplog, prose,
                                                                       label):
    """Takes response_format without looking and answers prose: in a JSON mode that is the
    mode ignored (step down, logged once); in free text only the label alone is a label,
    else the corrective retry, then invalid_answer with the text kept."""
    caplog.set_level(logging.WARNING, "edge.vlm.client")
    async with FakeVLM(model=MODEL, structured="ignored", prose=prose) as fake, \
            OpenAIVLM(vlm_config(fake.base_url)) as vlm:
        first = await vlm.ask(jpeg, DESCRIPTION, FOOD)
        second = await vlm.ask(jpeg, DESCRIPTION, FOOD)
        assert vlm.structured_output == "none"
    said = prose.replace("{label}", FOOD[0])
    print(f"\n{said!r}: {first.status} {first.label} via {first.structured_output}, "
          f"then {second.status}, {len(fake.chat_requests)} requests")
    sent = [(r.body.get("response_format") or {}).get("type") for r in fake.chat_requests]
    asked = 1 if label else 2  # with the corrective retry
    assert sent == ["json_schema", "json_object"] + [None] * (2 * asked)
    assert all(r.status == 200 for r in fake.chat_requests)
    for answer in (first, second):
        assert (answer.label, answer.structured_output, answer.raw) == (label, "none", said)
        assert answer.status == ("ok" if label else "invalid_answer")
        assert LABEL_ALONE in answer.request["messages"][0]["content"][0]["text"]
    assert (first.attempts, second.attempts) == (2 + asked, asked)
    warnings = ignored_warnings(caplog)
    assert [w.getMessage().split(" structured output ")[1][:11] for w in warnings] == [
        "json_schema", "json_object"]
    assert said[:40] in warnings[0].getMessage()


@pytest.mark.asyncio
async def test_prose_to_json_schema_is_asked_again_in_json_mode_first(jpeg, caplog):
    """One mode down at a time: a server that ignores json_schema may honour json_object."""
    caplog.set_level(logging.WARNING, "edge.vlm.client")
    async with FakeVLM(model=MODEL, choose=pick_second) as fake, \
            OpenAIVLM(vlm_config(fake.base_url)) as vlm:
        fake.script(Reply(content=f"It is {SECOND}."))
        answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
        assert vlm.structured_output == "json_object"
    assert (answer.status, answer.label, answer.structured_output) == ("ok", SECOND,
                                                                       "json_object")
    assert answer.outcomes == ("200", "200") and answer.request["response_format"] == {
        "type": "json_object"}
    (warning,) = ignored_warnings(caplog)
    assert f"answered 'It is {SECOND}.', not JSON" in warning.getMessage()


@pytest.mark.asyncio
async def test_markdown_around_json_is_json(jpeg, caplog):
    caplog.set_level(logging.WARNING, "edge.vlm.client")
    async with FakeVLM(model=MODEL) as fake, OpenAIVLM(vlm_config(fake.base_url)) as vlm:
        fake.script(Reply(content='```json\n{"label": "resin_replica_macaron"}\n```'))
        answer = await vlm.ask(jpeg, DESCRIPTION, FOOD)
        assert vlm.structured_output == "json_schema"
    assert (answer.status, answer.label, answer.attempts) == ("ok", "resin_replica_macaron", 1)
    assert answer.structured_output == "json_schema" and not ignored_warnings(caplog)


@pytest.mark.asyncio
async def test_a_server_with_json_mode_only_is_asked_in_json_mode(jpeg, caplog):
    """(c) Refuses json_schema with a 400 (an older llama.cpp server), takes json_object."""
    caplog.set_level(logging.WARNING, "edge.vlm.client")
    async with FakeVLM(model=MODEL, choose=pick_second, structured="json_object_only") as fake:
        async with OpenAIVLM(vlm_config(fake.base_url)) as vlm:
            first = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
            second = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
    assert [r.status for r in fake.chat_requests] == [400, 200, 200]
    assert fake.chat_requests[1].body["response_format"] == {"type": "json_object"}
    assert first.outcomes == ("400", "200") and second.outcomes == ("200",)
    assert (first.label, first.structured_output) == (SECOND, "json_object")
    (warning,) = fallback_warnings(caplog)
    assert 'must be one of "text" or "json_object", but got: json_schema' in warning.getMessage()


@pytest.mark.asyncio
async def test_json_mode_asks_for_json_when_a_custom_prompt_does_not(jpeg, tmp_path):
    (tmp_path / "vision_only.txt").write_text(
        "Which object is in the photo?\nCandidates: ${test_time_classes}\n")
    cfg = vlm_config("", mode="vision_only", prompt_dir=tmp_path,
                     structured_output="json_object")
    async with FakeVLM(model=MODEL, choose=pick_second) as fake:
        async with OpenAIVLM(replace(cfg, base_url=fake.base_url)) as vlm:
            answer = await vlm.ask(jpeg, "", CANDIDATES)
    assert answer.label == SECOND
    assert fake.chat_requests[0].prompt.endswith('Reply only with JSON: {"label": "<candidate>"}')


@pytest.mark.asyncio
async def test_a_400_about_something_else_is_a_plain_error_not_a_fallback(jpeg):
    async with FakeVLM(model=MODEL) as fake, OpenAIVLM(vlm_config(fake.base_url)) as vlm:
        fake.script(Reply.error(400, "messages[0].content: image too small"))
        with pytest.raises(VLMRejectedError) as err:
            await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
        assert not isinstance(err.value, VLMFormatRefusedError)
        assert vlm.structured_output == "json_schema" and len(fake.chat_requests) == 1
        assert "image too small" in str(err.value)


@pytest.mark.asyncio
async def test_probe_reports_the_mode_that_answered_and_the_refused_ones():
    async with FakeVLM(model=MODEL, structured="none_only") as fake, \
            OpenAIVLM(vlm_config(fake.base_url)) as vlm:
        probe = await vlm.probe()
        models = await vlm.list_models()
    print(f"\nprobe: {probe}")
    assert probe.structured_output == "none"
    assert probe.fallbacks == ("json_schema", "json_object")
    assert probe.reasons[0].startswith("refused (HTTP 400: [{'type': 'extra_forbidden'")
    assert len(probe.reasons) == 2
    assert probe.label == PROBE_CANDIDATES[0] and 0 < probe.latency_s < 5
    assert models == [MODEL]
    # The tiny photo went along (the prompt mode sends one), and only two candidates.
    req = fake.chat_requests[-1]
    assert len(req.images) == 1 and len(req.images[0]) < 2000
    assert req.candidates == list(PROBE_CANDIDATES)


@pytest.mark.asyncio
async def test_probe_reads_the_answer_as_a_recognition_does():
    """A server that ignores response_format and answers the negation: the probe says, before
    any press, what every recognition would end as."""
    async with FakeVLM(model=MODEL, structured="ignored", prose=NEGATION) as fake, \
            OpenAIVLM(vlm_config(fake.base_url)) as vlm:
        probe = await vlm.probe()
    print(f"\nprobe: {probe}")
    assert (probe.label, probe.raw, probe.structured_output) == (None, NEGATION, "none")
    assert probe.fallbacks == ("json_schema", "json_object")
    assert all(why.startswith(f"ignored (answered {NEGATION!r}") for why in probe.reasons)
    assert len(fake.chat_requests) == 4  # two modes ignored, free text and its retry


@pytest.mark.asyncio
async def test_probe_without_a_photo_in_tactile_only_mode():
    async with FakeVLM(model=MODEL) as fake, \
            OpenAIVLM(vlm_config(fake.base_url, mode="tactile_only")) as vlm:
        probe = await vlm.probe()
    assert (probe.structured_output, probe.fallbacks) == ("json_schema", ())
    assert fake.chat_requests[0].images == []


@pytest.mark.asyncio
async def test_probe_errors_say_what_is_wrong(monkeypatch):
    async with FakeVLM(model=MODEL, api_key="k" * 20) as fake:
        async with OpenAIVLM(vlm_config(fake.base_url)) as vlm:
            with pytest.raises(VLMRejectedError, match=r"HTTP 401 \(check the API key"):
                await vlm.probe()
        monkeypatch.setenv("VTZERO_VLM_API_KEY", "k" * 20)
        async with OpenAIVLM(vlm_config(fake.base_url, model="nope")) as vlm:
            with pytest.raises(VLMRejectedError, match=r"vlm\.model = 'nope' is served"):
                await vlm.probe()
    url = f"http://127.0.0.1:{free_port()}/v1"
    async with OpenAIVLM(vlm_config(url)) as vlm:
        started = time.monotonic()
        with pytest.raises(VLMConnectionError, match=f"connection to {url}"):
            await vlm.probe()
        took = time.monotonic() - started
    print(f"\nprobe of a closed port failed in {took * 1e3:.0f} ms")
    assert took < 1.0  # no transport retries in a probe


@pytest.mark.asyncio
async def test_list_models_is_none_where_the_route_is_not_served():
    async with FakeVLM(model=MODEL) as fake, \
            OpenAIVLM(vlm_config(f"http://127.0.0.1:{fake.port}/elsewhere")) as vlm:
        assert await vlm.list_models() is None


@pytest.mark.asyncio
async def test_unreachable_after_attempts_without_an_answer_and_back_on_an_answer(jpeg):
    port = free_port()
    url = f"http://127.0.0.1:{port}/v1"
    async with OpenAIVLM(vlm_config(url, max_retries=1)) as vlm:
        for n in range(UNREACHABLE_AFTER_ATTEMPTS // 2):
            assert vlm.unreachable is None, n
            with pytest.raises(VLMConnectionError):
                await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
        assert vlm.unreachable is not None
        assert vlm.unreachable.startswith(f"VLM at {url} unreachable: "
                                          f"{UNREACHABLE_AFTER_ATTEMPTS} attempts in a row")
        async with FakeVLM(model=MODEL, port=port):
            answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
        assert answer.status == "ok" and vlm.unreachable is None
