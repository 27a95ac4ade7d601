"""VLM faults through the real daemon: every recognition presses the emulated robot, then
the fake OpenAI-compatible server misbehaves. The episode must end ``pending`` (asked again
later), ``vlm_error`` (asking again will not help) or ``invalid_answer``, and is never given
a label the VLM did not give as one of the candidates."""

from __future__ import annotations

import asyncio
from dataclasses import replace
from typing import Any

import pytest

from edge.sim.fake_vlm import FakeVLM, Reply
from tests.support.daemon import (
    QUICK_OBJECT,
    fast_config,
    gripper_open,
    recognize,
    recording_events,
    sim_daemon,
    store_consistent,
)
from tests.support.waits import wait_until

pytestmark = pytest.mark.asyncio
OBJECT = QUICK_OBJECT


def truth(_req) -> str:
    return OBJECT


def vlm_config(url: str, **vlm: Any):
    cfg = fast_config(url)
    return replace(cfg, vlm=replace(cfg.vlm, **vlm))


def labels_given(events: list[dict]) -> set:
    return {e.get("label") for e in events if e.get("type") == "result"} - {None}


async def result_event(events: list[dict], episode_id: str, timeout_s: float = 5.0) -> dict:
    """The episode's ``result`` event. It is published once the store update is durable, so
    a poll of GET /v1/episodes can see the final status a moment before it arrives."""
    return await wait_until(
        lambda: next((e for e in events if e.get("type") == "result"
                      and e.get("episode") == episode_id), None),
        timeout_s, f"a result event for {episode_id} among {events}")


# (name, scripted replies, [vlm] overrides, how the first answer ends, words in its error)
TRANSIENT = [
    ("500 twice", [Reply.error(500, "upstream exploded"), Reply.error(503)], {}, "HTTP 50"),
    ("dropped connection", [Reply.dropped()], {}, "connection"),
    ("timeout", [Reply(delay_s=2.5)], {"total_timeout_s": 1.0}, "total_timeout_s"),
    ("slow body", [Reply(chunk_delay_s=0.1, chunk_bytes=16)], {"total_timeout_s": 1.0},
     "total_timeout_s"),
]


@pytest.mark.parametrize(("name", "replies", "vlm", "words"), TRANSIENT,
                         ids=[t[0] for t in TRANSIENT])
async def test_transient_vlm_failure_waits_pending_then_completes(tmp_path, name, replies,
                                                                  vlm, words):
    async with FakeVLM(choose=truth) as fake:
        fake.script(*replies)
        async with sim_daemon(tmp_path, OBJECT, cfg=vlm_config(fake.base_url, **vlm)) as \
                (robot, d), recording_events(d) as events:
            first = await recognize(d)
            # The user: pending, why, and when it is asked again; no label.
            print(f"{name}: {first['status']}: {first.get('last_error')}")
            assert first["status"] == "pending" and first.get("label") is None
            assert words in first["last_error"] and first["next_retry_at"] > first["created"]
            assert gripper_open(robot)
            status, _ = await d.get("/healthz")
            assert status == 200  # a VLM outage is not the robot's health
            # Retried by the daemon (every 0.2 s here) until the server answers.
            done = await d.wait_status(first["id"], {"done", "vlm_error", "invalid_answer"})
            assert done["status"] == "done" and done["label"] == OBJECT
            assert done["attempts"] == len(replies) + 1
            assert len(fake.chat_requests) == done["attempts"]  # never asked twice at once
            assert (await result_event(events, done["id"]))["label"] == OBJECT
            assert labels_given(events) == {OBJECT}
            pending = [e for e in events if e.get("status") == "pending"]
            assert len(pending) == len(replies) and all(words in e["error"] for e in pending)
            (kept,) = store_consistent(d.store.root)
            assert kept["label"] == OBJECT


async def test_vlm_refusing_connections_keeps_the_episode_pending(tmp_path):
    async with FakeVLM() as probe:
        url, port = probe.base_url, probe.port  # nothing listens there any more
    cfg = vlm_config(url)
    # Retries 0.1, 0.2, 0.4 s... apart, at most 30 s: the schedule, not the cap, must rule.
    cfg = replace(cfg, runtime=replace(cfg.runtime, vlm_retry_base_s=0.1,
                                       vlm_retry_max_s=30.0))
    async with sim_daemon(tmp_path, OBJECT, cfg=cfg) as (_robot, d):
        first = await recognize(d)
        print("refused:", first["last_error"])
        assert first["status"] == "pending" and first.get("label") is None
        assert "connection" in first["last_error"]
        await asyncio.sleep(0.5)  # retried (and refused) meanwhile: still pending
        again = (await d.get(f"/v1/episodes/{first['id']}"))[1]
        assert again["status"] == "pending" and again["attempts"] >= 2
        async with FakeVLM(port=port, choose=truth):
            done = await d.wait_status(first["id"], {"done"})
        assert done["label"] == OBJECT


async def test_429_retry_after_is_honoured(tmp_path):
    async with FakeVLM(choose=truth) as fake:
        fake.script(Reply.error(429, "slow down", retry_after=1))
        cfg = vlm_config(fake.base_url, max_retries=1, backoff_base_s=0.01,
                         backoff_cap_s=0.02)
        async with sim_daemon(tmp_path, OBJECT, cfg=cfg) as (_robot, d):
            ep = await recognize(d)
    vlm = ep["vlm"]
    print(f"429 then 200: outcomes {vlm['outcomes']}, answered after {vlm['elapsed_s']:.2f} s")
    assert ep["status"] == "done" and ep["label"] == OBJECT
    assert vlm["outcomes"] == ["429", "200"] and vlm["elapsed_s"] >= 1.0


@pytest.mark.parametrize(("name", "reply", "words"), [
    ("non-JSON body", Reply(body=b"<html><body>502 Bad Gateway</body></html>"), "not JSON"),
    ("huge answer", Reply.huge(3_000_000), "max_response_bytes"),
    ("huge chunked answer", Reply.huge(3_000_000, chunked=True), "max_response_bytes"),
], ids=["non-json", "huge", "huge-chunked"])
async def test_broken_answers_end_vlm_error_without_a_label(tmp_path, name, reply, words):
    async with FakeVLM(choose=truth) as fake:
        fake.script(reply)
        async with sim_daemon(tmp_path, OBJECT, cfg=vlm_config(fake.base_url)) as (_robot, d):
            ep = await recognize(d)
            print(f"{name}: {ep['status']}: {ep.get('last_error')}")
            assert ep["status"] == "vlm_error" and ep.get("label") is None
            assert words in ep["last_error"] and len(ep["last_error"]) < 600
            await asyncio.sleep(0.3)  # longer than the retry period: not asked again
            assert len(fake.chat_requests) == 1
            assert (await d.get(f"/v1/episodes/{ep['id']}"))[1]["status"] == "vlm_error"
            (kept,) = store_consistent(d.store.root)
            assert kept.get("label") is None


async def test_labels_outside_the_candidates_end_invalid_answer(tmp_path):
    async with FakeVLM(choose=truth) as fake:
        fake.script(Reply(label="a_brick"), Reply(content="It is clearly a brick."))
        async with sim_daemon(tmp_path, OBJECT, cfg=vlm_config(fake.base_url)) as \
                (_robot, d), recording_events(d) as events:
            ep = await recognize(d)
            assert ep["status"] == "invalid_answer" and ep["label"] is None
            assert ep["vlm"]["outcomes"] == ["200", "200"]  # one corrective retry
            assert "brick" in ep["vlm"]["raw"]
            assert (await result_event(events, ep["id"]))["status"] == "invalid_answer"
            assert labels_given(events) == set()
            # A corrected answer is taken (the case/spacing mapping is unit-tested in
            # tests/vlm); it is the VLM's, not a guess.
            fake.script(Reply(label="melon"), Reply(label=OBJECT))
            corrected = await recognize(d)
    assert corrected["status"] == "done" and corrected["label"] == OBJECT
    assert corrected["vlm"]["outcomes"] == ["200", "200"]
