"""The daemon's lifecycle on every path out: a failed start, a task that dies, SIGTERM; the
events stream across silence; a reload that reaches the next press."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
from dataclasses import replace

import pytest

import edge.interfaces.http.api
from edge.app import assemble
from edge.core.errors import StartError
from edge.hw.arm import gripper_raw
from edge.sim.robot import SimRobot
from tests.support.daemon import (
    CUBE,
    QUICK_OBJECT,
    Daemon,
    base_config,
    fast_config,
    gripper_open,
)
from tests.support.waits import wait_until

GRIPPER_TOL_RAW = 20


def torque(robot: SimRobot, cfg) -> dict[int, int]:
    return {i: robot.dxl.get_register(i, "Torque Enable")
            for i in (*cfg.bus.joint_ids, cfg.bus.gripper_id)}


@pytest.mark.asyncio
async def test_a_taken_api_port_fails_the_start_in_one_line_with_torque_never_on(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        async with SimRobot("wood_cube", seed=1, cfg=base_config()) as robot:
            cfg = robot.runtime_config(base_config())
            cfg = replace(cfg, api=replace(cfg.api, port=port),
                          runtime=replace(cfg.runtime, state_dir=str(tmp_path)))
            with pytest.raises(StartError) as err:
                async with assemble(cfg):
                    pytest.fail("the daemon started on a taken port")
            assert str(err.value) == (f"cannot listen on 127.0.0.1:{port}: "
                                      "address already in use")
            assert set(torque(robot, cfg).values()) == {0}


@pytest.mark.asyncio
async def test_a_task_dying_mid_press_leaves_the_gripper_open_and_torque_off(tmp_path):
    async with SimRobot("gelatin_soft", seed=2, cfg=base_config()) as robot:
        cfg = robot.runtime_config(fast_config())
        d = Daemon(robot, fast_config(), tmp_path)
        with pytest.raises(ExceptionGroup) as err:
            async with d:
                assert set(torque(robot, cfg).values()) == {1}
                status, ep = await d.post("/v1/recognize", {"candidates": CUBE})
                assert status == 202, ep
                await d.wait_press_state({"closing"})

                def die(now: float, late: float) -> None:
                    raise RuntimeError("sampler bug")

                d.runtime.sampler.on_tick = die  # the sampler task dies mid-press
                await asyncio.wait_for(asyncio.shield(d.task), 20)
        assert err.group_contains(RuntimeError, match="sampler bug")
        assert gripper_open(robot)
        assert set(torque(robot, cfg).values()) == {0}


@pytest.mark.asyncio
async def test_events_stay_open_across_silence_and_deliver_the_next_press(tmp_path,
                                                                         monkeypatch):
    # 25 keepalive periods of silence (40 s at the shipped 15 s keepalive is 2.7): the
    # stream used to end at the first one.
    keepalive_s = 0.08
    monkeypatch.setattr(edge.interfaces.http.api, "SSE_KEEPALIVE_S", keepalive_s)
    async with SimRobot(QUICK_OBJECT, seed=3, cfg=base_config()) as robot, \
            Daemon(robot, fast_config(), tmp_path) as d:
        events, keepalives = [], 0
        async with d.http.get(d.url + "/v1/events") as resp:
            async def listen():
                nonlocal keepalives
                async for line in resp.content:
                    if line.startswith(b": keepalive"):
                        keepalives += 1
                    elif line.startswith(b"data: "):
                        events.append(json.loads(line[6:]))
                        if events[-1].get("type") == "result":
                            return

            listener = asyncio.create_task(listen())
            await asyncio.sleep(25 * keepalive_s)
            assert not listener.done(), "the event stream ended during the silence"
            assert keepalives >= 10
            _, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            await asyncio.wait_for(listener, 20)
        print(f"\n{keepalives} keepalives in {25 * keepalive_s:.1f} s of silence, then "
              f"{len(events)} events")
        assert events[-1]["episode"] == ep["id"] and events[-1]["status"] == "not_configured"


@pytest.mark.asyncio
async def test_sighup_changes_open_width_and_close_timeout_for_the_next_press(tmp_path):
    async with SimRobot(QUICK_OBJECT, seed=4, cfg=base_config()) as robot:
        async with Daemon(robot, fast_config(), tmp_path) as d:
            gripper = d.cfg.bus.gripper_id
            _, first = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            assert first["press"]["contact"], first
            old_open = robot.dxl.true_position(gripper)
            assert abs(old_open - gripper_raw(d.cfg.press.open_width_m)) < GRIPPER_TOL_RAW
            wider, short = 0.012, 0.05
            new = replace(d.cfg, press=replace(d.cfg.press, open_width_m=wider),
                          runtime=replace(d.cfg.runtime, close_timeout_s=short))
            d.runtime.reloader = lambda: (new, d.runtime.model, d.runtime.vlm)
            os.kill(os.getpid(), signal.SIGHUP)
            await wait_until(lambda: d.runtime.cfg.press.open_width_m == wider, 5,
                             "the reload")
            _, second = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            # Closing stops after the new, short timeout: no contact.
            assert second["status"] == "failed", second
            assert f"for {short} s of closing" in second["error"], second["error"]
            now_open = robot.dxl.true_position(gripper)
            print(f"\ngripper open at {old_open:.0f} raw before the reload, {now_open:.0f} "
                  f"after (goal {gripper_raw(wider)})")
            assert abs(now_open - gripper_raw(wider)) < GRIPPER_TOL_RAW
