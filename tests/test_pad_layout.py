"""Another uSkin on the fingers: a robot with 4 x 6 pads (configs/sim-4x6.toml) collects,
builds and recognises with the same commands as the 4 x 4 one; the shipped 4 x 4 model on it
is refused at start in one line, exit 2, torque never on (and a 4 x 6 model on a 4 x 4
robot likewise)."""

from __future__ import annotations

import asyncio
import json
import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from edge.app import assemble
from edge.core import recording
from edge.core.config import Config, load_config
from edge.core.errors import ConfigError, StartError
from edge.core.layout import XR1944, PadLayout
from edge.core.model import load_model, model_ref
from edge.lab.collect import collect_plan
from edge.lab.plan import load_plan
from edge.lab.record import record_press, sim_config
from edge.ops.doctor import Level, _check_model
from edge.recordings import lerobot, mcaplog
from edge.sim.catalogue import get
from edge.sim.contact import ObjectInstance
from edge.sim.fake_vlm import FakeVLM, Reply
from edge.sim.robot import SimRobot
from edge.sim.skin import TAXEL_PITCH_M, Skin
from edge.sim.world import robot_pads
from edge.sim.xela_replay import load_replay
from tests.app.test_start_checks import torque_registers, vt_edge_run
from tests.interfaces.test_operator_api import sse_frames
from tests.support.daemon import ROOT, Daemon, base_config
from train.cli import main as train_main

SIM_4X6 = ROOT / "configs" / "sim-4x6.toml"
LAYOUT_4X6 = PadLayout(2, 4, 6)
LABELS = ("wood_cube", "sponge_cube", "otedama")
PLAN = """
[dataset]
name = "lab_4x6"
recorder = "test"
presses = 2
val = ["otedama"]
""" + "".join(f'\n[[class]]\nlabel = "{label}"\ndescription = "{get(label).description}"\n'
              for label in LABELS)
EPOCHS = 3


def with_4x6_pads(cfg: Config) -> Config:
    """``cfg`` with the [sensor] pads of configs/sim-4x6.toml (its other settings kept)."""
    pads = load_config(SIM_4X6).sensor
    return replace(cfg, sensor=replace(cfg.sensor, model=pads.model, pads=pads.pads,
                                       taxels_per_pad=pads.taxels_per_pad,
                                       taxel_rows=pads.taxel_rows))


pytestmark = pytest.mark.usefixtures("logging_as_found")


@pytest.mark.parametrize("layout", [XR1944, LAYOUT_4X6], ids=["4x4", "4x6"])
@pytest.mark.parametrize("name", ["glass_marble", "rubber_ball"])
def test_the_contact_patch_lands_on_the_grid_where_it_touches(layout, name):
    """A round object's patch, far off the pad's centre (toward a corner: past the 4 x 4
    grid's edge on the 4 x 6 one), loads the taxels around that point: the centre of the z
    load over the grid (taxel centres 4.7 mm apart) is the patch's."""
    rng = np.random.default_rng(3)
    reach_x, reach_y = 0.3 * layout.cols * TAXEL_PITCH_M, 0.3 * layout.rows * TAXEL_PITCH_M
    inst = replace(ObjectInstance.draw(get(name), rng),
                   patch_offsets_m=((reach_x, -reach_y), (-reach_x, 0.5 * reach_y)))
    skin = Skin(inst, rng, robot_pads(0, layout))
    z = skin.forces(4.0, 2e-3).reshape(layout.pads, layout.rows, layout.cols, 3)[..., 2]
    ys = (np.arange(layout.rows) - (layout.rows - 1) / 2) * TAXEL_PITCH_M
    xs = (np.arange(layout.cols) - (layout.cols - 1) / 2) * TAXEL_PITCH_M
    for pad in range(layout.pads):
        load = z[pad]
        centre = (float((load.sum(axis=0) * xs).sum() / load.sum()),
                  float((load.sum(axis=1) * ys).sum() / load.sum()))
        expected = skin.inst.patch_offsets_m[pad]
        print(f"{layout.rows}x{layout.cols} {name} pad {pad}: load centre "
              f"({centre[0] * 1e3:+.2f}, {centre[1] * 1e3:+.2f}) mm, patch "
              f"({expected[0] * 1e3:+.2f}, {expected[1] * 1e3:+.2f}) mm, "
              f"total {load.sum():.3f} N")
        assert load.shape == (layout.rows, layout.cols)
        assert abs(load.sum() - 4.0) < 1e-6  # the finger's whole force, on this pad
        assert np.allclose(centre, expected, atol=0.25 * TAXEL_PITCH_M)


@pytest.mark.asyncio
async def test_the_doctor_fails_a_model_for_other_pads(tmp_path):
    cfg = with_4x6_pads(base_config())
    checks = {c.part: c for c in _check_model(cfg)}
    print(checks["model pads"].found)
    assert checks["model"].level is Level.OK  # the files are sound...
    assert checks["model pads"].level is Level.FAIL  # ...but not for these pads
    assert "expects 96 channels (2 pads x 16 taxels x 3)" in checks["model pads"].found
    assert "vt-train build" in checks["model pads"].fix
    assert "model pads" not in {c.part for c in _check_model(base_config())}


@pytest.mark.asyncio
async def test_a_4x6_robot_collects_builds_and_recognises_and_each_model_fits_its_pads(
        tmp_path, caplog):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    data, models = tmp_path / "data-4x6", tmp_path / "models-4x6"
    cfg = with_4x6_pads(base_config())
    async with FakeVLM(model="fake-vlm") as fake, \
            SimRobot("stainless_cube", seed=21, cfg=cfg) as robot:
        # Collect: the person puts each object the prompt names in the gripper.
        def person(message: str) -> None:
            if message.startswith("place the "):
                robot.world.place(message.split()[2])

        t0 = time.perf_counter()
        report = await collect_plan(robot.runtime_config(cfg), load_plan(plan), data, person)
        print(f"collect: {len(LABELS)} classes x 2 presses in {time.perf_counter() - t0:.1f} s")
        assert report.complete and not report.failed
        presses = sorted(data.rglob(f"*{recording.SUFFIX}"))
        assert len(presses) == 2 * len(LABELS)
        for path in presses:
            rec = recording.load(path)
            assert rec.channels == 144 and rec.sensor_model == "XR1946"
            assert PadLayout.of_recording(rec.extra, rec.channels) == LAYOUT_4X6
            assert rec.extra["peak_level"] > rec.threshold  # pressed, not idle noise
        index = json.loads((data / "dataset.json").read_text())
        assert index["origin"]["sensor"]["model"] == "XR1946"
        # More presses into it from 4 x 4 pads: refused before anything moves.
        with pytest.raises(ConfigError, match=r"wood_cube_000\.press\.npz was pressed with 2 "
                           r"pads of 4 x 6 taxels, \[sensor\] gives 2 pads of 4 x 4 taxels"):
            await collect_plan(robot.runtime_config(base_config()), load_plan(plan), data,
                               None)

        # Build: the model's input channels come from the presses.
        t0 = time.perf_counter()
        rc = await asyncio.to_thread(train_main, [
            "build", "--data", str(data), "--out", str(models), "--max-epochs", str(EPOCHS),
            "-q"])
        print(f"vt-train build: {time.perf_counter() - t0:.1f} s")
        assert rc == 0
        model = load_model(models)
        assert model.encoder.channels == 144
        assert model.manifest["encoder"]["input_shape"] == ["batch", 25, 144]
        assert model.manifest["sensor_layout"] == {"pads": 2, "taxels_per_pad": 24,
                                                   "taxel_rows": 4}
        assert model_ref(models).layout.text() == "144 channels (2 pads x 24 taxels x 3)"

        # Recognise: the daemon loads the 4 x 6 model and a recognition ends done.
        live = Path(shutil.copytree(models, tmp_path / "live-models"))
        run = replace(with_4x6_pads(base_config(fake.base_url)),
                      runtime=replace(base_config().runtime, models_dir=str(live)))
        async with Daemon(robot, run, tmp_path / "state") as d:
            # The operator page's live view gets the grid to draw: 4 rows of 6.
            frames = await sse_frames(d.http, d.url + "/v1/tactile", 0.5)
            last = frames[-1][1]
            assert (last["rows"], last["cols"]) == (4, 6)
            assert [len(p[axis]) for p in last["pads"] for axis in "xyz"] == [24] * 6
            robot.world.place("wood_cube")
            fake.script(Reply(label="wood_cube"))
            status, ep = await d.post("/v1/recognize", {"candidates": list(LABELS),
                                                        "wait": True})
            print(f"recognition: {ep['status']}, top-k {[t['label'] for t in ep['topk']]}")
            assert status == 200 and ep["status"] == "done", ep
            assert ep["label"] == "wood_cube" and {t["label"] for t in ep["topk"]} <= \
                set(LABELS)
            assert robot.dxl.torque_enables >= 1

            # The exports split the channels into two pads of 24 taxels.
            mcap = await asyncio.to_thread(mcaplog.export_episode, d.store, ep["id"],
                                           tmp_path / "episode.mcap")
            with mcap.open("rb") as fh:
                frames = [json.loads(m.data) for _, ch, m in make_reader(fh).iter_messages(
                    topics=["/tactile/raw"])]
            assert frames and all(len(f["pads"]) == 2 for f in frames)
            assert {len(p["z"]) for f in frames for p in f["pads"]} == {24}
            dest = await asyncio.to_thread(lerobot.export_dataset,
                                           lerobot.from_episodes(d.store, [ep["id"]]),
                                           tmp_path / "episode.lerobot")
            info = json.loads((Path(dest) / "meta" / "info.json").read_text())
            names = info["features"]["observation.tactile"]["names"]
            assert len(names) == 144 and names[-1] == "pad1_taxel23_z"

            # The shipped 4 x 4 model put in its place: SIGHUP's reload refuses it, and the
            # 4 x 6 one goes on answering.
            shutil.rmtree(live)
            shutil.copytree(ROOT / "models", live)
            caplog.set_level(logging.ERROR, "edge.runtime.lifecycle")
            assert await d.runtime.reload() is False
            assert "reload refused" in caplog.text and "expects 96 channels" in caplog.text
            assert d.runtime.model.digest == model_ref(models).digest

    # The 4 x 6 model on a robot with 4 x 4 pads: refused at start, torque never on.
    async with SimRobot("stainless_cube", seed=22, cfg=base_config()) as robot4:
        cfg4 = robot4.runtime_config(base_config())
        cfg4 = replace(cfg4, runtime=replace(cfg4.runtime, models_dir=str(models),
                                             state_dir=str(tmp_path / "state4")))
        with pytest.raises(StartError) as err:
            async with assemble(cfg4):
                pytest.fail("the daemon started with a model for other pads")
        print(err.value)
        assert "expects 144 channels (2 pads x 24 taxels x 3)" in str(err.value)
        assert "gives 96 (2 pads x 16 taxels x 3)" in str(err.value)
        assert "vt-train build" in str(err.value)
        assert robot4.dxl.torque_enables == 0


@pytest.mark.asyncio
async def test_the_shipped_4x4_model_on_the_4x6_robot_exits_2_in_one_line_torque_never_on(
        tmp_path):
    pads = load_config(SIM_4X6).sensor
    async with SimRobot("stainless_cube", seed=23, cfg=with_4x6_pads(base_config())) as robot:
        code, err = await vt_edge_run(tmp_path, robot, {"sensor": {
            "model": pads.model, "taxels_per_pad": pads.taxels_per_pad,
            "taxel_rows": pads.taxel_rows}})
        print(f"exit {code}, stderr:\n{err}")
        assert code == 2
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("vt-edge: model "), lines
        assert "expects 96 channels (2 pads x 16 taxels x 3)" in lines[0]
        assert "the sensor [sensor] gives 144 (2 pads x 24 taxels x 3)" in lines[0]
        assert "build a model from this robot's presses (vt-train build)" in lines[0]
        assert robot.dxl.torque_enables == 0
        assert torque_registers(robot, base_config()) == {0}


def test_a_4x6_press_recording_names_its_pads_and_replays_as_them(tmp_path):
    """The virtual recorder on 4 x 6 pads: 144 channels, its layout in the metadata (a 4 x 4
    recording names none, as before), and `sim serve --replay` serves it as 2 x 24 taxels."""
    cfg = with_4x6_pads(sim_config())
    rec = record_press("wood_cube", 4, cfg=cfg).recording
    assert rec.channels == 144 and rec.extra["layout"] == {
        "pads": 2, "taxel_rows": 4, "taxels_per_pad": 24}
    path = recording.save(rec, tmp_path / f"wood_cube_000{recording.SUFFIX}")
    replay = load_replay(path)
    assert (replay.sensors, replay.taxels) == (2, 24)
    four = record_press("wood_cube", 4).recording
    assert four.channels == 96 and "layout" not in four.extra
    assert PadLayout.of_recording(four.extra, four.channels) == XR1944
    # At the press's peak a 25 mm cube loads the 4 x 6 grid's middle (its face spans 5.3 of
    # the 6 columns, 4.7 mm each): the outer columns less than the inner ones.
    change = rec.frames.astype(float) - rec.tare
    z = change[int(np.argmax(np.linalg.norm(change, axis=1)))].reshape(2, 4, 6, 3)[..., 2]
    print(f"4x6 z change at the peak (counts), pad 0:\n{np.round(z[0])}")
    for pad in z:
        assert (pad > 0).sum() >= 20
        assert pad[:, 2:4].mean() > pad[:, [0, 5]].mean()


def test_a_model_for_other_pads_with_the_same_channel_count_is_refused():
    from edge.core.model import ModelLayout
    from edge.runtime.startcheck import model_mismatch

    two_pads = base_config().sensor  # 2 pads x 16 taxels = 96 channels
    assert model_mismatch(two_pads, ModelLayout(96, 2, 16)) is None
    assert model_mismatch(two_pads, ModelLayout(96)) is None  # a manifest naming no pads
    why = model_mismatch(two_pads, ModelLayout(96, 1, 32))
    assert why is not None and "1 pad x 32 taxels" in why
