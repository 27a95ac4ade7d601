"""Collect mode against the emulated robot."""

import pytest

from edge.core import recording
from edge.sim.robot import SimRobot
from edge.tools.collect import collect
from tests.support.daemon import base_config


@pytest.mark.asyncio
async def test_collect_writes_labelled_recordings(tmp_path):
    cfg = base_config()
    prompts = []
    async with SimRobot("otedama", seed=11, cfg=cfg) as robot:
        files = await collect(robot.runtime_config(cfg), "otedama", 2, tmp_path,
                              prompt=prompts.append)
    assert len(files) == 2 and len(prompts) == 1 and "move the otedama" in prompts[0]
    for f in files:
        rec = recording.load(f)
        assert rec.label == "otedama" and rec.source == "sim"
        assert rec.extra["stop_latency_s"] > 0

