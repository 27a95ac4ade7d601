"""The daemon with VLM servers that are not OpenAI: one refusing ``response_format`` (the
fallback), a failing one whose episodes are asked again (``POST /v1/episodes/{id}/retry``,
``vt-edge episodes retry``), and a wrong URL (``/healthz`` and ``/metrics`` say so). Every
recognition presses the emulated robot through the real drivers."""

from __future__ import annotations

import asyncio
import re
from dataclasses import replace

import pytest

from edge.cli import main as cli_main
from edge.core.errors import NotFoundError, StateError
from edge.core.vlm import UNREACHABLE_AFTER_ATTEMPTS
from edge.sim.fake_vlm import FakeVLM, Reply
from edge.tools.episode_retry import run_retry
from tests.support.daemon import FOOD, QUICK_OBJECT, fast_config, sim_daemon, wait_health
from tests.support.waits import free_port

pytestmark = pytest.mark.asyncio
OBJECT = QUICK_OBJECT


def truth(_req) -> str:
    return OBJECT


async def recognize(d) -> dict:
    status, ep = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
    assert status == 200 and ep["press"]["contact"], ep
    return ep


async def metric(d, name: str) -> float:
    async with d.http.get(d.url + "/metrics") as resp:
        text = await resp.text()
    m = re.search(rf"^{re.escape(name)} (\S+)$", text, re.M)
    assert m, f"{name} not in /metrics"
    return float(m.group(1))


async def test_a_server_refusing_response_format_still_recognises(tmp_path):
    """Fake (a): every response_format refused with vLLM's 400. Recognitions end done with a
    candidate; the episode and /metrics say which structured mode answered."""
    async with FakeVLM(choose=truth, structured="none_only") as fake, \
            sim_daemon(tmp_path, OBJECT, cfg=fast_config(fake.base_url)) as (_robot, d):
        first = await recognize(d)
        second = await recognize(d)
        for ep in (first, second):
            print(f"{ep['id']}: {ep['status']} {ep['label']} via {ep['structured_output']}, "
                  f"outcomes {ep['vlm']['outcomes']}")
            assert ep["status"] == "done" and ep["label"] in FOOD and ep["label"] == OBJECT
            assert ep["structured_output"] == "none"
            assert ep["vlm"]["structured_output"] == "none"
            assert "response_format" not in ep["vlm"]["request"]
        assert first["vlm"]["outcomes"] == ["400", "400", "200"]
        assert second["vlm"]["outcomes"] == ["200"]  # remembered for the daemon's client
        assert await metric(d, 'vtzero_vlm_answers_total{structured_output="none"}') == 2
        assert await metric(d, "vtzero_vlm_reachable") == 1
        stored = d.store.get(first["id"])
        assert stored.structured_output == "none"
    assert [r.status for r in fake.chat_requests] == [400, 400, 200, 200]


async def test_failed_episodes_are_asked_again_by_route_and_command(tmp_path):
    async with FakeVLM(choose=truth) as fake, \
            sim_daemon(tmp_path / "state", OBJECT, cfg=fast_config(fake.base_url)) as \
            (_robot, d):
        # Made by real recognitions against a failing server: a refusal and two answers
        # outside the candidates.
        fake.script(Reply.error(403, "this key may not use fake-vlm"))
        refused = await recognize(d)
        fake.script(Reply(label="a_brick"), Reply(label="still_a_brick"))
        invalid = await recognize(d)
        assert (refused["status"], invalid["status"]) == ("vlm_error", "invalid_answer")
        await asyncio.sleep(0.3)  # longer than the retry period: not asked by the daemon
        assert len(fake.chat_requests) == 3

        # The route: the stored description and photo asked again, now answered.
        status, ep = await d.post(f"/v1/episodes/{refused['id']}/retry", {})
        assert status == 200 and ep["status"] == "done" and ep["label"] == OBJECT, ep
        asked = fake.chat_requests[-1]
        assert asked.description == refused["description"] and asked.candidates == FOOD
        assert asked.images and asked.images[0][:2] == b"\xff\xd8"
        # Refused in one line: a done episode, an unknown one.
        status, body = await d.post(f"/v1/episodes/{refused['id']}/retry", {})
        assert status == 409 and body["error"] == (
            f"episode {refused['id']} is done: only vlm_error or invalid_answer episodes "
            "are asked again")
        status, body = await d.post("/v1/episodes/20990101T000000Z-deadbeef/retry", {})
        assert status == 404

        # The command, through the daemon (a thread: the daemon runs on this loop).
        config = tmp_path / "robot.toml"
        config.write_text(f'[runtime]\nstate_dir = "{tmp_path / "state"}"\n')
        lines: list[str] = []
        rc = await asyncio.to_thread(run_retry, d.cfg, d.store, None, True, d.url,
                                     lines.append)
        print("\n".join(lines))
        assert rc == 0 and len(lines) == 1
        assert lines[0].startswith(f"{invalid['id']}  done") and OBJECT in lines[0]
        assert d.store.get(invalid["id"]).status == "done"
        rc = await asyncio.to_thread(cli_main, ["episodes", "--config", str(config), "retry",
                                                "--all-failed", "--url", d.url])
        assert rc == 0  # none left
        with pytest.raises(StateError, match="is done: only vlm_error"):
            await asyncio.to_thread(run_retry, d.cfg, d.store, invalid["id"], False, d.url)
        with pytest.raises(NotFoundError, match="no episode 'nope'"):
            await asyncio.to_thread(run_retry, d.cfg, d.store, "nope", False, d.url)
        rc = await asyncio.to_thread(cli_main, ["episodes", "--config", str(config), "retry",
                                                invalid["id"], "--url", d.url])
        assert rc == 2
    rc = cli_main(["episodes", "--config", str(config), "retry", invalid["id"],
                   "--url", f"http://127.0.0.1:{free_port()}"])
    assert rc == 2  # no daemon: said in one line


async def test_a_wrong_vlm_url_shows_on_healthz_and_metrics_until_it_answers(tmp_path):
    port = free_port()
    url = f"http://127.0.0.1:{port}/v1"
    cfg = fast_config(url)
    cfg = replace(cfg, runtime=replace(cfg.runtime, vlm_retry_base_s=0.05,
                                       vlm_retry_max_s=0.2))
    async with sim_daemon(tmp_path, OBJECT, cfg=cfg) as (_robot, d):
        assert (await wait_health(d, True))["vlm_error"] is None
        ep = await recognize(d)
        assert ep["status"] == "pending"
        health = await wait_health(d, False)
        print("healthz:", health["vlm_error"])
        assert health["vlm_error"].startswith(f"VLM at {url} unreachable: "
                                              f"{UNREACHABLE_AFTER_ATTEMPTS} attempts")
        assert health["sensor_fresh"] and health["bus_error"] is None
        assert await metric(d, "vtzero_vlm_reachable") == 0
        async with FakeVLM(port=port, choose=truth):
            done = await d.wait_status(ep["id"], {"done"})
            assert done["label"] == OBJECT
            assert (await wait_health(d, True))["vlm_error"] is None
            assert await metric(d, "vtzero_vlm_reachable") == 1
