"""Security of the running daemon: the bearer token off loopback, and a VLM API key that
never leaks (logs, episodes on disk, API answers, exception strings)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import subprocess
import sys
from dataclasses import replace

import pytest

from edge.core import tomledit
from edge.core.config import ApiConfig
from edge.core.errors import ConfigError, VLMError
from edge.interfaces.http.api import Api
from edge.sim.camera import render
from edge.sim.fake_vlm import FakeVLM, Reply
from edge.sim.robot import SimRobot
from tests.support.daemon import (
    FOOD,
    QUICK_OBJECT,
    ROOT,
    base_config,
    fast_config,
    joints,
    sim_daemon,
    store_consistent,
)

pytestmark = pytest.mark.asyncio
TOKEN = "vtzero-test-token-0123456789abcdef"
KEY = "sk-vtzero-PLANTED-9f8e7d6c5b4a39281706"


# --- the bearer token ----------------------------------------------------------------------

def exposed_config(**api):
    cfg = fast_config()
    return replace(cfg, api=replace(cfg.api, host="0.0.0.0", **api))


async def test_off_loopback_every_route_but_healthz_needs_the_token(tmp_path, caplog):
    caplog.set_level(logging.DEBUG)
    async with sim_daemon(tmp_path, cfg=exposed_config(token=TOKEN)) as (robot, d):
        before = joints(robot, d.cfg)
        status, health = await d.get("/healthz")  # open: a supervisor needs no secret
        assert status == 200 and health["ok"]
        wrong = [None, "Bearer", f"Bearer {TOKEN[:-1]}", f"Bearer {TOKEN}x", f"Basic {TOKEN}",
                 f"bearer{TOKEN}", TOKEN, f"Bearer  {TOKEN}"]
        routes = [("POST", "/v1/recognize"), ("GET", "/v1/episodes/20200101T000000000Z-abcdef"),
                  ("GET", "/metrics"), ("GET", "/v1/events"), ("POST", "/v1/abort"),
                  ("POST", "/v1/episodes/20200101T000000000Z-abcdef/retry"),
                  ("GET", "/no/such/route")]
        for auth in wrong:
            headers = {} if auth is None else {"Authorization": auth}
            for method, path in routes:
                async with d.http.request(method, d.url + path, headers=headers,
                                          json={"candidates": FOOD}) as resp:
                    body = await resp.json()
                    assert resp.status == 401, (auth, method, path, resp.status, body)
                    assert resp.headers["WWW-Authenticate"] == "Bearer"
                    assert "token" in body["error"] and TOKEN not in str(body)
        assert joints(robot, d.cfg) == before and d.store.ids() == []
        good = {"Authorization": f"Bearer {TOKEN}"}
        status, ep = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True},
                                  headers=good)
        assert status == 200 and ep["status"] == "not_configured"
        status, again = await d.get(f"/v1/episodes/{ep['id']}", headers=good)
        assert status == 200 and again["id"] == ep["id"]
    assert TOKEN not in caplog.text


@pytest.mark.parametrize("api", [{}, {"token": "short-token"}, {"token_file": "/nonexistent"}],
                         ids=["no-token", "short-token", "unreadable-token-file"])
async def test_off_loopback_without_a_usable_token_the_api_refuses_to_start(api):
    cfg = replace(ApiConfig(), host="0.0.0.0", **api)
    with pytest.raises(ConfigError, match=r"api\.(host|token_file)") as err:
        Api(runtime=None, cfg=cfg)  # type: ignore[arg-type]
    print(err.value)


async def test_off_loopback_without_a_token_the_daemon_exits_before_touching_the_arm(
        tmp_path):
    """``vt-edge run`` with api.host = 0.0.0.0 and no token: exit 2 with the reason, and
    the motors never got torque (the refusal comes before the hardware)."""
    async with SimRobot(QUICK_OBJECT, seed=2, cfg=base_config()) as robot:
        run_cfg = tmp_path / "run.toml"
        tomledit.update(ROOT / "configs" / "sim.toml", run_cfg, {
            "sensor": {"url": robot.xela.url}, "bus": {"port": robot.dxl.port},
            "api": {"host": "0.0.0.0", "port": 0},
            "runtime": {"state_dir": str(tmp_path / "state")}})
        env = {k: v for k, v in __import__("os").environ.items() if k != "VTZERO_API_TOKEN"}
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "edge", "run", "--config", str(run_cfg), cwd=ROOT, env=env,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        _, err = await asyncio.wait_for(proc.communicate(), 60)
        print(err.decode()[-500:])
        assert proc.returncode == 2
        assert "api.host = '0.0.0.0' exposes the API" in err.decode()
        assert all(robot.dxl.get_register(i, "Torque Enable") == 0
                   for i in (11, 12, 13, 14, 15))


# --- the VLM API key -----------------------------------------------------------------------

@contextlib.asynccontextmanager
async def key_daemon(tmp_path, fake):
    cfg = fast_config(fake.base_url)
    async with sim_daemon(tmp_path, cfg=cfg) as (robot, d):
        yield robot, d


async def every_answer(d) -> str:
    """Everything the API says about the daemon's episodes, metrics and health."""
    texts = []
    for episode_id in d.store.ids():
        async with d.http.get(f"{d.url}/v1/episodes/{episode_id}") as resp:
            texts.append(await resp.text())
    for path in ("/metrics", "/healthz"):
        async with d.http.get(d.url + path) as resp:
            texts.append(await resp.text())
    return "\n".join(texts)


def all_log_text(caplog) -> str:
    """Every record the daemon logged (tracebacks included); not the fake server's own."""
    formatter = logging.Formatter("%(name)s %(levelname)s %(message)s")
    return "\n".join(formatter.format(record) for record in caplog.records
                     if not record.name.startswith("edge.sim.fake_vlm"))


def store_bytes(root) -> bytes:
    return b"".join(p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file())


async def test_planted_vlm_key_never_leaks(tmp_path, monkeypatch, caplog):
    caplog.set_level(logging.DEBUG)
    monkeypatch.setenv("VTZERO_VLM_API_KEY", KEY)
    seen: list = []

    async with FakeVLM(api_key=KEY, choose=lambda req: QUICK_OBJECT) as fake:
        # A 500 quoting the key, then (retried) prose quoting it (taken for the JSON mode
        # ignored, and logged), answers that are the key itself twice (invalid_answer, the
        # corrective request echoing it back), then a good answer.
        fake.script(Reply.error(500, f"upstream auth {KEY} failed"),
                    Reply(content=f"my key is {KEY}"), Reply(content=f'{{"label": "{KEY}"}}'),
                    Reply(content=KEY))
        async with key_daemon(tmp_path / "a", fake) as (_, d):
            assert "api_key=set" in repr(d.vlm) and KEY not in repr(d.vlm)
            status, first = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
            assert status == 200 and first["status"] == "pending"
            ended = await d.wait_status(first["id"], {"invalid_answer"})
            status, ok = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
            assert status == 200 and ok["status"] == "done"
            seen += [str(first), str(ended), str(ok), await every_answer(d)]
            store_consistent(d.store.root)
            on_disk = store_bytes(d.store.root)
        # The key was really sent (the test means something)...
        assert all(r.headers.get("Authorization") == f"Bearer {KEY}" for r in fake.requests)
        assert len(fake.chat_requests) == 5

    # ...and a server that refuses it and quotes it back.
    async with FakeVLM(api_key="the-right-key", echo_key_in_errors=True) as liar:
        async with key_daemon(tmp_path / "b", liar) as (_, d):
            status, refused = await d.post("/v1/recognize", {"candidates": FOOD,
                                                             "wait": True})
            assert status == 200 and refused["status"] == "vlm_error"
            assert "check the API key" in refused["last_error"]
            assert "<redacted>" in refused["last_error"]
            seen += [str(refused), await every_answer(d)]
            on_disk += store_bytes(d.store.root)
            # The exception itself, as a caller of the client gets it.
            with pytest.raises(VLMError) as err:
                await d.vlm.ask(render(QUICK_OBJECT), "a description", FOOD)
            seen += [str(err.value), repr(err.value), getattr(err.value, "excerpt", "")]
        assert liar.requests[0].error and KEY in liar.requests[0].error  # it did quote it

    logs = all_log_text(caplog)
    print(f"{len(caplog.records)} log records, {len(on_disk)} bytes on disk, "
          f"{sum(map(len, seen))} characters of answers checked")
    assert KEY not in logs
    assert KEY.encode() not in on_disk
    for text in seen:
        assert KEY not in text
    assert "<redacted>" in ended["vlm"]["raw"] or ended["vlm"]["raw"] == ""
