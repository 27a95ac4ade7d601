"""The fake server itself: it refuses what a real server (or our contract) would refuse."""

import asyncio
import base64
import copy
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import aiohttp
import pytest

from edge.sim.fake_vlm import FakeVLM, plain_reason
from edge.vlm.chat import response_format
from edge.vlm.prompt import format_candidates
from tests.support.waits import free_port
from tests.vlm.helpers import CANDIDATES, MODEL, image_bytes

ROOT = Path(__file__).resolve().parents[2]


def good_body() -> dict:
    url = "data:image/png;base64," + base64.b64encode(image_bytes(32, 32, "PNG")).decode()
    return {
        "model": MODEL, "temperature": 0, "seed": 0,
        "response_format": response_format(CANDIDATES),
        "messages": [{"role": "user", "content": [
            {"type": "text", "text": "Which? By touch, the object is similar to a rock."},
            {"type": "image_url", "image_url": {"url": url}}]}],
    }


def mutated(path, value):
    body = copy.deepcopy(good_body())
    *parents, last = path
    target = body
    for key in parents:
        target = target[key]
    if value is KeyError:
        del target[last]
    else:
        target[last] = value
    return body


RF = ("response_format",)
SCHEMA = (*RF, "json_schema", "schema")
IMAGE = ("messages", 0, "content", 1, "image_url", "url")


@pytest.mark.asyncio
@pytest.mark.parametrize(
    ("body", "needle"),
    [
        (mutated(("temperature",), KeyError), "temperature: required"),
        (mutated(("temperature",), 0.7), "temperature: must be 0"),
        (mutated(("model",), ""), "model: required"),
        (mutated(("messages",), []), "messages: required"),
        (mutated(("seed",), "0"), "seed: must be an integer"),
        (mutated(IMAGE, "http://example.com/cat.jpg"), "only data: URLs"),
        (mutated(IMAGE, "data:image/jpeg;base64,@@@"), "does not decode"),
        (mutated(IMAGE, "data:image/jpeg;base64," + base64.b64encode(b"hello").decode()),
         "not a decodable image"),
        (mutated(RF, KeyError), "no 'Candidates:' line"),
        (mutated(RF, {"type": "json_object"}), "must contain the word 'json'"),
        (mutated(RF, {"type": "xml"}), "response_format.type"),
        (mutated((*RF, "json_schema", "strict"), False), "strict: must be true"),
        (mutated((*SCHEMA, "properties", "label", "enum"), []), "enum"),
        (mutated((*SCHEMA, "properties", "label", "enum"), ["a", "a"]), "enum"),
        (mutated((*SCHEMA, "additionalProperties"), True), "additionalProperties"),
        (mutated((*SCHEMA, "properties"), {"label": {"type": "string", "enum": ["a"]},
                                          "reason": {"type": "string"}}),
         "only label, or reason then label"),
        (mutated((*SCHEMA, "properties"), {"reason": {"type": "integer"},
                                          "label": {"type": "string", "enum": ["a"]}}),
         "reason: must be a string property"),
        (mutated((*SCHEMA, "properties"), {"reason": {"type": "string"},
                                          "label": {"type": "string", "enum": ["a"]}}),
         "every property required in order"),
        (mutated(("messages", 0, "role"), "robot"), "role"),
        ("not json at all", "not valid JSON"),
    ],
)
async def test_malformed_requests_get_400(fake, body, needle):
    data = body if isinstance(body, str) else json.dumps(body)
    async with aiohttp.ClientSession() as session:
        async with session.post(f"{fake.base_url}/chat/completions", data=data) as resp:
            assert resp.status == 400
            error = (await resp.json())["error"]
    assert needle in error["message"]
    assert fake.requests[-1].error == error["message"] and fake.requests[-1].status == 400
    assert fake.pending == 0


@pytest.mark.asyncio
async def test_good_request_is_answered_like_openai(fake):
    async with aiohttp.ClientSession() as session:
        async with session.post(f"{fake.base_url}/chat/completions",
                                json=good_body()) as resp:
            assert resp.status == 200
            data = await resp.json()
        async with session.get(f"{fake.base_url}/models") as resp:
            models = await resp.json()
    assert data["object"] == "chat.completion" and data["model"] == MODEL
    assert json.loads(data["choices"][0]["message"]["content"]) == {"label": CANDIDATES[0]}
    assert data["usage"]["total_tokens"] > 0
    assert models["data"][0]["id"] == MODEL
    req = fake.requests[0]
    assert req.candidates == CANDIDATES and req.description == "a rock"
    assert req.image_mimes == ["image/png"]



@pytest.mark.asyncio
async def test_a_schema_with_a_reason_is_answered_with_the_reason_first(fake):
    body = good_body()
    body["response_format"] = response_format(CANDIDATES, reason=True)
    async with aiohttp.ClientSession() as session:
        async with session.post(f"{fake.base_url}/chat/completions", json=body) as resp:
            assert resp.status == 200
            content = (await resp.json())["choices"][0]["message"]["content"]
    assert content == json.dumps({"reason": plain_reason(fake.requests[0], CANDIDATES[0]),
                                  "label": CANDIDATES[0]})


@pytest.mark.asyncio
async def test_on_request_sees_each_answered_request_with_its_arrival_time():
    seen = []
    async with FakeVLM(model=MODEL, on_request=seen.append) as fake:
        async with aiohttp.ClientSession() as session:
            t0 = time.monotonic()
            for body in (good_body(), "not json"):
                data = body if isinstance(body, str) else json.dumps(body)
                async with session.post(f"{fake.base_url}/chat/completions", data=data) as r:
                    await r.read()
            t1 = time.monotonic()
    assert [r.status for r in seen] == [200, 400] and seen == fake.requests
    assert t0 <= seen[0].received_at <= seen[1].received_at <= t1

@pytest.mark.parametrize(("args", "content"), [
    ((), json.dumps({"label": CANDIDATES[1]})),
    (("--structured", "ignored", "--prose", "Not a {label}."), f"Not a {CANDIDATES[1]}."),
], ids=["json", "ignored"])
def test_standalone_server_runs_and_stops(args, content):
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with subprocess.Popen(
        [sys.executable, "-m", "edge.sim.fake_vlm", "--port", str(port), "--choose",
         f"label:{CANDIDATES[1]}", *args],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=ROOT,
    ) as proc:
        try:
            _check_standalone(proc, port, content)
        finally:
            proc.terminate()
            assert proc.wait(timeout=10) == 0


def _check_standalone(proc, port, content):
    line = proc.stdout.readline()
    assert f"http://127.0.0.1:{port}/v1" in line, line

    body = good_body()  # the candidates in the prompt too, for a server ignoring the schema
    body["messages"][0]["content"][0]["text"] += f"\nCandidates: {format_candidates(CANDIDATES)}"

    async def call():
        async with aiohttp.ClientSession() as session:
            url = f"http://127.0.0.1:{port}/v1/chat/completions"
            async with session.post(url, json=body) as resp:
                return resp.status, await resp.json()

    status, data = asyncio.run(call())
    assert status == 200
    assert data["choices"][0]["message"]["content"] == content
