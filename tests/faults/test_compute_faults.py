"""The compute process (crop, encoder, image preparation) dies: one episode fails with the
press kept raw, the robot is safe, and the next press works on a new worker. A model it
cannot load stops the daemon before any motor is powered."""

import asyncio
import os
import shutil
import signal
import subprocess
import sys

import pytest

from edge.core import recording, tomledit
from edge.sim.robot import SimRobot
from tests.support.daemon import (
    FOOD,
    LOADED_HOST_TRIES,
    QUICK_OBJECT,
    ROOT,
    at_pose,
    base_config,
    gripper_open,
    sim_daemon,
    store_consistent,
)

pytestmark = pytest.mark.asyncio


async def test_compute_worker_killed_during_a_press(tmp_path):
    async with sim_daemon(tmp_path) as (robot, d):
        for attempt in range(1, LOADED_HOST_TRIES + 1):
            worker = d.compute.pid()
            status, ep = await d.post("/v1/recognize", {"candidates": FOOD})
            assert status == 202
            await d.wait_press_state({"closing"})
            os.kill(worker, signal.SIGKILL)  # as the OOM killer would
            failed = await d.wait_status(ep["id"], {"failed", "not_configured"})
            await d.wait_idle()
            # A press that did not end ok says nothing about the worker: this test injects no
            # bus fault, so it was a loaded host's doing (a stall past the Bus Watchdog, a
            # status packet starved past its timeout as the arm returned: make test beside
            # stress-ng saw both): pressed again, on the worker started since.
            if attempt < LOADED_HOST_TRIES and not failed["press"]["contact"]:
                print(f"  press {attempt} failed on a loaded host: {failed['error']}; "
                      f"{failed['press']['message']}")
                continue
            break
        first_worker = worker
        # The robot: the press itself did not need the worker; it ended as always.
        assert gripper_open(robot) and at_pose(robot, d.cfg, "above")
        assert failed["press"]["contact"] and failed["press"]["result"] == "ok"
        # The user: why, in words; the daemon is healthy.
        print("worker killed:", failed["error"])
        assert failed["status"] == "failed"
        assert "press worked but its analysis failed" in failed["error"]
        assert "compute worker died" in failed["error"]
        assert (await d.get("/healthz"))[0] == 200
        # Kept: the raw press, whole.
        kept = next(e for e in store_consistent(d.store.root) if e["id"] == failed["id"])
        rec = recording.load(d.store.root / kept["id"] / "press.press.npz")
        assert rec.frames.shape[0] > 100
        # The next press gets a new worker and a normal answer.
        status, ep2 = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
        assert status == 200 and ep2["status"] == "not_configured" and ep2["description"]
        assert d.compute.pid() not in (None, first_worker) and d.compute.restarts == attempt


async def test_a_damaged_model_stops_the_daemon_before_any_motor_moves(tmp_path):
    """As systemd sees it: ``vt-edge run`` exits 2 naming the file; torque never on."""
    models = tmp_path / "models"
    shutil.copytree(ROOT / "models", models)
    with (models / "database.npz").open("r+b") as f:
        f.seek(100)
        f.write(b"\x00damaged\x00")
    async with SimRobot(QUICK_OBJECT, seed=1, cfg=base_config()) as robot:
        run_cfg = tmp_path / "run.toml"
        tomledit.update(ROOT / "configs" / "sim.toml", run_cfg, {
            "sensor": {"url": robot.xela.url}, "bus": {"port": robot.dxl.port},
            "api": {"port": 0}, "runtime": {"state_dir": str(tmp_path / "state"),
                                            "models_dir": str(models)}})
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "edge", "run", "--config", str(run_cfg), cwd=ROOT,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        _, err = await asyncio.wait_for(proc.communicate(), 60)
        print(f"exit {proc.returncode}:", err.decode()[-300:])
        assert proc.returncode == 2
        assert "database.npz: sha256" in err.decode() and "does not match" in err.decode()
        assert all(robot.dxl.get_register(i, "Torque Enable") == 0 for i in (11, 12, 13, 14, 15))
