"""Collect mode (a collection plan, resumed, interrupted, with failed presses and photos;
refused beside a running daemon) against the emulated robot."""

import asyncio
import hashlib
import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest

from edge.core import preprocess, recording, tomledit
from edge.core.errors import ConfigError
from edge.lab import collect as collect_mod
from edge.lab.collect import CollectReport, collect, collect_plan
from edge.lab.plan import load_plan
from edge.lab.stack import http_json
from edge.runtime import lifecycle
from edge.sim.catalogue import DATASETS
from edge.sim.fake_vlm import FakeVLM, Reply
from edge.sim.robot import SimRobot
from edge.sim.xela_server import Fault
from tests.support import processes
from tests.support.daemon import CUBE, QUICK_OBJECT, ROOT, Daemon, base_config, fast_config
from tests.support.processes import COMMAND_TIMEOUT_S, VT_EDGE, Output, clean_env
from tests.support.waits import wait_until

PLAN = """
[dataset]
name = "lab_food"
recorder = "test"
presses = 2
val = ["wood_cube"]

[[class]]
label = "otedama"
description = "otedama (a small Japanese cloth beanbag filled with beans)"
photo = true

[[class]]
label = "wood_cube"
description = "wood cube"
x_th = 0.003
"""


def write_plan(tmp_path: Path, text: str = PLAN, name: str = "plan.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def digests(out: Path) -> dict[str, str]:
    return {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(out.rglob("*")) if p.is_file() and p.name != "dataset.json"}


def person(robot: SimRobot, placed: list[str], asked: list[str] | None = None):
    """The prompt's answer: the person puts the object the prompt names in the gripper
    (``asked`` keeps each request to place one)."""
    def answer(message: str) -> None:
        if message.startswith("place the "):
            name = message.split()[2]
            if asked is not None:
                asked.append(message)
            robot.world.place(name)
            placed.append(name)
    return answer


@pytest.mark.asyncio
async def test_plan_collects_every_class_with_photos_and_resumes_up_to_n(tmp_path, caplog):
    plan_path = write_plan(tmp_path)
    out = tmp_path / "data"
    placed: list[str] = []
    asked: list[str] = []
    async with SimRobot("stainless_cube", seed=13, cfg=base_config()) as robot:
        cfg = robot.runtime_config(fast_config())  # shorter moves and tare: 7 presses
        t0 = time.monotonic()
        report = await collect_plan(cfg, load_plan(plan_path), out,
                                    person(robot, placed, asked))
        elapsed = time.monotonic() - t0
        print(f"2 classes x 2 presses in {elapsed:.1f} s; pieces placed "
              f"{robot.world.placements}")
        assert placed == ["otedama", "wood_cube"] and report.complete and not report.failed
        # On the emulated robot, each request says what its table holds and how to change it.
        print(asked)
        place = f"`vt-edge sim place NAME --url {robot.control_url}` puts another there"
        assert [m.split("(the emulated table holds ")[1] for m in asked] == [
            f"stainless_cube; {place}), then Enter ", f"otedama; {place}), then Enter "]
        # The plan's wood_cube at 0.003 against the shipped model's 0.004 (1.33x) is said,
        # once; otedama at [press] x_th, the model's own, is not.
        x_th = [r.getMessage() for r in caplog.records if "references were pressed at" in
                r.getMessage()]
        print(x_th)
        assert x_th == [f"wood_cube's x_th ({plan_path}) = 0.003 is 0.75 times the x_th = "
                        "0.004 the model's references were pressed at (more than 1.25x either "
                        "way): presses at another threshold embed elsewhere. Use the model's "
                        "value, or this robot's calibrated one (`vt-edge calibrate threshold`) "
                        "with a model built from presses at it"]
        # The person placed each object once; the emulated robot put a fresh piece back
        # before each later press of it.
        assert robot.world.placements >= 1 + 2 * 2
        index = json.loads((out / "dataset.json").read_text())
        assert index["dataset"] == "lab_food"
        assert index["plan_sha256"] == hashlib.sha256(plan_path.read_bytes()).hexdigest()
        assert index["origin"]["kind"] == "emulated" and index["origin"]["recorder"] == "test"
        assert index["origin"]["sensor"]["model"] == "XR1944"
        assert isinstance(index["recorder"], str) and "test" in index["recorder"]
        classes = {c["label"]: c for c in index["classes"]}
        rate = classes["otedama"].pop("rate_hz")
        print(f"otedama's stream rate over its crop windows: {rate} frames/s")
        assert 100 < rate < 135  # the emulator's 125 Hz
        assert classes["otedama"] == {
            "label": "otedama", "split": "train", "x_th": cfg.press.x_th, "presses": 2,
            "photo": True, "failed": [],
            "description": "otedama (a small Japanese cloth beanbag filled with beans)"}
        assert classes["wood_cube"]["split"] == "val" and classes["wood_cube"]["x_th"] == 0.003
        for label, x_th in (("otedama", cfg.press.x_th), ("wood_cube", 0.003)):
            files = sorted((out / label).glob("*.press.npz"))
            assert [f.name for f in files] == [f"{label}_000.press.npz",
                                               f"{label}_001.press.npz"]
            for f in files:
                rec = recording.load(f)
                assert rec.label == label and rec.threshold == x_th
                assert rec.extra["stop_latency_s"] > 0
        photos = sorted((out / "otedama").glob("*.jpg"))
        assert [p.name for p in photos] == ["otedama_000.jpg", "otedama_001.jpg"]
        assert all(p.read_bytes()[:3] == b"\xff\xd8\xff" for p in photos)
        assert not list((out / "wood_cube").glob("*.jpg"))
        assert not list(out.rglob("*.tmp"))

        # Run again: nothing to do. Then 3 per class: one more each, numbered on.
        before = digests(out)
        again = await collect_plan(cfg, load_plan(plan_path), out, None)
        assert again.kept == [] and again.complete
        more = write_plan(tmp_path, PLAN.replace("presses = 2", "presses = 3"), "more.toml")
        # (placing each object: the table still holds the last class's)
        third = await collect_plan(cfg, load_plan(more), out, person(robot, placed))
        assert [p.name for p in third.kept] == ["otedama_002.press.npz",
                                                "wood_cube_002.press.npz"]
        after = digests(out)
        assert {k: after[k] for k in before} == before  # nothing rewritten
        assert (out / "otedama" / "otedama_002.jpg").exists()

        # A plan whose threshold differs from the kept presses' is refused, naming a file.
        other = write_plan(tmp_path, PLAN.replace("x_th = 0.003", "x_th = 0.0035"), "o.toml")
        with pytest.raises(ConfigError, match=r"wood_cube_000\.press\.npz was pressed at "
                                              r"x_th 0\.003, the plan .* says 0\.0035"):
            await collect_plan(cfg, load_plan(other), out, None)


@pytest.mark.asyncio
async def test_a_100_hz_stream_is_measured_kept_and_said_by_doctor_and_the_daemon(tmp_path,
                                                                                   caplog):
    from edge.lab import dataset
    from edge.ops import doctor

    plan = load_plan(write_plan(tmp_path, """
[dataset]
name = "slow_pads"
recorder = "test"
presses = 2
test = true

[[class]]
label = "wood_cube"
description = "wood cube"
"""))
    out = tmp_path / "data"
    # Some xela_server installs send about 100 frames/s; the shipped model's grid is 125 Hz.
    async with SimRobot("wood_cube", seed=17, cfg=base_config(), rate_hz=100.0) as robot:
        cfg = robot.runtime_config(fast_config())
        report = await collect_plan(cfg, plan, out, None)
        assert report.complete and len(report.kept) == 2
        for path in report.kept:
            rate = recording.load(path)
            print(f"{path.name}: {preprocess.recording_rate(rate)}")
        entry = json.loads((out / "dataset.json").read_text())["classes"][0]
        print(f"dataset.json: wood_cube at {entry['rate_hz']} frames/s")
        assert 80 < entry["rate_hz"] < 110
        text = dataset.format_summary(dataset.summarize(out))
        print(text)
        row = re.search(r"^wood_cube\s.*\s(\d+\.\d)$", text, re.M)
        assert "rate Hz" in text and row and float(row.group(1)) == entry["rate_hz"]
        # One rate in the dataset: no problem, but a line to look at against the 125 Hz grid.
        # 100 Hz is 20 % off the grid; the emulator on a loaded host sends a little faster or
        # slower (101.5 frames/s, 19 %, seen in a make test).
        assert re.search(r"^  wood_cube: stream at \d+\.\d frames/s is (1[5-9]|2\d) % off 125 Hz",
                         text, re.M) and "no problems" in text
        # Files for people follow the umask (the test's own, typically 022: 0644).
        umask = os.umask(0)
        os.umask(umask)
        assert all(p.stat().st_mode & 0o777 == 0o666 & ~umask
                   for p in [out / "dataset.json", *report.kept])

        xela = {c.part: c for c in await doctor._check_xela(cfg, 1.0)}
        check = xela["xela rate"]
        print(f"doctor: {check.level} {check.found} -> {check.fix}")
        assert str(check.level) == "WARN" and "expected 125" in check.found
        assert "% off 125 Hz" in check.fix and "xela_server's configuration" in check.fix

        async with Daemon(robot, base_config(), tmp_path / "state") as d:
            # The episode keeps the press's rate.
            _, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            print("episode's press:", ep["press"])
            assert 80 < ep["press"]["window_rate_hz"] < 110
            assert 80 < ep["press"]["press_rate_hz"] < 110
            warned = ("the tactile stream at", "the model's grid")
            said = lambda: [r.getMessage() for r in caplog.records  # noqa: E731
                            if all(w in r.getMessage() for w in warned)]
            await wait_until(said, 30, "the daemon's warning about the stream's rate",
                             interval_s=0.1)
            await asyncio.sleep(2 * lifecycle.RATE_CHECK_S)
            print("the daemon:", said())
            assert len(said()) == 1 and "% off 125 Hz" in said()[0]


@pytest.mark.asyncio
async def test_failed_presses_are_retried_then_the_class_is_skipped(tmp_path, monkeypatch):
    monkeypatch.setattr(collect_mod, "MAX_FAILED_IN_A_ROW", 3)
    plan = load_plan(write_plan(tmp_path, PLAN.replace("photo = true", "photo = false")))
    out = tmp_path / "data"
    async with SimRobot("otedama", seed=14, cfg=base_config()) as robot:
        cfg = robot.runtime_config(fast_config())  # shorter moves and tare: 8 presses
        report = CollectReport()

        async def stream(silent_until) -> None:
            robot.xela.fault = Fault.SILENT
            await wait_until(silent_until, 60, "the failed presses")
            robot.xela.fault = Fault.NONE

        # Two stale presses of the first class, then the stream comes back: retried, kept.
        server = asyncio.create_task(stream(lambda: report.failed >= 2))
        await asyncio.sleep(0.5)  # stale by now
        await collect_plan(cfg, plan, out, None, report=report)
        await server
        assert report.complete and report.failed == 2 and not report.skipped
        index = json.loads((out / "dataset.json").read_text())
        failed = {c["label"]: c["failed"] for c in index["classes"]}
        print("failed presses:", failed)
        assert [f["result"] for f in failed["otedama"]] == ["stale", "stale"]
        assert failed["wood_cube"] == []

        # A stream that stays silent: the first class is skipped after 3, the run goes on.
        more = load_plan(write_plan(tmp_path, PLAN.replace("presses = 2", "presses = 3")
                                    .replace("photo = true", "photo = false"), "more.toml"))
        report = CollectReport()
        server = asyncio.create_task(stream(lambda: "otedama" in report.skipped))
        await asyncio.sleep(0.5)
        await collect_plan(cfg, more, out, None, report=report)
        await server
        print(f"skipped {report.skipped}, have {report.have}, failed {report.failed}")
        assert report.skipped == ["otedama"] and not report.complete
        assert report.have == {"otedama": 2, "wood_cube": 3}
        assert len(list((out / "otedama").glob("*.press.npz"))) == 2


@pytest.mark.asyncio
async def test_collect_writes_labelled_recordings(tmp_path):
    cfg = fast_config()  # shorter moves and tare
    prompts = []
    async with SimRobot("otedama", seed=11, cfg=base_config()) as robot:
        files = await collect(robot.runtime_config(cfg), "otedama", 2, tmp_path,
                              prompt=prompts.append)
        # A rerun whose first frame comes late (a second, where the start used to wait a
        # fixed half second): its origin still names the pads, so it is not refused as
        # another robot's dataset.
        robot.xela.fault = Fault.SILENT
        asyncio.get_running_loop().call_later(1.0, setattr, robot.xela, "fault", Fault.NONE)
        more = await collect(robot.runtime_config(cfg), "otedama", 3, tmp_path, prompt=None)
    origin = json.loads((tmp_path / "dataset.json").read_text())["origin"]
    print(prompts, origin)
    assert len(more) == 1 and origin["sensor"]["model"] == "XR1944"
    assert len(files) == 2 and len(prompts) == 2
    assert "place the otedama" in prompts[0] and "move the otedama" in prompts[1]
    for f in files:
        rec = recording.load(f)
        assert rec.label == "otedama" and rec.source == "sim"
        assert rec.extra["stop_latency_s"] > 0


@pytest.mark.asyncio
async def test_a_bus_watchdog_trip_between_presses_is_cleared_not_a_failed_press(tmp_path):
    # A host stall past the watchdog (300 ms) trips the motors; the next press clears the
    # trip first, as the daemon's do, instead of failing every press after it.
    cfg = base_config()
    prompts = []

    def stall(message: str) -> None:
        prompts.append(message)
        for motor_id in (11, 12, 13, 14, 15):
            robot.dxl.trip_watchdog(motor_id)

    async with SimRobot("otedama", seed=16, cfg=cfg) as robot:
        files = await collect(robot.runtime_config(cfg), "otedama", 2, tmp_path, prompt=stall)
    print(prompts)
    assert len(files) == 2 and len(prompts) == 2


@pytest.fixture(scope="module")
def sim_serve(tmp_path_factory):
    """``vt-edge sim serve`` and its runtime configuration (quicker arm moves)."""
    env = clean_env()
    with processes.sim_serve(tmp_path_factory.mktemp("sim"), "otedama", env, {
            "sensor": {"stale_timeout_s": 0.25}, "runtime": {"move_time_s": 0.2}}) as config:
        yield config, env


def start_collect(config: Path, env: dict, *args: str) -> tuple[subprocess.Popen, Output]:
    return processes.start([*VT_EDGE, "collect", "--config", str(config), *args], env,
                           stdin=True)


def test_ctrl_c_mid_plan_keeps_what_was_pressed_and_the_rerun_goes_on(sim_serve, tmp_path):
    config, env = sim_serve
    plan = write_plan(tmp_path, PLAN.replace("presses = 2", "presses = 3")
                      .replace("photo = true", "photo = true\npresses = 4"))
    out = tmp_path / "data"
    args = ("--plan", str(plan), "--out", str(out), "--no-prompt")
    proc, output = start_collect(config, env, *args)
    output.wait_for("otedama press 2/4:")
    proc.send_signal(signal.SIGINT)  # during the third press (or its photo, or its file)
    t0 = time.monotonic()
    rc = proc.wait(30)
    print(f"exit {rc} {time.monotonic() - t0:.2f} s after SIGINT\n{output.text}")
    assert rc == 130 and "interrupted: kept" in output.text
    assert "run the same command again" in output.text
    control = processes.control_url(config)
    assert http_json("GET", f"{control}/object")["force_n"] == 0.0  # the gripper let go
    kept = sorted((out / "otedama").glob("*.press.npz"))
    assert 2 <= len(kept) <= 3 and not list(out.rglob("*.tmp"))
    for i, path in enumerate(kept):  # whole, numbered from 0, each with its photo
        assert path.name == f"otedama_{i:03d}.press.npz" and recording.load(path).label
        assert (out / "otedama" / f"otedama_{i:03d}.jpg").exists()
    index = json.loads((out / "dataset.json").read_text())
    assert [c["label"] for c in index["classes"]] == ["otedama", "wood_cube"]
    before = digests(out)

    proc, output = start_collect(config, env, *args)
    assert proc.wait(COMMAND_TIMEOUT_S) == 0, output.text
    print(output.text)
    assert f"otedama: {len(kept)}/4 pressed" in output.text
    for label, n in (("otedama", 4), ("wood_cube", 3)):
        names = sorted(p.name for p in (out / label).glob("*.press.npz"))
        assert names == [f"{label}_{i:03d}.press.npz" for i in range(n)]
    after = digests(out)
    assert {k: after[k] for k in before if k.endswith(".npz")} == {
        k: v for k, v in before.items() if k.endswith(".npz")}


def test_ctrl_c_at_the_prompt_exits_at_once(sim_serve, tmp_path):
    config, env = sim_serve
    proc, output = start_collect(config, env, "--plan", str(write_plan(tmp_path)), "--out",
                                 str(tmp_path / "data"))
    output.wait_for("place the otedama")
    rc, took = processes.interrupt(proc, output)
    assert rc == 130 and "interrupted: kept 0 presses" in output.text
    assert took < 10.0


@pytest.mark.asyncio
async def test_collect_beside_the_daemon_is_refused_and_the_daemon_unaffected(tmp_path):
    async with FakeVLM(model="fake-vlm") as fake, \
            SimRobot(QUICK_OBJECT, seed=15, cfg=base_config()) as robot:
        fake.script(Reply(label="raw_kiri_mochi"), Reply(label="raw_kiri_mochi"))
        async with Daemon(robot, base_config(fake.base_url), tmp_path / "state") as d:
            status, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            assert status == 200 and ep["status"] == "done", ep
            config = tmp_path / "run.toml"
            tomledit.update(ROOT / "configs" / "sim.toml", config, {
                "sensor": {"url": robot.xela.url}, "bus": {"port": robot.dxl.port}})
            proc = await asyncio.create_subprocess_exec(
                *VT_EDGE, "collect", "--config", str(config), "--label", QUICK_OBJECT,
                "--presses", "1", "--out", str(tmp_path / "data"), "--no-prompt", cwd=ROOT,
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
            stdout, stderr = await asyncio.wait_for(proc.communicate(), COMMAND_TIMEOUT_S)
            lines = stderr.decode().strip().splitlines() + stdout.decode().strip().splitlines()
            print(f"exit {proc.returncode}: {lines}")
            assert proc.returncode == 2 and len(lines) == 1
            assert "in use by pid" in lines[0] and "systemctl stop vtzero-edge" in lines[0]
            assert not (tmp_path / "data").exists()
            status, ep = await d.post("/v1/recognize", {"candidates": CUBE, "wait": True})
            print("the daemon's next recognition:", ep["status"], ep.get("error"))
            assert status == 200 and ep["status"] == "done", ep
            assert d.devices.bus.fault is None


def test_summary_flags_a_mixed_threshold_a_gap_a_late_stop_and_a_short_class(tmp_path,
                                                                              capsys):
    from dataclasses import replace

    import numpy as np

    from edge.cli import main
    from edge.lab import dataset
    from edge.lab.record import record_press

    out = tmp_path / "data"
    # Presses of the virtual-clock recorder (the daemon's press controller), as collect
    # writes them: otedama at 0.004 but one at 0.003 (an earlier --x-th); wood_cube short.
    recs = [record_press("otedama", seed, x_th=x).recording
            for seed, x in ((1, 0.004), (2, 0.004), (3, 0.004), (4, 0.003))]
    for i, rec in enumerate(recs):
        recording.save(rec, recording.press_path(out, "otedama", i))
    gap = recs[1]
    keep = ~((gap.recv_time > gap.t_stop + 0.1) & (gap.recv_time < gap.t_stop + 0.2))
    recording.save(replace(gap, frames=gap.frames[keep], recv_time=gap.recv_time[keep],
                           sensor_time=gap.sensor_time[keep], seq=gap.seq[keep]),
                   recording.press_path(out, "otedama", 1))
    late = recs[2]
    loud = late.tare + 40.0 * (late.frames - late.tare)
    recording.save(replace(late, frames=np.clip(loud, 0, 65535).astype(np.uint16)),
                   recording.press_path(out, "otedama", 2))
    cube = record_press("wood_cube", 5).recording
    recording.save(cube, recording.press_path(out, "wood_cube", 0))
    index = dataset.new_index("lab_food", "test", {"kind": "emulated", "recorder": "test",
                                                   "robot": None, "sensor": None}, "0" * 64)
    index["classes"] = [
        {"label": "otedama", "split": "train", "description": "otedama", "x_th": 0.004,
         "presses": 4, "photo": False, "failed": [{"result": "stale", "message": "x"}]},
        {"label": "wood_cube", "split": "val", "description": "wood cube", "x_th": 0.004,
         "presses": 2, "photo": False, "failed": []}]
    dataset.write_index(out, index)

    summary = dataset.summarize(out)
    print(dataset.format_summary(summary))
    oted = summary.classes[0]
    assert oted.thresholds == [0.003, 0.004] and oted.failed == {"stale": 1}
    assert summary.problems == [
        "otedama: mixes thresholds 0.003, 0.004 (otedama_003.press.npz unlike the class's "
        "0.004)", "wood_cube: 1 of 2 planned presses"]
    flags = {p.path.name: p.flags for p in oted.presses}
    assert flags["otedama_000.press.npz"] == ()
    assert len(flags["otedama_001.press.npz"]) == 1
    assert flags["otedama_001.press.npz"][0].startswith("stream gap of 1")
    assert "stopped late" in flags["otedama_002.press.npz"][0]
    # A rigid reference squeezed by the hold far past x_th after a timely stop is no late stop.
    marble = tmp_path / "marble" / "glass_marble_000.press.npz"
    recording.save(record_press("glass_marble", 6).recording, marble)
    checked = dataset.check_press(marble)
    print(f"glass marble: peak {checked.peak / 0.004:.0f}x x_th over the press")
    assert checked.flags == ()
    assert "unlike the class's 0.004" in flags["otedama_003.press.npz"][0]
    peaks = [p.peak for p in oted.presses]
    assert all(0.003 < p < 0.02 for i, p in enumerate(peaks) if i != 2)
    assert all(p.stop_latency_ms > 0 for p in oted.presses)
    assert main(["dataset", "summary", str(out)]) == 1
    text = capsys.readouterr().out
    assert "origin: the emulated robot, pressed by test" in text and "problems:" in text

    # Made whole (the odd press pressed again at 0.004, wood_cube once more): exit 0; a
    # plan asking for more makes it short again.
    recording.save(record_press("otedama", 7).recording, recording.press_path(out, "otedama", 3))
    recording.save(record_press("wood_cube", 6).recording,
                   recording.press_path(out, "wood_cube", 1))
    assert main(["dataset", "summary", str(out)]) == 0
    plan = write_plan(tmp_path, PLAN.replace("presses = 2", "presses = 3"))
    assert main(["dataset", "summary", str(out), "--plan", str(plan)]) == 1
    assert "wood_cube: 2 of 3 planned presses" in capsys.readouterr().out


def test_summary_with_a_plan_shows_classes_not_collected_yet_as_the_plan_says(tmp_path):
    from edge.lab import dataset

    summary = dataset.summarize(tmp_path / "data", load_plan(write_plan(tmp_path)))
    text = dataset.format_summary(summary)
    print(text)
    assert [(c.label, c.split, c.x_th, c.planned, len(c.presses)) for c in summary.classes] == [
        ("otedama", "train", None, 2, 0), ("wood_cube", "val", 0.003, 2, 0)]
    assert re.search(r"^wood_cube\s+val\s+0/2\s+0\s+0\.003\s", text, re.M)
    assert summary.problems == ["otedama: 0 of 2 planned presses",
                                "wood_cube: 0 of 2 planned presses"]


def test_the_shipped_paper_plan_and_the_readme_examples_load(tmp_path):
    import re

    plan = load_plan(ROOT / "configs" / "plan-paper-reference.toml")
    ref = DATASETS["reference"]
    assert [(c.label, c.description, c.split, c.x_th, c.presses) for c in plan.classes] == [
        (o.name, o.description, o.split, o.x_th, 10) for o in ref]
    assert sum(c.split == "val" for c in plan.classes) == 5 and len(plan.classes) == 32
    blocks = re.findall(r"```toml\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    examples = [load_plan(write_plan(tmp_path, b, f"readme{i}.toml"))
                for i, b in enumerate(blocks) if "[dataset]" in b]
    assert [p.name for p in examples] == ["lab_reference", "lab_food"]
    assert {c.split for c in examples[1].classes} == {"test"}
    assert all(c.photo for c in examples[1].classes)
    assert examples[0].get("gelatin_soft").x_th == 0.003


@pytest.mark.asyncio
async def test_a_plan_of_another_dataset_is_refused_before_the_robot_is_opened(tmp_path):
    """A test plan collected into the reference plan's directory would take over its name and
    plan hash (what vt-train build and table1 report): refused in one line, nothing written."""
    from edge.lab import dataset

    out = tmp_path / "data"
    dataset.write_index(out, dataset.new_index("lab_reference", "test", {
        "kind": "emulated", "recorder": "test", "robot": None, "sensor": None}, "0" * 64))
    before = (out / "dataset.json").read_bytes()
    plan = load_plan(write_plan(tmp_path))  # lab_food
    # No robot: the refusal comes before the devices open (they would fail on this config).
    with pytest.raises(ConfigError) as caught:
        await collect_plan(base_config(), plan, out, None)
    print(caught.value)
    assert str(caught.value) == (
        f"{out / 'dataset.json'} is dataset 'lab_reference', the plan ({plan.source}) is "
        "'lab_food': collect each plan into its own --out (a test set's directory goes to "
        "vt-train build --unseen and vt-train table1 --unseen)")
    assert (out / "dataset.json").read_bytes() == before and sorted(out.iterdir()) == [
        out / "dataset.json"]


@pytest.mark.parametrize("change, message", [
    (("presses = 2", "presses = 0"), "[dataset]: presses = 0: must be 1..1000"),
    (("x_th = 0.003", "x_th = 2.0"), "class 'wood_cube': x_th = 2.0: must be in (0, 1)"),
    (("x_th = 0.003", "x_th = 0.003\nfoo = 1"), "class 'wood_cube': unknown key(s) foo"),
    (('description = "wood cube"', 'description = "hard wood cube"'),
     "description of 'wood_cube' 'hard wood cube' says how the object feels (hard)"),
    (('val = ["wood_cube"]', 'val = ["wood"]'), "val names wood, which no [[class]] has"),
    (('val = ["wood_cube"]', 'val = ["wood_cube"]\ntest = true'), "a test set"),
    (('label = "otedama"', 'label = "wood_cube"'), "class 'wood_cube': listed twice"),
    (('photo = true', 'photo = "yes"'), "class 'otedama': photo = 'yes': must be true or"),
])
def test_a_bad_plan_is_refused_naming_the_field_and_the_class(tmp_path, change, message):
    path = write_plan(tmp_path, PLAN.replace(*change))
    with pytest.raises(ConfigError) as caught:
        load_plan(path)
    print(caught.value)
    assert message in str(caught.value) and str(path) in str(caught.value)
