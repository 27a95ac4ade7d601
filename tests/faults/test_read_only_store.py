"""The state directory's filesystem turns read-only under the running daemon (an SD card does
after an error), then writable again.

Root ignores file modes, so the read-only condition is a real one: a small tmpfs remounted
read-only and back. Where this host does not allow ``mount``, EROFS is raised where the
store writes (its ``open`` and atomic writes), as the filesystem would."""

from __future__ import annotations

import builtins
import contextlib
import errno
import os
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from edge.runtime import store
from edge.sim.fake_vlm import FakeVLM
from tests.support.daemon import (
    FOOD,
    QUICK_OBJECT,
    Daemon,
    fast_config,
    gripper_open,
    joints,
    sim_daemon,
    store_consistent,
    wait_health,
)
from tests.support.waits import wait_until

pytestmark = pytest.mark.asyncio


def _mount(*args: str) -> bool:
    return subprocess.run(["mount", *args], capture_output=True).returncode == 0


@contextlib.contextmanager
def toggled_fs(path: Path, monkeypatch: pytest.MonkeyPatch
               ) -> Iterator[Callable[[bool], None]]:
    """``path`` on a filesystem that ``set_read_only(True/False)`` turns read-only and back."""
    path.mkdir()
    # (Larger than the default keep_free_mb, or retention would empty it; a tmpfs takes
    # memory only for what is written.)
    if _mount("-t", "tmpfs", "-o", "size=512m", "tmpfs", str(path)):
        def set_read_only(ro: bool) -> None:
            assert _mount("-o", f"remount,{'ro' if ro else 'rw'}", str(path))
        try:
            print("read-only condition: a tmpfs remounted")
            yield set_read_only
        finally:
            subprocess.run(["umount", "-l", str(path)], check=False)
        return
    print("read-only condition: EROFS raised where the store writes (mount not allowed)")
    real_open = builtins.open

    def erofs(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    def ro_open(file, mode="r", *args, **kwargs):
        if any(c in mode for c in "wax+") and str(file).startswith(str(path)):
            erofs()
        return real_open(file, mode, *args, **kwargs)

    def set_read_only(ro: bool) -> None:
        if ro:
            monkeypatch.setattr(store, "open", ro_open, raising=False)
            monkeypatch.setattr(store, "atomic_write_text", erofs)
        else:
            monkeypatch.undo()

    yield set_read_only


def daemon_on(state: Path, fake: FakeVLM):
    cfg = fast_config(fake.base_url)
    # A 1 s hold: the store turned read-only while the gripper closes (a remount, a process
    # of its own on a busy host) is read-only before the press's episode is written.
    return sim_daemon(state, cfg=replace(cfg, press=replace(cfg.press, dt_stopping_s=1.0)))


async def metric(d: Daemon, name: str) -> float:
    async with d.http.get(d.url + "/metrics") as resp:
        text = await resp.text()
    (line,) = [x for x in text.splitlines() if x.startswith(name + " ")]
    return float(line.split()[1])


async def test_read_only_state_dir_refuses_presses_before_motion_and_recovers(
        tmp_path, monkeypatch):
    async with FakeVLM(choose=lambda req: QUICK_OBJECT) as fake, \
            contextlib.AsyncExitStack() as stack:
        set_read_only = stack.enter_context(toggled_fs(tmp_path / "state", monkeypatch))
        robot, d = await stack.enter_async_context(daemon_on(tmp_path / "state", fake))
        status, first = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
        assert status == 200 and first["status"] == "done", first

        await d.wait_idle()
        set_read_only(True)

        def motors() -> list[float]:
            return [*joints(robot, d.cfg), robot.dxl.true_position(robot.world.gripper_id)]

        before = motors()
        status, refused = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
        print("refused:", status, refused)
        assert status == 503 and "read-only" in refused["error"]
        assert "Traceback" not in str(refused)
        # The arm never moved: joints and gripper where they stood (within a raw count: the
        # last move's profile settling), no press ran.
        assert max(abs(a - b) for a, b in zip(motors(), before, strict=True)) < 1.0
        assert d.runtime.press.state == "idle" and not d.runtime.recognizer.work
        health = await wait_health(d, False)
        print("healthz:", health)
        assert "read-only" in health["store_error"]
        assert await metric(d, "vtzero_store_ok") == 0

        set_read_only(False)
        health = await wait_health(d, True)  # by itself: no restart
        assert health["store_error"] is None and await metric(d, "vtzero_store_ok") == 1
        status, again = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
        assert status == 200 and again["status"] == "done", again
        assert [e["id"] for e in store_consistent(d.store.root)] == [first["id"], again["id"]]


async def test_a_press_whose_write_failed_is_readable_and_written_once_the_store_is_back(
        tmp_path, monkeypatch):
    async with FakeVLM(choose=lambda req: QUICK_OBJECT) as fake, \
            contextlib.AsyncExitStack() as stack:
        set_read_only = stack.enter_context(toggled_fs(tmp_path / "state", monkeypatch))
        robot, d = await stack.enter_async_context(daemon_on(tmp_path / "state", fake))
        # Accepted (noted on disk), then the store goes read-only while the gripper closes.
        status, ep = await d.post("/v1/recognize", {"candidates": FOOD})
        assert status == 202
        await d.wait_press_state({"closing", "holding"})
        set_read_only(True)
        assert d.runtime.press.state in ("closing", "holding"), "read-only too late"
        held = await d.wait_status(ep["id"], {"done"})
        print("held:", held["note"])
        assert "held in memory" in held["note"] and held["label"] == QUICK_OBJECT
        await d.wait_idle()
        assert gripper_open(robot)
        assert not (d.store.root / ep["id"]).exists()
        assert await metric(d, "vtzero_store_held_episodes") == 1
        assert await metric(d, "vtzero_store_write_failures_total") >= 1
        health = await wait_health(d, False)
        assert health["store_error"] is not None

        set_read_only(False)
        await wait_until(lambda: (d.store.root / ep["id"] / "episode.json").exists(), 10.0,
                         "the held episode written")
        await wait_health(d, True)
        assert await metric(d, "vtzero_store_held_episodes") == 0
        assert await metric(d, "vtzero_store_lost_total") == 0
        (kept,) = store_consistent(d.store.root)
        assert kept["id"] == ep["id"] and kept["status"] == "done"
        assert kept["label"] == QUICK_OBJECT and "note" not in kept
        status, read = await d.get(f"/v1/episodes/{ep['id']}")
        assert status == 200 and read["status"] == "done" and "note" not in read


async def test_a_stop_while_episodes_are_held_says_so_and_the_next_start_keeps_them(
        tmp_path, monkeypatch, caplog):
    async with FakeVLM(choose=lambda req: QUICK_OBJECT) as fake, \
            contextlib.AsyncExitStack() as stack:
        set_read_only = stack.enter_context(toggled_fs(tmp_path / "state", monkeypatch))
        async with daemon_on(tmp_path / "state", fake) as (_, d):
            status, ep = await d.post("/v1/recognize", {"candidates": FOOD})
            assert status == 202
            await d.wait_press_state({"closing", "holding"})
            set_read_only(True)
            assert d.runtime.press.state in ("closing", "holding"), "read-only too late"
            await d.wait_status(ep["id"], {"done"})
            await d.wait_idle()
        # Stopped with the episode held: said, not silent.
        assert any("1 episode(s) held in memory could not be written before the stop"
                   in r.getMessage() for r in caplog.records)
        set_read_only(False)
        async with daemon_on(tmp_path / "state", fake) as (_, d):
            status, back = await d.get(f"/v1/episodes/{ep['id']}")
        print(back)
        assert status == 200 and back["status"] == "failed"
        assert back["error"].startswith("interrupted")
