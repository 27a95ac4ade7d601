"""Pose teaching and checking against the emulated robot (the real driver over a pty)."""

import time

import pytest

from edge.core.config import Config, load_config
from edge.core.errors import EdgeError
from edge.ops.pose import SUPPORT_PROMPT, goto_pose, teach_pose
from edge.sim.robot import SimRobot

TOLERANCE_RAW = 15  # DynamixelArm's in-position tolerance


@pytest.mark.asyncio
async def test_teach_warns_before_torque_off_then_stores_the_pose(tmp_path):
    path = tmp_path / "robot.toml"
    path.write_text('mode = "sim"\n# my comment stays\n[press]\nx_th = 0.003\n')
    path.chmod(0o644)  # as installed: the service user reads it
    cfg = Config()
    hand = (2100, 1500, 2700, 1990)
    prompts, torque_at_prompt = [], []
    async with SimRobot("wood_cube", seed=12, cfg=cfg) as robot:
        # The arm holds a raised pose (torque on), as after `pose goto` or a killed daemon.
        for motor_id in cfg.bus.joint_ids:
            robot.dxl.set_register(motor_id, "Torque Enable", 1)

        def user(message):
            prompts.append(message)
            torque_at_prompt.append(
                [robot.dxl.get_register(i, "Torque Enable") for i in cfg.bus.joint_ids])
            if len(prompts) == 2:  # moves the arm by hand
                for motor_id, raw in zip(cfg.bus.joint_ids, hand, strict=True):
                    robot.dxl.set_register(motor_id, "Present Position", raw)

        joints = await teach_pose(robot.runtime_config(cfg), path, "above", prompt=user)
        torque = [robot.dxl.get_register(i, "Torque Enable") for i in cfg.bus.joint_ids]
    assert prompts[0] == SUPPORT_PROMPT and "support the arm" in prompts[0]
    assert torque_at_prompt[0] == [1, 1, 1, 1]  # warned while it still held
    assert "'above'" in prompts[1] and torque_at_prompt[1] == [0, 0, 0, 0]
    assert all(abs(a - b) <= 1 for a, b in zip(joints, hand, strict=True))
    assert torque == [0, 0, 0, 0]
    saved = path.read_text()
    assert path.stat().st_mode & 0o777 == 0o644  # still readable by the service
    assert "# my comment stays" in saved and "x_th = 0.003" in saved
    loaded = load_config(path)
    assert loaded.poses["above"] == joints
    assert loaded.poses["rest"] == cfg.poses["rest"] and loaded.press.x_th == 0.003


@pytest.mark.asyncio
async def test_goto_moves_slowly_holds_then_rests_with_torque_off():
    cfg = Config()
    move_time_s = 0.8
    prompts, seen = [], []
    async with SimRobot("wood_cube", seed=13, cfg=cfg) as robot:
        ids = cfg.bus.joint_ids

        def user(message):
            prompts.append(message)
            seen.append((time.monotonic(),
                         [robot.dxl.get_register(i, "Present Position") for i in ids],
                         [robot.dxl.get_register(i, "Torque Enable") for i in ids]))

        joints = await goto_pose(robot.runtime_config(cfg), "lowered", prompt=user,
                                 move_time_s=move_time_s)
        after = ([robot.dxl.get_register(i, "Present Position") for i in ids],
                 [robot.dxl.get_register(i, "Torque Enable") for i in ids])
    (t0, start, _), (t1, held, torque_held) = seen
    target, rest = cfg.poses["lowered"], cfg.poses["rest"]
    print(f"goto lowered: {t1 - t0:.2f} s from Enter to holding (move time {move_time_s} s); "
          f"from {start} to {held}, taught {list(target)}")
    assert "over 0.8 s" in prompts[0] and "'lowered'" in prompts[1]
    assert max(abs(a - b) for a, b in zip(start, target, strict=True)) > 100  # it moved
    assert all(abs(a - b) <= TOLERANCE_RAW for a, b in zip(held, target, strict=True)), held
    # (what goto reports is where the arm holds, within the settling a loaded host may see)
    assert all(abs(a - b) <= TOLERANCE_RAW for a, b in zip(joints, held, strict=True))
    assert torque_held == [1, 1, 1, 1]
    # The profile spreads the move over move_time_s: not a jump.
    assert t1 - t0 >= 0.8 * move_time_s
    assert all(abs(a - b) <= TOLERANCE_RAW for a, b in zip(after[0], rest, strict=True))
    assert after[1] == [0, 0, 0, 0]


@pytest.mark.asyncio
async def test_goto_an_unknown_pose_is_refused_before_anything_moves():
    with pytest.raises(EdgeError, match=r"pose 'abve' is not in \[poses\].*pose teach abve"):
        await goto_pose(Config(), "abve", prompt=lambda _m: pytest.fail("prompted"))


@pytest.mark.asyncio
async def test_closed_stdin_is_a_one_line_error_and_the_arm_goes_back_to_rest():
    cfg = Config()
    prompts = []

    def user(message):  # Enter to start, then the input ends (a pipe, a closed terminal)
        prompts.append(message)
        if len(prompts) > 1:
            raise EOFError

    async with SimRobot("wood_cube", seed=14, cfg=cfg) as robot:
        with pytest.raises(EdgeError, match="standard input is closed"):
            await goto_pose(robot.runtime_config(cfg), "above", prompt=user, move_time_s=0.3)
        ids = cfg.bus.joint_ids
        pos = [robot.dxl.get_register(i, "Present Position") for i in ids]
        torque = [robot.dxl.get_register(i, "Torque Enable") for i in ids]
    assert "holding 'above'" in prompts[1]
    assert all(abs(a - b) <= TOLERANCE_RAW for a, b in zip(pos, cfg.poses["rest"], strict=True))
    assert torque == [0, 0, 0, 0]


def test_ctrl_c_at_the_prompt_exits_at_once(tmp_path):
    """The first prompt comes before the bus is opened: no robot is needed to reach it."""

    from tests.support import processes
    from tests.support.processes import VT_EDGE, clean_env

    config = tmp_path / "robot.toml"
    config.write_text('mode = "sim"\n')
    proc, output = processes.start([*VT_EDGE, "pose", "teach", "above", "--config",
                                    str(config)], clean_env(), stdin=True)
    output.wait_for("support the arm")
    rc, took = processes.interrupt(proc, output)
    assert rc == 130 and took < 10.0
    proc.stdin.close()  # type: ignore[union-attr]
