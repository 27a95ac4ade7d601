"""The compute process (crop, encoder, image preparation) dies: one episode fails with the
press kept raw, the robot is safe, and the next press works on a new worker."""

import os
import signal

import pytest

from edge import recording
from tests.harness import FOOD, at_pose, gripper_open, sim_daemon, store_consistent

pytestmark = pytest.mark.asyncio


async def test_compute_worker_killed_during_a_press(tmp_path):
    async with sim_daemon(tmp_path) as (robot, d):
        first_worker = d.compute.pid()
        status, ep = await d.post("/v1/recognize", {"candidates": FOOD})
        assert status == 202
        await d.wait_press_state({"closing"})
        os.kill(first_worker, signal.SIGKILL)  # as the OOM killer would
        failed = await d.wait_status(ep["id"], {"failed", "not_configured"})
        await d.wait_idle()
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
        (kept,) = store_consistent(d.store.root)
        rec = recording.load(d.store.root / kept["id"] / "press.press.npz")
        assert rec.frames.shape[0] > 100
        # The next press gets a new worker and a normal answer.
        status, ep2 = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
        assert status == 200 and ep2["status"] == "not_configured" and ep2["description"]
        assert d.compute.pid() not in (None, first_worker) and d.compute.restarts == 1
