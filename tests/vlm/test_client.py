"""OpenAIVLM against the fake server over real loopback HTTP."""

import asyncio
import base64
import email.utils
import hashlib
import io
import json
import logging
import time

import pytest
from PIL import Image

from edge.core.errors import (
    ConfigError,
    EdgeError,
    ImageError,
    VLMConnectionError,
    VLMError,
    VLMRejectedError,
    VLMResponseError,
    VLMResponseTooLargeError,
    VLMServerError,
    VLMTimeoutError,
    VLMUnavailableError,
)
from edge.sim.fake_vlm import FakeVLM, Reply, choose_by_description
from edge.vlm.chat import encode_json, response_format
from edge.vlm.client import (
    NoVLM,
    OpenAIVLM,
    VLMAnswer,
    VLMClient,
    VLMConfig,
    make_vlm,
)
from edge.vlm.prompt import load_template
from tests.support.waits import free_port
from tests.vlm.helpers import CANDIDATES, DESCRIPTION, MODEL, image_bytes, vlm_config


class RecordedSleep:
    """An injected sleep: records the backoff delays and does not wait."""

    def __init__(self):
        self.delays = []

    async def __call__(self, delay):
        self.delays.append(delay)


async def ask(config, image, *, candidates=CANDIDATES, description=DESCRIPTION, **kw):
    async with OpenAIVLM(config, **kw) as vlm:
        return await vlm.ask(image, description, candidates)


@pytest.mark.asyncio
async def test_request_has_image_temperature_seed_and_schema(fake, jpeg):
    answer = await ask(vlm_config(fake.base_url, seed=1234), jpeg)
    assert answer.status == "ok" and answer.label == CANDIDATES[0]
    assert answer.attempts == 1 and len(answer.latency_s) == 1 and answer.outcomes == ("200",)
    [req] = fake.requests
    assert req.error is None and req.status == 200
    body = req.body
    assert body["model"] == MODEL and body["temperature"] == 0 and body["seed"] == 1234
    assert body["response_format"] == response_format(CANDIDATES)
    assert body["response_format"]["json_schema"]["schema"]["properties"]["label"][
        "enum"] == CANDIDATES
    [message] = body["messages"]
    text, image = message["content"]
    assert text == {"type": "text", "text": answer.prompt}
    url = image["image_url"]["url"]
    assert url.startswith("data:image/jpeg;base64,")
    assert base64.b64decode(url.split(",", 1)[1]) == jpeg == req.images[0]
    assert DESCRIPTION in req.prompt and req.candidates == CANDIDATES
    assert "Authorization" not in req.headers  # no key configured, none sent
    # The stored request is the one sent, with the image elided to its hash and size.
    stored = answer.request["messages"][0]["content"][1]["image_url"]["url"]
    assert stored.startswith("<elided image/jpeg image") and answer.image["sha256"] in stored
    assert "base64" not in json.dumps(answer.to_dict())
    assert answer.response["choices"][0]["message"]["content"] == json.dumps(
        {"label": CANDIDATES[0]})
    assert answer.image == {**answer.image, "bytes": len(jpeg), "reencoded": False}


@pytest.mark.asyncio
@pytest.mark.parametrize(
    ("content", "mode", "label"),
    [
        ("Raw Kiri Mochi", "none", "raw_kiri_mochi"),
        ('```json\n{"label": "BOILED KIRI MOCHI"}\n```', "json_schema", "boiled_kiri_mochi"),
        ('"raw_kabocha_squash"', "none", "raw_kabocha_squash"),
    ],
)
async def test_variants_map_to_the_candidate(fake, jpeg, content, mode, label):
    fake.script(Reply(content=content))
    answer = await ask(vlm_config(fake.base_url, structured_output=mode), jpeg)
    assert (answer.status, answer.label, answer.attempts) == ("ok", label, 1)
    assert answer.raw == content and answer.structured_output == mode


@pytest.mark.asyncio
async def test_label_outside_candidates_gets_one_corrective_retry(fake, jpeg):
    fake.script(Reply(label="pizza"), Reply(label="boiled_kiri_mochi"))
    answer = await ask(vlm_config(fake.base_url), jpeg)
    assert (answer.status, answer.label, answer.attempts) == ("ok", "boiled_kiri_mochi", 2)
    first, second = fake.requests
    msgs = second.body["messages"]
    assert len(msgs) == 3 and msgs[0] == first.body["messages"][0]
    assert msgs[1] == {"role": "assistant", "content": '{"label": "pizza"}'}
    assert msgs[2]["role"] == "user" and "not one of the candidates" in msgs[2]["content"]
    assert second.images == first.images  # the image is sent again with the conversation
    assert len(answer.request["messages"]) == 3


@pytest.mark.asyncio
@pytest.mark.parametrize(("first", "mode"), [("{not json", "none"),
                                             ('{"label": "rice_cake"}', "json_schema")])
async def test_two_bad_answers_give_invalid_answer_never_a_label(fake, jpeg, first, mode):
    fake.script(Reply(content=first), Reply(content="It is a delicious rice cake."))
    answer = await ask(vlm_config(fake.base_url, structured_output=mode), jpeg)
    assert answer.status == "invalid_answer" and answer.label is None
    assert answer.structured_output == mode
    assert answer.raw == "It is a delicious rice cake." and answer.attempts == 2
    assert len(fake.requests) == 2  # exactly one corrective retry


@pytest.mark.asyncio
async def test_429_retry_after_seconds_is_honoured(fake, jpeg):
    fake.script(Reply.error(429, "slow down", retry_after=1))
    started = time.monotonic()
    answer = await ask(vlm_config(fake.base_url), jpeg)
    waited = time.monotonic() - started
    print(f"\n429 with Retry-After: 1 -> answer after {waited:.3f} s")
    assert answer.status == "ok" and answer.outcomes == ("429", "200")
    assert 0.9 <= waited < 10  # honoured (the backoff alone is <= 0.05 s here)


@pytest.mark.asyncio
async def test_retry_after_http_date_and_cap(fake, jpeg):
    sleep = RecordedSleep()
    later = email.utils.formatdate(time.time() + 3, usegmt=True)
    fake.script(Reply.error(503, retry_after=later), Reply.error(429, retry_after=3600))
    cfg = vlm_config(fake.base_url, retry_after_cap_s=2.0)
    answer = await ask(cfg, jpeg, sleep=sleep)
    assert answer.status == "ok" and answer.attempts == 3
    print(f"\nrecorded waits for Retry-After <date +3 s>, 3600: {sleep.delays}")
    assert 1.0 <= sleep.delays[0] <= 2.0  # ~3 s away, capped at 2
    assert sleep.delays[1] == 2.0  # an hour, capped


@pytest.mark.asyncio
async def test_5xx_are_retried_with_capped_backoff_then_succeed(fake, jpeg):
    sleep = RecordedSleep()
    fake.script(Reply.error(500), Reply.error(502), Reply.error(503), Reply.error(504))
    cfg = vlm_config(fake.base_url, max_retries=4, backoff_base_s=1.0, backoff_cap_s=3.0)
    answer = await ask(cfg, jpeg, sleep=sleep)
    assert answer.status == "ok" and answer.outcomes == ("500", "502", "503", "504", "200")
    assert len(answer.latency_s) == 5 and len(fake.requests) == 5
    bounds = [(0.5, 1.0), (1.0, 2.0), (1.5, 3.0), (1.5, 3.0)]  # 1, 2, 4->3, 8->3, jittered
    assert all(lo <= d <= hi for d, (lo, hi) in zip(sleep.delays, bounds, strict=True))


@pytest.mark.asyncio
@pytest.mark.parametrize("status", [408, 409, 429, 500, 503])
async def test_retryable_statuses_run_out_as_unavailable(fake, jpeg, status):
    fake.script(*[Reply.error(status, "busy")] * 3)
    with pytest.raises(VLMServerError) as err:
        await ask(vlm_config(fake.base_url, max_retries=2), jpeg)
    assert err.value.status == status and "busy" in str(err.value)
    assert isinstance(err.value, VLMUnavailableError) and isinstance(err.value, EdgeError)
    assert len(fake.requests) == 3


@pytest.mark.asyncio
@pytest.mark.parametrize("status", [400, 401, 403, 404, 413, 422])
async def test_client_errors_are_never_retried(jpeg, status):
    server = FakeVLM(model=MODEL, api_key="the-right-key",
                     max_request_bytes=2_000 if status == 413 else 20_000_000)
    cfg = dict(api_key_env="", api_key_file=None)
    async with server as fake:
        if status == 401:
            cfg["api_key_env"] = "VTZERO_TEST_WRONG_KEY"
        elif status == 404:
            cfg["model"] = "no-such-model"
        if status in (400, 403, 422):
            fake.script(Reply.error(status, f"scripted {status}"))
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("VTZERO_TEST_WRONG_KEY", "a-wrong-key")
            mp.setenv("VTZERO_TEST_KEY", "the-right-key")
            if status != 401:
                cfg["api_key_env"] = "VTZERO_TEST_KEY"
            with pytest.raises(VLMRejectedError) as err:
                await ask(vlm_config(fake.base_url, **cfg), image_bytes(200, 200, noise=True))
        assert err.value.status == status and f"HTTP {status}" in str(err.value)
        assert not isinstance(err.value, VLMUnavailableError)
        assert len(fake.requests) == 1, "never retried"
        print(f"\n{status}: {err.value}")


@pytest.mark.asyncio
async def test_timeouts_are_retried_then_raise_timeout_error(fake, jpeg):
    fake.script(Reply(delay_s=10), Reply(delay_s=10))
    cfg = vlm_config(fake.base_url, connect_timeout_s=0.2, total_timeout_s=0.3,
                      max_retries=1)
    started = time.monotonic()
    with pytest.raises(VLMTimeoutError) as err:
        await ask(cfg, jpeg)
    took = time.monotonic() - started
    print(f"\n2 attempts x total_timeout_s=0.3 -> VLMTimeoutError after {took:.2f} s")
    assert isinstance(err.value, TimeoutError) and isinstance(err.value, VLMUnavailableError)
    assert "total_timeout_s=0.3" in str(err.value)
    assert took < 5 and len(fake.requests) == 2


@pytest.mark.asyncio
async def test_a_trickling_body_times_out(fake, jpeg):
    fake.script(Reply(chunk_delay_s=0.1, chunk_bytes=4))  # ~250 bytes over ~6 s
    cfg = vlm_config(fake.base_url, connect_timeout_s=0.3, total_timeout_s=0.6,
                      max_retries=0)
    started = time.monotonic()
    with pytest.raises(VLMTimeoutError):
        await ask(cfg, jpeg)
    assert time.monotonic() - started < 5


@pytest.mark.asyncio
async def test_non_json_body_is_refused_clearly(fake, jpeg):
    fake.script(Reply(body=b"<html><body>502 Bad Gateway</body></html>"))
    with pytest.raises(VLMResponseError, match="not JSON: '<html><body>502 Bad Gateway"):
        await ask(vlm_config(fake.base_url), jpeg)
    assert len(fake.requests) == 1


@pytest.mark.asyncio
async def test_json_without_choices_is_refused_clearly(fake, jpeg):
    fake.script(Reply(body=json.dumps({"error": "model is loading"}).encode()))
    with pytest.raises(VLMResponseError, match=r"no choices.*model is loading"):
        await ask(vlm_config(fake.base_url), jpeg)


@pytest.mark.asyncio
@pytest.mark.parametrize("chunked", [False, True])
async def test_huge_answer_is_refused(fake, jpeg, chunked):
    fake.script(Reply.huge(8_000_000, chunked=chunked))
    cfg = vlm_config(fake.base_url, max_response_bytes=65_536)
    started = time.monotonic()
    with pytest.raises(VLMResponseTooLargeError, match="max_response_bytes=65536"):
        await ask(cfg, jpeg)
    print(f"\n8 MB answer (chunked={chunked}) refused in {time.monotonic() - started:.3f} s")
    assert len(fake.requests) == 1


@pytest.mark.asyncio
async def test_connection_refused_is_retried_then_raises(jpeg):
    port = free_port()  # nothing listens there
    sleep = RecordedSleep()
    with pytest.raises(VLMConnectionError) as err:
        await ask(vlm_config(f"http://127.0.0.1:{port}/v1", max_retries=2), jpeg,
                  sleep=sleep)
    assert isinstance(err.value, ConnectionError) and isinstance(err.value, VLMError)
    assert len(sleep.delays) == 2
    print(f"\nrefused: {err.value}")


@pytest.mark.asyncio
async def test_dropped_connection_is_retried(fake, jpeg):
    fake.script(Reply.dropped())
    answer = await ask(vlm_config(fake.base_url), jpeg)
    assert answer.status == "ok" and answer.outcomes == ("connection", "200")


@pytest.mark.asyncio
async def test_api_key_never_leaks(monkeypatch, caplog, tmp_path, jpeg):
    planted = "sk-PLANTED-secret-0123456789abcdef"
    caplog.set_level(logging.DEBUG)
    monkeypatch.setenv("VTZERO_VLM_API_KEY", planted)
    seen = []
    # 1. A careless server that quotes the (wrong) key in its 401.
    async with FakeVLM(model=MODEL, api_key="another-key", echo_key_in_errors=True) as fake:
        vlm = OpenAIVLM(vlm_config(fake.base_url))
        seen.append(repr(vlm))
        with pytest.raises(VLMRejectedError) as err:
            await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
        await vlm.close()
        assert fake.requests[0].headers["Authorization"] == f"Bearer {planted}"
        assert planted in fake.requests[0].error  # the server did quote it...
        seen += [str(err.value), repr(err.value), err.value.excerpt, repr(err.value.args)]
        assert "<redacted>" in str(err.value)  # ...and the client redacted it
    # 2. The right key, a server that echoes it in the answer (taken for ignoring both JSON
    # modes, then in free text and the corrective retry); from a key file.
    key_file = tmp_path / "vlm.key"
    key_file.write_text(planted + "\n")
    key_file.chmod(0o644)
    async with FakeVLM(model=MODEL, api_key=planted) as fake:
        fake.script(*[Reply(content=f"my key is {planted}")] * 3, Reply(content=planted))
        cfg = vlm_config(fake.base_url, api_key_env="", api_key_file=key_file)
        answer = await ask(cfg, jpeg)
        assert (answer.status, answer.attempts) == ("invalid_answer", 4)
        assert caplog.text.count("ignored structured output") == 2
        seen.append(json.dumps(answer.to_dict()))
        seen.append(repr(answer))
    assert "readable by group or others" in caplog.text
    # 3. Timeouts and refused connections.
    port = free_port()  # nothing listens there
    with pytest.raises(VLMConnectionError) as err:
        await ask(vlm_config(f"http://127.0.0.1:{port}/v1", max_retries=0), jpeg)
    seen += [str(err.value), repr(err.value)]
    # Everything logged on this side (the fake server is the careless other side).
    ours = [r for r in caplog.records if r.name != "edge.sim.fake_vlm"]
    assert any(r.name == "edge.vlm.client" for r in ours)
    seen += [logging.Formatter().format(r) for r in ours]
    for text in seen:
        assert planted not in text


@pytest.mark.asyncio
async def test_api_key_file_problems_are_config_errors(tmp_path, fake):
    empty = tmp_path / "empty.key"
    empty.write_text("\n")
    with pytest.raises(ConfigError, match="empty"):
        OpenAIVLM(vlm_config(fake.base_url, api_key_file=empty))
    with pytest.raises(ConfigError, match="cannot be read"):
        OpenAIVLM(vlm_config(fake.base_url, api_key_file=tmp_path / "missing.key"))
    bad = tmp_path / "bad.key"
    bad.write_text("sk-two words")
    with pytest.raises(ConfigError, match="not allowed in a header") as err:
        OpenAIVLM(vlm_config(fake.base_url, api_key_file=bad))
    assert "two words" not in str(err.value)


@pytest.mark.asyncio
async def test_large_image_is_shrunk_before_sending(fake):
    big = image_bytes(3000, 2000, noise=True)
    answer = await ask(vlm_config(fake.base_url, max_image_side_px=512,
                                   max_image_bytes=60_000), big)
    sent = Image.open(io.BytesIO(fake.requests[0].images[0]))
    assert sent.format == "JPEG" and max(sent.size) <= 512
    assert len(fake.requests[0].images[0]) <= 60_000
    assert answer.image["reencoded"] and answer.image["source_bytes"] == len(big)
    print(f"\nimage {len(big)} B 3000x2000 sent as {answer.image['bytes']} B "
          f"{sent.size[0]}x{sent.size[1]}; ask took {answer.elapsed_s:.3f} s")


@pytest.mark.asyncio
async def test_non_image_is_refused_before_any_request(fake):
    with pytest.raises(ImageError, match="not a JPEG or PNG"):
        await ask(vlm_config(fake.base_url), b"%PDF-1.7 not a photo")
    with pytest.raises(ImageError, match="needs an image"):
        await ask(vlm_config(fake.base_url), None)
    assert fake.requests == []


@pytest.mark.asyncio
async def test_tactile_only_sends_no_image_and_vision_only_no_description(fake, jpeg):
    answer = await ask(vlm_config(fake.base_url, mode="tactile_only"), jpeg)
    [req] = fake.requests
    assert req.images == [] and isinstance(req.body["messages"][0]["content"], str)
    assert answer.image is None and DESCRIPTION in answer.prompt
    await ask(vlm_config(fake.base_url, mode="vision_only"), jpeg)
    assert len(fake.requests[1].images) == 1 and DESCRIPTION not in fake.requests[1].prompt


@pytest.mark.asyncio
async def test_fake_can_choose_from_the_tactile_description(jpeg):
    async with FakeVLM(model=MODEL, choose=choose_by_description) as fake:
        answer = await ask(vlm_config(fake.base_url), jpeg,
                           candidates=["stainless_cube", "wood_cube", "sponge_cube"],
                           description="wood cube")
    assert answer.label == "wood_cube"


@pytest.mark.asyncio
async def test_concurrent_asks_share_one_client(fake):
    async with OpenAIVLM(vlm_config(fake.base_url)) as vlm:
        answers = await asyncio.gather(*[
            vlm.ask(image_bytes(seed=i, noise=True), DESCRIPTION, CANDIDATES)
            for i in range(8)])
    assert all(a.status == "ok" for a in answers) and len(fake.requests) == 8


@pytest.mark.asyncio
async def test_no_vlm_gives_the_prompt_it_would_send(jpeg):
    client = make_vlm(VLMConfig())
    assert isinstance(client, NoVLM) and isinstance(client, VLMClient)
    answer = await client.ask(jpeg, DESCRIPTION, CANDIDATES)
    assert isinstance(answer, VLMAnswer)
    assert answer.status == "not_configured" and answer.label is None
    assert answer.prompt == load_template("vision_tactile").render(DESCRIPTION, CANDIDATES)
    assert answer.attempts == 0 and answer.request is None
    await client.close()
    vision_only = await NoVLM(mode="vision_only").ask(None, DESCRIPTION, CANDIDATES)
    assert DESCRIPTION not in vision_only.prompt


@pytest.mark.asyncio
async def test_make_vlm_and_repr(fake):
    client = make_vlm(vlm_config(fake.base_url))
    assert isinstance(client, OpenAIVLM) and isinstance(client, VLMClient)
    assert repr(client) == (f"OpenAIVLM(url='{fake.base_url}/chat/completions', "
                            f"model='{MODEL}', mode='vision_tactile', api_key=none)")
    await client.close()
    with pytest.raises(ConfigError, match="no VLM configured"):
        OpenAIVLM(VLMConfig())


@pytest.mark.asyncio
async def test_image_work_goes_to_the_offload_and_arrives_whole(fake):
    """The image is prepared where ``offload`` runs CPU work (the daemon: its compute
    process), and its data URL is spliced into the JSON body byte for byte."""
    calls = []

    async def offload(fn, *args):
        calls.append(fn.__name__)
        return await asyncio.to_thread(fn, *args)

    big = image_bytes(2000, 1500, noise=True)
    answer = await ask(vlm_config(fake.base_url), big, offload=offload)
    assert calls == ["prepare_for_vlm"] and answer.status == "ok"
    [req] = fake.requests
    assert req.error is None
    sent = req.images[0]
    assert sent != big and answer.image["sha256"] == hashlib.sha256(sent).hexdigest()
    assert Image.open(io.BytesIO(sent)).size == (answer.image["width"], answer.image["height"])
    # Stored: the request with the image named, never its bytes.
    stored = json.dumps(answer.request)
    assert "base64" not in stored and answer.image["sha256"] in stored


def test_json_body_splices_the_data_url_where_its_placeholder_stands():
    body = {"messages": [{"content": [{"text": "a \"quoted\" prompt"},
                                      {"image_url": {"url": "<elided sha256:ab>"}}]}]}
    payload = encode_json(body, ("<elided sha256:ab>", b"data:image/png;base64,QUJD"))
    assert json.loads(payload)["messages"][0]["content"][1]["image_url"]["url"] == (
        "data:image/png;base64,QUJD")
    assert json.loads(payload)["messages"][0]["content"][0]["text"] == 'a "quoted" prompt'
    with pytest.raises(AssertionError, match="placeholder"):
        encode_json(body, ("<other>", b"data:"))
