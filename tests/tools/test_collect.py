"""Collect mode and pose teaching against the emulated robot."""

import pytest

from edge.core import recording
from edge.core.config import Config, load_config
from edge.sim.robot import SimRobot
from edge.tools.collect import collect, teach_pose
from tests.support.daemon import base_config


@pytest.mark.asyncio
async def test_collect_writes_labelled_recordings(tmp_path):
    cfg = base_config()
    prompts = []
    async with SimRobot("otedama", seed=11, cfg=cfg) as robot:
        files = await collect(robot.runtime_config(cfg), "otedama", 2, tmp_path,
                              prompt=prompts.append)
    print(prompts)
    assert len(files) == 2 and len(prompts) == 2
    assert "place the otedama" in prompts[0] and "move the otedama" in prompts[1]
    for f in files:
        rec = recording.load(f)
        assert rec.label == "otedama" and rec.source == "sim"
        assert rec.extra["stop_latency_s"] > 0


@pytest.mark.asyncio
async def test_teach_stores_the_pose_and_keeps_the_rest_of_the_file(tmp_path):
    path = tmp_path / "robot.toml"
    path.write_text('mode = "sim"\n# my comment stays\n[press]\nx_th = 0.003\n')
    cfg = Config()
    hand = (2100, 1500, 2700, 1990)
    async with SimRobot("wood_cube", seed=12, cfg=cfg) as robot:
        def move_by_hand(message):
            assert "'above'" in message
            for motor_id, raw in zip(cfg.bus.joint_ids, hand, strict=True):
                robot.dxl.set_register(motor_id, "Present Position", raw)

        joints = await teach_pose(robot.runtime_config(cfg), path, "above",
                                  prompt=move_by_hand)
        torque = [robot.dxl.get_register(i, "Torque Enable") for i in cfg.bus.joint_ids]
    assert all(abs(a - b) <= 1 for a, b in zip(joints, hand, strict=True))
    assert torque == [0, 0, 0, 0]
    saved = path.read_text()
    assert "# my comment stays" in saved and "x_th = 0.003" in saved
    loaded = load_config(path)
    assert loaded.poses["above"] == joints
    assert loaded.poses["rest"] == cfg.poses["rest"] and loaded.press.x_th == 0.003
