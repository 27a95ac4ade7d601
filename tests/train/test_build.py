"""``vt-train build``: a collected dataset (the collect format, pressed by the robot's press
controller on the emulated robot) to a model directory the daemon loads as it is and takes
with SIGHUP; resumable; refusing mixed thresholds and origins within a class."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import time
from dataclasses import replace
from pathlib import Path

import pytest

from edge.core import recording
from edge.core.errors import ModelError, RecordingError
from edge.core.model import load_model, model_ref
from edge.sim.robot import SimRobot
from tests.support.daemon import QUICK_OBJECT, ROOT, Daemon, base_config
from tests.support.lab_data import ORIGIN, PLAN_SHA256, write_lab_dataset
from tests.support.waits import wait_until
from train.cli import main
from train.eval import evaluate
from train.learn.data import STD_FLOOR_FRACTION
from train.learn.trainer import Progress
from train.ship.build import (
    EMBEDDINGS,
    BuildConfig,
    Steps,
    build,
    choice_markdown,
    choice_of,
    partial_dir,
    read_dataset,
)

REFERENCE = {"wood_cube": ("train", 3, False), "sponge_cube": ("train", 3, False),
             "otedama": ("train", 3, False), "marshmallow": ("val", 3, False)}
TEST = {"raw_kiri_mochi": ("test", 3, True), "boiled_kiri_mochi": ("test", 3, True)}
EPOCHS = 3


pytestmark = pytest.mark.usefixtures("logging_as_found")


@pytest.fixture(scope="module")
def lab_food(tmp_path_factory) -> Path:
    return write_lab_dataset(tmp_path_factory.mktemp("lab") / "lab_food", REFERENCE | TEST)


def quick(data: Path, out: Path, **kw) -> BuildConfig:
    """The shipped embedding, without the choice (tested on its own)."""
    return BuildConfig(data=data, out=out, max_epochs=EPOCHS, **({"embedding": "shipped"} | kw))


@pytest.mark.asyncio
async def test_build_gives_a_directory_the_daemon_takes_with_sighup(lab_food, tmp_path):
    models = Path(shutil.copytree(ROOT / "models", tmp_path / "models"))
    cfg = base_config()
    # The daemon shares this process with the build's training (torch, in a thread): on a
    # loaded host the stream stalled 0.53 s right after it and failed the press as stale,
    # which is not what this test is about.
    cfg = replace(cfg, runtime=replace(cfg.runtime, models_dir=str(models)),
                  sensor=replace(cfg.sensor, stale_timeout_s=1.0))
    async with SimRobot(QUICK_OBJECT, seed=31, cfg=base_config()) as robot, \
            Daemon(robot, cfg, tmp_path / "state") as d:
        _, health = await d.get("/healthz")
        t0 = time.perf_counter()
        rc = await asyncio.to_thread(main, ["build", "--data", str(lab_food), "--out",
                                            str(models), "--max-epochs", str(EPOCHS),
                                            "--embedding", "shipped", "-q"])
        print(f"vt-train build: {time.perf_counter() - t0:.1f} s")
        assert rc == 0
        assert not partial_dir(models).exists()
        assert (tmp_path / "models.previous" / "manifest.json").exists()
        os.kill(os.getpid(), signal.SIGHUP)

        async def reloaded():
            _, h = await d.get("/healthz")
            return h["model_digest"] != health["model_digest"]

        await wait_until(reloaded, 30, "the daemon took the built model", interval_s=0.1)
        assert d.runtime.model.digest == model_ref(models).digest
        _, ep = await d.post("/v1/recognize", {"candidates": list(TEST), "wait": True})
        assert ep["status"] == "not_configured", ep.get("error")  # no VLM: touch only
        assert {t["label"] for t in ep["topk"]} <= set(REFERENCE) and len(ep["topk"]) == 3

    model = load_model(models)  # hashes verified, prompts included
    manifest = model.manifest
    assert manifest["origin"] == ORIGIN and manifest["plan_sha256"] == PLAN_SHA256
    assert {f"prompts/{m}.txt" for m in ("vision_tactile", "vision_only", "tactile_only")} \
        <= set(manifest["files"])
    assert manifest["prompts"]["vision_tactile"]["sha256"] == \
        manifest["files"]["prompts/vision_tactile.txt"]["sha256"]
    assert len(model.database) == 4 * 3 * 5 and model.database.offsets == [0, 1, 2, 3, 4]
    assert manifest["training"]["dataset"]["test_classes"] == list(TEST)
    # Each class's stream rate as pressed (the virtual robot's 125 Hz), beside its x_th.
    assert set(manifest["class_rate_hz"]) == set(REFERENCE)
    assert all(abs(r - 125) < 1 for r in manifest["class_rate_hz"].values())
    assert manifest["training"]["vq"]["config"]["model"]["decoder"] == "teacher"
    assert manifest["training"]["std_floor_fraction"] == STD_FLOOR_FRACTION  # recorded
    assert manifest["sequences"] is None  # a robot build, whatever OUT held before
    assert manifest["encoder"]["parity"]["max_abs_diff_z"] < 1e-5
    report = json.loads((models / "eval" / "eval.json").read_text())
    rows = {(r["variant"], r["space"]) for r in report["rows"]}
    assert {("vq", "z"), ("baseline", "z")} <= rows
    assert sorted(report["unseen_classes"]) == sorted(TEST)
    md = (models / "eval" / "eval.md").read_text()
    assert "| baseline | z |" in md and "## The encoder against the trivial baseline" in md


def test_an_interrupted_build_resumes_and_a_rerun_skips_what_is_done(lab_food, tmp_path,
                                                                     monkeypatch):
    out = tmp_path / "models"
    cfg = quick(lab_food, out, variants=("beta",))

    def interrupted(*_a, **_k):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(evaluate, "evaluate", interrupted)
        with pytest.raises(KeyboardInterrupt):
            build(cfg, Progress(enabled=False))
    assert not out.exists()  # nothing half-built where the daemon looks
    state = json.loads((partial_dir(out) / "build-state.json").read_text())
    assert set(state) == {"train vq", "train beta", "export", "database"}

    first = build(cfg, Progress(enabled=False))
    assert first["timings"]["steps_skipped"] == ["train vq", "train beta", "export", "database"]
    assert (out / "training" / "beta" / "checkpoint.pt").exists()
    again = build(cfg, Progress(enabled=False))
    assert again["timings"]["steps_skipped"] == ["train vq", "train beta", "export",
                                                  "database", "eval"]
    assert again["files"] == first["files"]
    # Another setting trains again: the key is the inputs' hash.
    other = build(replace(cfg, seed=1), Progress(enabled=False))
    assert "train vq" not in other["timings"]["steps_skipped"]


def _rewrite(path: Path, **changes) -> None:
    recording.save(replace(recording.load(path), **changes), path)


def test_mixed_thresholds_or_origins_within_a_class_are_refused_by_name(lab_food, tmp_path):
    data = Path(shutil.copytree(lab_food, tmp_path / "mixed"))
    _rewrite(data / "otedama" / "otedama_002.press.npz", threshold=0.2)
    with pytest.raises(RecordingError, match=r"class 'otedama' mixes thresholds x_th: "
                       r"0\.004 \(otedama_000, otedama_001\); 0\.2 \(otedama_002\)"):
        build(quick(data, tmp_path / "m"), Progress(enabled=False))
    _rewrite(data / "otedama" / "otedama_002.press.npz", threshold=0.004)
    _rewrite(data / "wood_cube" / "wood_cube_001.press.npz", sensor_model="XR1946")
    with pytest.raises(RecordingError, match="class 'wood_cube' mixes origins: .*XR1944.*"
                       r"XR1946 \(wood_cube_001\)"):
        build(quick(data, tmp_path / "m"), Progress(enabled=False))
    assert not (tmp_path / "m").exists()
    index = json.loads((data / "dataset.json").read_text())
    index["origin"]["kind"] = "real"
    (data / "dataset.json").write_text(json.dumps(index))
    with pytest.raises(RecordingError,
                       match=r"origin kind must be 'emulated' or 'robot', got 'real'"):
        build(quick(data, tmp_path / "m"), Progress(enabled=False))


def test_a_dataset_class_without_a_label_is_refused_naming_the_file(lab_food, tmp_path):
    data = Path(shutil.copytree(lab_food, tmp_path / "unlabelled"))
    index = json.loads((data / "dataset.json").read_text())
    del index["classes"][1]["label"]
    (data / "dataset.json").write_text(json.dumps(index))
    with pytest.raises(RecordingError, match=r"dataset\.json: classes\[1\] has no 'label'"):
        read_dataset(data, progress=False)


def test_a_null_origin_reads_as_the_emulated_robot(lab_food, tmp_path):
    data = Path(shutil.copytree(lab_food, tmp_path / "null_origin"))
    index = json.loads((data / "dataset.json").read_text())
    index["origin"] = None
    (data / "dataset.json").write_text(json.dumps(index))
    origin = read_dataset(data, progress=False).origin
    assert origin["kind"] == "emulated" and origin["recorder"] == index["recorder"]


def test_a_corrupt_build_state_runs_every_step_again(tmp_path, caplog):
    (tmp_path / "build-state.json").write_text('{"train vq": {"key": ')  # cut short
    steps = Steps(tmp_path)
    assert steps.state == {}
    assert "build-state.json: unreadable" in caplog.text
    assert steps.run("export", "k", [], lambda: {"n": 1})["n"] == 1 and steps.ran == ["export"]
    assert json.loads((tmp_path / "build-state.json").read_text())["export"]["key"] == "k"


# --- vt-train db add ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def lab_model(lab_food, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("built") / "models"
    build(quick(lab_food, out), Progress(enabled=False))
    return out


@pytest.fixture
def model_dir(lab_model, tmp_path) -> Path:
    return Path(shutil.copytree(lab_model, tmp_path / "models"))


def add(model: Path, recordings: Path, label: str, *flags: str) -> int:
    return main(["db", "add", "--model", str(model), "--recordings", str(recordings),
                 "--label", label, "--description", f"{label.replace('_', ' ')} (a food)",
                 *flags])


def test_db_add_refuses_a_press_it_holds_whatever_its_file_name(model_dir, lab_food, tmp_path,
                                                                caplog):
    raw = lab_food / "raw_kiri_mochi"
    assert add(model_dir, raw, "raw_kiri_mochi", "--allow-test") == 0
    before = load_model(model_dir).database
    assert len(before) == 4 * 3 * 5 + 3 * 5
    assert add(model_dir, raw, "raw_kiri_mochi", "--allow-test") == 2
    err = caplog.text
    assert "3 of these presses are in the database already (the same frames" in err
    assert ("raw_kiri_mochi_000.press.npz is raw_kiri_mochi/raw_kiri_mochi_000.press.npz"
            in err and "Nothing added" in err)
    # The same press copied under another name (and a reference press of the build) is the
    # same press.
    copies = tmp_path / "copies"
    copies.mkdir()
    shutil.copyfile(raw / "raw_kiri_mochi_001.press.npz", copies / "mochi_900.press.npz")
    shutil.copyfile(lab_food / "otedama" / "otedama_000.press.npz",
                    copies / "otedama_777.press.npz")
    caplog.clear()
    assert add(model_dir, copies, "mochi", "--relabel") == 2
    err = caplog.text
    print(err)
    assert "2 of these presses are in the database already" in err
    assert "mochi_900.press.npz is raw_kiri_mochi/raw_kiri_mochi_001.press.npz" in err
    assert "otedama_777.press.npz is otedama/otedama_000.press.npz" in err
    assert len(load_model(model_dir).database) == len(before)


def test_db_add_refuses_a_test_split_unless_allowed_and_table1_says_so(model_dir, lab_food,
                                                                      tmp_path, caplog):
    raw = lab_food / "raw_kiri_mochi"
    assert add(model_dir, raw, "raw_kiri_mochi") == 2
    err = caplog.text
    assert (f"3 presses of raw_kiri_mochi are split test in {lab_food / 'dataset.json'}"
            in err and "--allow-test" in err)
    assert "raw_kiri_mochi" not in load_model(model_dir).database.labels
    assert add(model_dir, lab_food, "raw_kiri_mochi", "--relabel") == 2  # the whole dataset
    assert add(model_dir, raw, "raw_kiri_mochi", "--allow-test") == 0
    manifest = load_model(model_dir).manifest
    assert manifest["test_presses_added"] == [
        {"label": "raw_kiri_mochi", "presses": 3, "dataset": str(lab_food / "dataset.json")}]
    out = tmp_path / "table1"
    assert main(["table1", "--model-dir", str(model_dir), "--unseen", str(lab_food),
                 "--work", str(tmp_path / "work"), "--out", str(out), "--limit", "1",
                 "-q"]) == 0
    md = (out / "table1.md").read_text()
    assert ("**The database holds test presses**: 3 presses of raw_kiri_mochi from the test "
            f"split of {lab_food / 'dataset.json'}") in md


def test_db_add_refuses_another_label_unless_relabel(model_dir, lab_food, caplog):
    raw = lab_food / "raw_kiri_mochi"
    assert add(model_dir, raw, "cherry_tomato") == 2
    err = caplog.text
    assert "3 presses labelled 'raw_kiri_mochi' in their metadata, not 'cherry_tomato'" in err
    assert "--relabel" in err
    assert "cherry_tomato" not in load_model(model_dir).database.labels
    assert add(model_dir, raw, "kiri_mochi", "--relabel", "--allow-test") == 0
    db = load_model(model_dir).database
    assert "kiri_mochi" in db.labels and "raw_kiri_mochi" not in db.labels


def test_db_add_refuses_an_unlike_threshold_unless_forced(model_dir, lab_food, tmp_path,
                                                          caplog):
    odd = Path(shutil.copytree(lab_food / "boiled_kiri_mochi", tmp_path / "odd"))
    for path in odd.glob("*.press.npz"):
        _rewrite(path, threshold=0.2)
    assert add(model_dir, odd, "boiled_kiri_mochi") == 2
    err = caplog.text
    assert "made at x_th 0.2; the database's classes at 0.004" in err and "--force" in err
    assert add(model_dir, odd, "boiled_kiri_mochi", "--force") == 0
    manifest = load_model(model_dir).manifest
    assert manifest["class_x_th"]["boiled_kiri_mochi"] == 0.2
    _rewrite(next(odd.glob("*.press.npz")), threshold=0.004)
    assert add(model_dir, odd, "other_mochi", "--relabel", "--force") == 2
    assert "mixes thresholds x_th" in caplog.text


BLOCK_TORCH_AND_ONNX = """
import importlib.abc, sys

class Blocked(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("torch", "onnx"):
            raise ModuleNotFoundError(f"No module named {name!r} (blocked by the test)")
        return None

sys.meta_path.insert(0, Blocked())
from train.cli import main
rc = main(sys.argv[1:])
assert not {"torch", "onnx"} & set(sys.modules), sorted({"torch", "onnx"} & set(sys.modules))
sys.exit(rc)
"""


def test_db_add_works_on_an_edge_only_install(model_dir, lab_food):
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", BLOCK_TORCH_AND_ONNX, "db", "add", "--model", str(model_dir),
         "--recordings", str(lab_food / "raw_kiri_mochi"), "--label", "raw_kiri_mochi",
         "--description", "raw kiri mochi (a Japanese rice cake)", "--allow-test"],
        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "raw_kiri_mochi" in load_model(model_dir).database.labels


# --- Table I and Fig. 6 on the lab's data ---------------------------------------------------

def test_table1_and_fig6_on_a_lab_named_set_describe_its_data(lab_model, lab_food, tmp_path,
                                                              capsys):
    out = tmp_path / "table1"
    assert main(["table1", "--model-dir", str(lab_model), "--unseen", str(lab_food),
                 "--paper-set", "lab_food=foodreplica", "--work", str(tmp_path / "work"),
                 "--out", str(out), "-q"]) == 0
    report = json.loads((out / "table1.json").read_text())
    assert report["sets"] == [{"name": "lab_food", "paper_set": "foodreplica",
                               "origin": ORIGIN, "presses": 6}]
    rows = {(m["model"], r["condition"]): r for m in report["models"] for r in m["rows"]}
    lab = rows[("simulated-vlm", "vq_top3")]["sets"]["lab_food"]
    # The test classes are the questions, their labels the candidates.
    assert lab["n"] == 6 and lab["confusion"]["rows"] == list(TEST)
    assert lab["paper"] == 58.9  # GPT-4V on FoodReplica, beside the set mapped to it
    assert rows[("simulated-vlm-vision-led", "vision_only")]["sets"]["lab_food"]["paper"] == 39.0
    assert "beta_top3" in report["missing"] and not any(c == "beta_top3" for _, c in rows)
    md = (out / "table1.md").read_text()
    print(md)
    assert "| lab_food (as FoodReplica) | paper: FoodReplica |" in md
    assert "decoder `teacher` (the paper's" in md
    assert ("real presses by the robot `lab-arm-1` with a XELA XR1944 (XR1944-0001) pressed "
            "by a lab member") in md
    # The advice names the data the model was built from, not a placeholder.
    assert "`vt-train build --data " in md and "DATASET" not in md
    assert f"--out {lab_model} --variant beta`" in md
    assert "vt-train release" not in md and "simulated presses" not in md
    assert "images: lab_food: photos beside the presses" in md  # found without --images

    fig = tmp_path / "fig6"
    assert main(["fig6", "--model-dir", str(lab_model), "--unseen", str(lab_food),
                 "--paper-set", "lab_food=foodreplica", "--sizes", "0,3", "--draws", "2",
                 "--max-epochs", "2", "--work", str(tmp_path / "fwork"), "--out", str(fig),
                 "-q"]) == 0
    r = json.loads((fig / "fig6.json").read_text())
    assert [row["size"] for row in r["sizes"]] == [0, 3]
    assert r["sizes"][0]["sets"]["lab_food"]["paper"] == 53.6  # vision only, FoodReplica
    assert r["data"]["reference"]["directory"] == str(lab_food)  # from the manifest
    md = (fig / "fig6.md").read_text()
    assert "decoder `teacher`: the paper's" in md and "lab_food (as FoodReplica)" in md
    assert "real presses by the robot `lab-arm-1`" in md and "photos beside the presses" in md


# --- the embedding deployed, chosen by held-out evidence --------------------------------------

def test_a_build_chooses_its_embedding_on_the_validation_classes_and_says_why(lab_food,
                                                                              tmp_path):
    out = tmp_path / "models"
    t0 = time.perf_counter()
    manifest = build(quick(lab_food, out, embedding=None, seeds=2), Progress(enabled=False))
    print(f"build with the choice over 2 seeds: {time.perf_counter() - t0:.1f} s")
    choice = manifest["metrics"]["choice"]
    figures = choice["figures"]
    assert set(figures) == set(EMBEDDINGS) and choice["seeds"] == 2
    for name, f in figures.items():
        val = f["loo_1nn_val_classes"]
        assert len(val["seeds"]) == 2 and 0 <= val["min"] <= val["mean"] <= val["max"] <= 1
        assert len(f["top3_consistency"]["seeds"]) == 2  # the test classes' consistency
        print(name, val, f["top3_consistency"]["mean"])
    assert figures["mean"]["loo_1nn_val_classes"]["min"] == \
        figures["mean"]["loo_1nn_val_classes"]["max"]  # nothing random in a channel mean
    # The best challenger replaces the shipped network only on a lead beyond the noise.
    val = {name: f["loo_1nn_val_classes"] for name, f in figures.items()}
    challenger = choice["challenger"]
    assert val[challenger]["mean"] == max(v["mean"] for n, v in val.items() if n != "shipped")
    assert choice["validation_presses"] == 3
    assert choice["noise_floor"] == pytest.approx(0.5 / 3 ** 0.5)
    lead = val[challenger]["mean"] - val["shipped"]["mean"]
    replaces = lead > choice["noise_floor"] and val[challenger]["min"] > val["shipped"]["max"]
    winner = choice["winner"]
    assert winner == (challenger if replaces else "shipped")
    assert choice["margin"] == pytest.approx(
        val[winner]["mean"] - val[choice["runner_up"]]["mean"])
    # The winner is what the directory deploys, served as its kind.
    assert manifest["encoder"]["embedding"] == winner
    assert manifest["encoder"]["kind"] == ("mean" if winner == "mean" else "onnx")
    assert load_model(out).manifest["encoder"]["embedding"] == winner
    md = (out / "eval" / "eval.md").read_text()
    section = md[md.index("## The embedding deployed"):]
    print(section)
    assert f"| {winner} (deployed) |" in section
    assert all(f"| {name}" in section for name in EMBEDDINGS)
    if winner != "shipped":
        assert f"`{winner}` replaced `shipped`, {choice['margin']:.3f} above it" in section
    elif lead > 0:
        assert "within the noise: kept the shipped network" in section
    else:
        assert f"`shipped` won, {choice['margin']:.3f} above `{challenger}`" in section
        assert ("beyond the seed spread" in section) == choice["beyond_spread"]
    assert "--seeds 2" in manifest["created_by"]
    # A rerun trains nothing again.
    again = build(quick(lab_food, out, embedding=None, seeds=2), Progress(enabled=False))
    assert {"train vq", "train paper", "train vq seed 1", "train paper seed 1", "choose"} \
        <= set(again["timings"]["steps_skipped"])


def test_the_choice_without_a_validation_class_is_refused_before_any_training(lab_food,
                                                                             tmp_path):
    data = Path(shutil.copytree(lab_food, tmp_path / "no_val"))
    index = json.loads((data / "dataset.json").read_text())
    for c in index["classes"]:
        if c["split"] == "val":
            c["split"] = "train"
    (data / "dataset.json").write_text(json.dumps(index))
    with pytest.raises(ModelError, match=r"no validation class .*--embedding"):
        build(quick(data, tmp_path / "m", embedding=None), Progress(enabled=False))
    assert not (partial_dir(tmp_path / "m") / "training").exists()


def scores(shipped, paper, mean):
    """Each candidate's validation figure per seed (the consistency alike throughout)."""
    return {name: {"loo_1nn_val_classes": v, "top3_consistency": [0.5] * len(v)}
            for name, v in (("shipped", shipped), ("paper", paper), ("mean", mean))}


def test_the_choice_says_whether_a_difference_is_beyond_the_seed_spread():
    apart = choice_of(scores([0.9, 0.8], [0.5, 0.6], [0.7, 0.7]), 2, 25)
    assert apart["winner"] == "shipped" and apart["runner_up"] == "mean"
    assert apart["beyond_spread"] and apart["margin"] == pytest.approx(0.15)
    close = choice_of(scores([0.9, 0.6], [0.5, 0.6], [0.7, 0.7]), 2, 25)
    assert close["winner"] == "shipped" and not close["beyond_spread"]
    assert "does not tell them apart" in choice_markdown(close)
    one = choice_of(scores([0.9], [0.5], [0.7]), 1, 25)
    assert not one["beyond_spread"] and "one seed" in choice_markdown(one)
    tie = choice_of(scores([0.7], [0.7], [0.7]), 1, 25)
    assert tie["winner"] == "shipped"  # the candidates' order breaks a full tie
    with pytest.raises(ModelError, match="no validation class"):
        choice_of(scores([], [], []), 1, 0)


def test_a_challenger_replaces_the_shipped_network_only_on_a_lead_beyond_the_noise():
    # One seed of 5 validation presses: the floor is 0.5 / sqrt(5) = 0.224. One press (0.2)
    # is the lead build saw come and go between runs; two presses (0.4) are beyond it.
    one_press = choice_of(scores([0.8], [0.6], [1.0]), 1, 5)
    print(one_press["noise_floor"])
    assert one_press["noise_floor"] == pytest.approx(0.2236, abs=1e-4)
    assert one_press["winner"] == "shipped" and one_press["challenger"] == "mean"
    assert one_press["kept_within_noise"] and one_press["lead"] == pytest.approx(0.2)
    md = choice_markdown(one_press)
    assert "| shipped (deployed) |" in md
    assert "`mean` led `shipped` by 0.200" in md
    assert "within the noise: kept the shipped network" in md
    two_presses = choice_of(scores([0.6], [0.6], [1.0]), 1, 5)
    assert two_presses["winner"] == "mean" and two_presses["runner_up"] == "shipped"
    assert not two_presses["kept_within_noise"]
    assert "`mean` replaced `shipped`, 0.400 above it" in choice_markdown(two_presses)
    # Over seeds, a lead above the floor still needs the challenger's lowest seed above the
    # network's highest.
    spread = choice_of(scores([0.4, 0.96], [0.5, 0.5], [0.95, 0.95]), 2, 25)
    assert spread["lead"] > spread["noise_floor"] and spread["winner"] == "shipped"
    assert spread["kept_within_noise"]
    clear = choice_of(scores([0.4, 0.5], [0.6, 0.7], [0.95, 0.95]), 2, 25)
    assert clear["winner"] == "mean" and clear["beyond_spread"]
    # The best challenger by its mean is the one compared: here the paper's network.
    paper = choice_of(scores([0.2, 0.3], [0.9, 1.0], [0.6, 0.6]), 2, 25)
    assert paper["winner"] == "paper" and paper["runner_up"] == "shipped"
