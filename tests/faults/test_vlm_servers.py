"""The daemon with VLM servers that are not OpenAI: one refusing ``response_format`` (the
fallback), one ignoring it and answering prose (never a wrong label), a failing one whose
episodes are asked again (``POST /v1/episodes/{id}/retry``, ``vt-edge episodes retry``), and
a wrong URL (``/healthz`` and ``/metrics`` say so). Every recognition presses the emulated
robot through the real drivers."""

from __future__ import annotations

import asyncio
import os
import re
import sys
from dataclasses import replace

import pytest

from edge.core.errors import EdgeError, NotFoundError
from edge.ops.doctor import Level, _check_vlm, _vlm_client
from edge.ops.episode_retry import run_retry
from edge.sim.fake_vlm import FakeVLM, Reply
from edge.sim.robot import SimRobot
from edge.vlm.transport import UNREACHABLE_AFTER_ATTEMPTS
from tests.support.daemon import (
    FOOD,
    QUICK_OBJECT,
    ROOT,
    Daemon,
    base_config,
    fast_config,
    recognize,
    sim_daemon,
    wait_health,
)
from tests.support.waits import free_port

pytestmark = pytest.mark.asyncio
OBJECT = QUICK_OBJECT


def truth(_req) -> str:
    return OBJECT


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


NEGATION = "This is not a real macaron; it is a resin replica."


async def test_a_server_ignoring_response_format_never_turns_prose_into_a_label(tmp_path):
    """Takes response_format without looking and answers the negation to everything: doctor's
    probe says, before any press, that recognitions would end invalid_answer; 8 of 8 do (none
    macaron), each recording the mode that answered (free text) and the text it gave."""
    assert "macaron" in FOOD
    async with FakeVLM(choose=truth, structured="ignored", prose=NEGATION) as fake:
        cfg = fast_config(fake.base_url)
        vlm, _ = _vlm_client(cfg)
        assert vlm is not None
        async with vlm:
            *_, probe = await _check_vlm(vlm, [])
        print(f"doctor: {probe.level} {probe.part}: {probe.found} -> {probe.fix}")
        assert (probe.part, probe.level) == ("vlm probe", Level.WARN)
        assert "recognitions would end invalid_answer" in probe.found
        assert NEGATION in probe.found and "json_schema ignored" in probe.found
        assert probe.data["structured_output"] == "none" and probe.data["label"] is None
        probed = len(fake.chat_requests)
        async with sim_daemon(tmp_path, OBJECT, cfg=cfg) as (_robot, d):
            episodes = [await recognize(d) for _ in range(8)]
            answers = await metric(d, 'vtzero_vlm_answers_total{structured_output="none"}')
        outcomes = [ep["vlm"]["outcomes"] for ep in episodes]
        print(f"{len(episodes)} recognitions: {[ep['status'] for ep in episodes]}, "
              f"outcomes {outcomes}")
        for ep in episodes:
            assert (ep["status"], ep["label"]) == ("invalid_answer", None), ep["id"]
            assert ep["structured_output"] == ep["vlm"]["structured_output"] == "none"
            assert ep["vlm"]["raw"] == NEGATION
            assert "response_format" not in ep["vlm"]["request"]
        # The first asked both JSON modes in vain; every one got its corrective retry.
        assert outcomes == [["200"] * 4] + [["200"] * 2] * 7
        assert answers == 8 and len(fake.chat_requests) == probed + 4 + 7 * 2


async def test_failed_episodes_are_asked_again_by_route_and_command(tmp_path):
    state = tmp_path / "state"
    async with FakeVLM(choose=truth) as fake, \
            SimRobot(OBJECT, seed=7, cfg=base_config()) as robot:
        # Made by real recognitions against a failing server, by an earlier run of the
        # daemon: a refusal and two answers outside the candidates.
        async with Daemon(robot, fast_config(fake.base_url), state) as d:
            fake.script(Reply.error(403, "this key may not use fake-vlm"))
            refused = await recognize(d)
            fake.script(Reply(label="a_brick"), Reply(label="still_a_brick"))
            invalid = await recognize(d)
        assert (refused["status"], invalid["status"]) == ("vlm_error", "invalid_answer")
        async with Daemon(robot, fast_config(fake.base_url), state) as d:
            await asyncio.sleep(0.3)  # longer than the retry period: not asked by itself
            assert len(fake.chat_requests) == 3

            # The command, through the daemon (its own process, as a person runs it): the
            # old vlm_error episode's stored description and photo asked again.
            config = tmp_path / "robot.toml"
            config.write_text(f'[runtime]\nstate_dir = "{state}"\n')
            status, ep = await d.get(f"/v1/episodes/{refused['id']}")
            assert ep["status"] == "vlm_error" and "HTTP 403" in ep["last_error"]
            rc, out, err = await vt_edge("episodes", "--config", str(config), "retry",
                                         refused["id"], "--url", d.url)
            print(out, err[-300:])
            assert rc == 0 and out.startswith(f"{refused['id']}  done") and OBJECT in out
            ep = d.store.get(refused["id"])
            assert ep.status == "done" and ep.label == OBJECT
            assert ep.structured_output == "json_schema"
            asked = fake.chat_requests[-1]
            assert asked.description == refused["description"] and asked.candidates == FOOD
            assert asked.images and asked.images[0][:2] == b"\xff\xd8"
            # The route, as the command's --all-failed asks it: the invalid_answer one.
            status, ep = await d.post(f"/v1/episodes/{invalid['id']}/retry", {})
            assert status == 200 and ep["status"] == "done" and ep["label"] == OBJECT, ep
            # Refused in one line: a done episode, an unknown one; nothing left to ask.
            status, body = await d.post(f"/v1/episodes/{refused['id']}/retry", {})
            assert status == 409 and body["error"] == (
                f"episode {refused['id']} is done: only vlm_error or invalid_answer "
                "episodes are asked again")
            status, body = await d.post("/v1/episodes/20990101T000000Z-deadbeef/retry", {})
            assert status == 404
            rc, out, err = await vt_edge("episodes", "--config", str(config), "retry",
                                         invalid["id"], "--url", d.url)
            (line,) = [x for x in err.splitlines() if "ERROR" in x]
            assert rc == 2 and line.endswith(f"episode {invalid['id']} is done: only "
                                             "vlm_error or invalid_answer episodes are asked "
                                             "again")
            lines: list[str] = []
            assert await asyncio.to_thread(run_retry, d.cfg, d.store, None, True, d.url,
                                           lines.append) == 0
            assert lines == ["no vlm_error or invalid_answer episodes to ask again"]
            with pytest.raises(NotFoundError, match="no episode 'nope'"):
                await asyncio.to_thread(run_retry, d.cfg, d.store, "nope", False, d.url)
    url = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(EdgeError, match=f"no daemon answers at {url}"):
        run_retry(d.cfg, d.store, invalid["id"], False, url)


async def vt_edge(*args: str) -> tuple[int, str, str]:
    """``vt-edge ARGS`` in a process of its own: (exit status, stdout, stderr)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "edge", *args, cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    return proc.returncode, out.decode(), err.decode()


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
