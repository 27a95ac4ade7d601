"""``kill -9`` of the daemon while it writes an episode, then a restart: the store loads,
nothing is half-written, every committed episode is intact, the press that was cut off is
kept as ``failed`` "interrupted" (never silently gone), the daemon serves again.

Two ways in: a daemon process that kills itself at the worst instant (inside
``EpisodeStore.create`` after every file is written, before the rename; or inside the
atomic replacement of ``episode.json``), and the real ``vt-edge run`` killed from outside
the moment its temp directory appears.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import aiohttp
import pytest

from edge.core import recording, tomledit
from edge.sim.robot import SimRobot
from tests.support.daemon import (
    FOOD,
    QUICK_OBJECT,
    ROOT,
    Daemon,
    at_pose,
    base_config,
    fast_config,
    gripper_open,
    store_consistent,
    wait_health,
)
from tests.support.waits import free_port

pytestmark = pytest.mark.asyncio

SELF_KILLING_DAEMON = """
import asyncio, os, signal, sys
from pathlib import Path

import edge.core.atomic
from edge.sim.robot import SimRobot
from edge.runtime.store import EpisodeStore
from tests.support.daemon import FOOD, QUICK_OBJECT, Daemon, base_config, fast_config

state, where = Path(sys.argv[1]), sys.argv[2]


def die(*args, **kwargs):
    print("killed while writing", flush=True)
    os.kill(os.getpid(), signal.SIGKILL)


async def main():
    async with SimRobot(QUICK_OBJECT, seed=3, cfg=base_config()) as robot, \\
            Daemon(robot, fast_config(), state) as d:
        if where == "update":
            # The first episode is created whole; replacing its episode.json kills us.
            def replace(src, dst):
                if str(dst).endswith("episode.json"):
                    die()
                os.replace(src, dst)

            edge.core.atomic.os = type("os", (), {**vars(os), "replace": replace})
        else:
            status, ep = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
            print("committed", ep["id"], ep["status"], flush=True)
            real_create = EpisodeStore.create

            def create(self, episode, files):
                os.rename = die  # every file written and fsynced, the rename never happens
                return real_create(self, episode, files)

            EpisodeStore.create = create
        status, ep = await d.post("/v1/recognize", {"candidates": FOOD})
        print("accepted", ep["id"], flush=True)
        await asyncio.sleep(60)


asyncio.run(main())
"""


@pytest.mark.parametrize("where", ["create", "update"])
async def test_kill_9_inside_a_store_write_then_restart(tmp_path, where):
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c", SELF_KILLING_DAEMON, str(tmp_path), where, cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), "VTZERO_LOG_LEVEL": "WARNING"},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), 90)
    lines = out.decode().splitlines()
    print(lines)
    assert proc.returncode == -signal.SIGKILL, err.decode()[-2000:]
    assert lines[-1] == "killed while writing"
    root = tmp_path / "episodes"
    committed = [line.split()[1] for line in lines if line.startswith("committed")]
    (accepted,) = [line.split()[1] for line in lines if line.startswith("accepted")]
    # What the kill left: a temp directory (create) or a temp episode.json (update).
    left = sorted(str(p.relative_to(root)) for p in root.rglob(".*") if p.name != ".accepted")
    print("left by the kill:", left)
    assert left and all(".tmp" in name for name in left)
    if where == "create":  # and the note that the press was accepted
        assert (root / ".accepted" / f"{accepted}.json").is_file()

    async with SimRobot(QUICK_OBJECT, seed=4, cfg=base_config()) as robot, \
            Daemon(robot, fast_config(), tmp_path) as d:
        # The store loads, the leftovers are gone, the restart says how many it discarded.
        async with d.http.get(d.url + "/metrics") as resp:
            metrics = await resp.text()
        if where == "update":
            # The update never landed: the episode is as it was before (pending), whole,
            # and the restarted daemon asks again (let it finish writing before looking).
            ep = await d.wait_status(accepted, {"not_configured"})
            assert ep["attempts"] == 1
        for ep in store_consistent(root):
            if ep["id"] == accepted and where == "create":
                continue  # (kept as interrupted, below)
            assert ep["press"]["contact"]
            recording.load(root / ep["id"] / "press.press.npz")
        await wait_health(d, True)
        if where == "create":
            assert f"vtzero_store_discarded_partial_total {len(left)}" in metrics
            kept = {e["id"]: e for e in store_consistent(root)}
            assert set(kept) == {committed[0], accepted}
            assert (await d.get(f"/v1/episodes/{committed[0]}"))[1]["status"] == (
                "not_configured")
            # The episode killed while being written: none of its half-written files, but
            # the user learns what became of the press.
            status, lost = await d.get(f"/v1/episodes/{accepted}")
            print("the press cut off:", lost)
            assert status == 200 and lost["status"] == "failed"
            assert lost["error"].startswith("interrupted: the daemon stopped")
            assert lost["candidates"] == FOOD and lost["source"] == "api"
            assert not (root / accepted / "press.press.npz").exists()
        assert gripper_open(robot)


def kill_when_writing(pid: int, root: Path, episode_id: str, timeout_s: float) -> dict:
    """In a thread: SIGKILL ``pid`` the moment a temp episode directory appears (or, if the
    write was too quick to be seen, the moment the episode is there; or at the timeout)."""
    seen: dict = {}
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            try:
                names = os.listdir(root)
            except FileNotFoundError:
                time.sleep(0.001)
                continue
            tmp = [n for n in names if n.startswith(".tmp-")]
            if tmp:
                seen["temp_dir"] = tmp[0]
                return seen
            if episode_id in names:
                seen["committed_before_seen"] = episode_id
                return seen
            time.sleep(0.0002)
        seen["timeout"] = timeout_s
        return seen
    finally:
        os.kill(pid, signal.SIGKILL)


async def test_real_daemon_killed_9_while_writing_then_restarted(tmp_path):
    state = tmp_path / "state"
    env = {**os.environ, "VTZERO_STATE_DIR": str(state), "VTZERO_LOG_LEVEL": "WARNING",
           "PYTHONUNBUFFERED": "1"}
    env.pop("VTZERO_VLM_URL", None)
    async with SimRobot(QUICK_OBJECT, seed=5, cfg=base_config()) as robot:
        run_cfg, port = tmp_path / "run.toml", free_port()
        tomledit.update(ROOT / "configs" / "sim.toml", run_cfg, {
            "sensor": {"url": robot.xela.url}, "bus": {"port": robot.dxl.port},
            "api": {"port": port}, "runtime": {"move_time_s": 0.1},
            "press": {"tare_s": 0.15}})
        api = f"http://127.0.0.1:{port}"
        cfg = robot.runtime_config(base_config())

        async def start() -> asyncio.subprocess.Process:
            # Its stderr into a file (both starts'): a start that fails says why in the
            # assertion.
            log = tmp_path / "daemon.log"
            with log.open("ab") as err:
                proc = await asyncio.create_subprocess_exec(
                    sys.executable, "-m", "edge", "run", "--config", str(run_cfg), cwd=ROOT,
                    env=env, stderr=err)
            deadline = time.monotonic() + 60
            async with aiohttp.ClientSession() as http:
                while True:
                    assert proc.returncode is None and time.monotonic() < deadline, \
                        (proc.returncode, log.read_text()[-2000:])
                    try:
                        async with http.get(api + "/healthz") as resp:
                            if resp.status == 200:
                                return proc
                    except aiohttp.ClientError:
                        pass
                    await asyncio.sleep(0.1)

        proc = await start()
        try:
            async with aiohttp.ClientSession() as http:
                async with http.post(api + "/v1/recognize", json={"candidates": FOOD}) as r:
                    accepted = (await r.json())["id"]
                seen = await asyncio.to_thread(kill_when_writing, proc.pid,
                                               state / "episodes", accepted, 30)
                await proc.wait()
                t_kill = time.monotonic()
                print(f"killed: {seen}")
                assert proc.returncode == -signal.SIGKILL and "timeout" not in seen
                # The robot: no host any more; each motor's Bus Watchdog stops it (0.3 s).
                await asyncio.sleep(0.5)
                assert all(robot.dxl.get_register(i, "Bus Watchdog") == -1
                           for i in (11, 12, 13, 14, 15)), time.monotonic() - t_kill
                assert gripper_open(robot) and at_pose(robot, cfg, "above")

                proc = await start()
                store_consistent(state / "episodes")
                async with http.get(f"{api}/v1/episodes/{accepted}") as resp:
                    status, body = resp.status, await resp.json()
                print("after restart:", status, body.get("status") or body)
                assert status == 200
                if body.get("error", "").startswith("interrupted"):  # none of its data
                    assert body["status"] == "failed" and "press" not in body
                elif body["press"]["contact"]:  # renamed into place before the kill: whole
                    # (a loaded host may fail the press itself)
                    recording.load(state / "episodes" / accepted / "press.press.npz")
                async with http.get(api + "/metrics") as resp:
                    text = await resp.text()
                interrupted = body.get("error", "").startswith("interrupted")
                assert f"vtzero_store_discarded_partial_total {int(interrupted)}" in text
        finally:
            if proc.returncode is None:
                proc.send_signal(signal.SIGTERM)
                await asyncio.wait_for(proc.wait(), 30)
        assert proc.returncode == 0
        assert gripper_open(robot)
