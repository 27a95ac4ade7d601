"""The disk fills up under the running daemon (a fake ENOSPC at the store layer). The user
gets a clear error, older episodes stay intact, nothing half-written is left, the press that
could not be written is held and written once there is space, the daemon keeps serving and
presses again once there is space."""

from __future__ import annotations

import builtins
import errno
import json
import os
from dataclasses import replace
from types import SimpleNamespace

import pytest

from edge.core import recording
from edge.runtime import store
from tests.support.daemon import (
    FOOD,
    at_pose,
    fast_config,
    gripper_open,
    joints,
    sim_daemon,
    store_consistent,
    wait_health,
)

pytestmark = pytest.mark.asyncio


def enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


async def test_disk_full_while_writing_is_a_clear_error_and_the_daemon_serves_on(
        tmp_path, monkeypatch):
    # Retention off: with keep_free_mb it would remove the older episode to make room.
    cfg = fast_config()
    cfg = replace(cfg, runtime=replace(cfg.runtime, keep_free_mb=0.0))
    async with sim_daemon(tmp_path, cfg=cfg) as (robot, d):
        status, old = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
        assert status == 200 and old["status"] == "not_configured"
        old_json = (d.store.root / old["id"] / "episode.json").read_bytes()

        # The disk fills while the next press runs (accepted: its note was written): every
        # write of the store fails from the moment the gripper closes.
        real_open = builtins.open

        def full_open(path, mode="r", *args, **kwargs):
            if "w" in mode and "episodes" in str(path):
                enospc()
            return real_open(path, mode, *args, **kwargs)

        status, held = await d.post("/v1/recognize", {"candidates": FOOD})
        assert status == 202
        await d.wait_press_state({"closing", "holding"})
        monkeypatch.setattr(store, "open", full_open, raising=False)
        monkeypatch.setattr(store, "atomic_write_text", enospc)
        held = await d.wait_status(held["id"], {"not_configured"})
        print("while writing:", held["note"])
        # The user: a clear note; the press is readable, held in memory until it is written.
        assert "disk is full" in held["note"] and "older episodes are intact" in held["note"]
        # The robot finished its press normally.
        await d.wait_idle()
        assert gripper_open(robot) and at_pose(robot, d.cfg, "above")

        # The disk stays full: /healthz says so, and a press is refused before any motion.
        monkeypatch.setattr(store.os, "statvfs", lambda path: SimpleNamespace(
            f_bavail=10, f_frsize=4096, f_files=1000, f_favail=1000))
        health = await wait_health(d, False)
        print("healthz:", health)
        assert "disk is full" in health["store_error"]
        before = joints(robot, d.cfg)
        status, refused = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
        assert status == 503 and "disk" in refused["error"]
        assert joints(robot, d.cfg) == before and d.runtime.press.state == "idle"

        # The store: the older episode intact, nothing half-written.
        (kept,) = store_consistent(d.store.root)
        assert kept["id"] == old["id"]
        assert (d.store.root / old["id"] / "episode.json").read_bytes() == old_json
        recording.load(d.store.root / old["id"] / "press.press.npz")

        # Space again: the held press written, healthy, and a press is accepted.
        monkeypatch.undo()
        await wait_health(d, True)
        status, ep = await d.post("/v1/recognize", {"candidates": FOOD})
        assert status == 202
        ep = await d.wait_status(ep["id"], {"not_configured"})
        assert [e["id"] for e in store_consistent(d.store.root)] == [
            old["id"], held["id"], ep["id"]]
        assert json.loads(old_json)["status"] == "not_configured"
