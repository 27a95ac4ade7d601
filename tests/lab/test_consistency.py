"""The robot's presses embed where the dataset's do: a reduced `vt-edge sim consistency`
(the full one, 8 objects, 3 runs, writes models/eval/consistency.md), and the comparison and
report on embeddings whose answer is known."""

import json
import shutil

import numpy as np
import pytest

from edge.cli import main
from edge.core import tomledit
from edge.core.errors import EdgeError
from edge.lab.consistency import (
    OBJECT_RATIO_MAX,
    Report,
    compare,
    dataset_transport,
    run_consistency,
)
from edge.sim.virtual import Transport
from tests.support.daemon import ROOT

NAMES = ("a", "b", "c", "d")


def _cloud(rng, centre, n, sd=0.1):
    return centre + sd * rng.standard_normal((n, centre.size))


def test_presses_from_the_dataset_distribution_give_a_ratio_near_one():
    rng = np.random.default_rng(1)
    centres = {n: rng.standard_normal(16) for n in NAMES}
    runs = [compare({n: _cloud(rng, c, 10) for n, c in centres.items()},
                    {n: _cloud(rng, c, 20) for n, c in centres.items()}, seed)
            for seed in range(3)]
    report = Report(runs, 10, 20, {"p50": 0.2, "p99": 0.3}, 1.0)
    print([round(r.median_ratio, 3) for r in runs])
    # Same distribution on both sides: the daemon presses' distance to a centroid they did
    # not make is a little above the dataset's own (in-sample) spread, sqrt(21/19) ~ 1.05.
    assert all(0.9 <= r.median_ratio <= 1.25 for r in runs)
    assert report.passed and all(r.reid_daemon == 1.0 for r in runs)


def test_presses_off_their_object_are_flagged_in_the_run_they_happen():
    rng = np.random.default_rng(2)
    centres = {n: rng.standard_normal(16) for n in NAMES}

    def run(seed, shift):
        daemon = {n: _cloud(rng, c + (shift if n == "b" else 0.0), 10)
                  for n, c in centres.items()}
        return compare(daemon, {n: _cloud(rng, c, 20) for n, c in centres.items()}, seed)

    runs = [run(0, 0.0), run(1, 0.5), run(2, 0.0)]
    report = Report(runs, 10, 20, {"p50": 0.2, "p99": 0.3}, 1.0)
    ratios = {o["name"]: o for o in report.to_json()["objects"]}
    print({n: [round(x, 2) for x in o["ratio_runs"]] for n, o in ratios.items()})
    assert runs[1].above == ["b"] and runs[0].above == runs[2].above == []
    assert ratios["b"]["ratio_max"] > OBJECT_RATIO_MAX > ratios["b"]["ratio_min"]
    assert not runs[1].passed and runs[0].passed and not report.passed
    # The median over objects stays near one: one object off does not move it much.
    assert report.median_ratio < 1.3
    doc = report.to_json()
    assert doc["objects_above_max"] == ["b"] and doc["passed"] is False
    assert [r["seed"] for r in doc["runs"]] == [0, 1, 2]
    md = report.markdown("vt-edge sim consistency")
    assert "| 2 (1) |" in md and "NOT met" in md


def test_the_recorder_presses_with_the_transport_of_the_models_dataset(tmp_path):
    manifest = json.loads((ROOT / "models" / "manifest.json").read_text())
    assert dataset_transport(ROOT / "models") == Transport(
        **manifest["training"]["dataset"]["transport"])
    shutil.copy(ROOT / "models" / "manifest.json", tmp_path / "manifest.json")
    manifest["training"]["dataset"]["transport"]["stop_latency_p50_ms"] = 0.3
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(EdgeError, match=r"training\.dataset\.transport .*stop_latency_p50_ms"):
        dataset_transport(tmp_path)


def test_bad_counts_are_refused_before_anything_starts(capsys):
    assert main(["sim", "consistency", "--runs", "0", "--objects", "macaron", "canele"]) == 2
    assert "--runs must be at least 1, got 0" in capsys.readouterr().err


@pytest.mark.slow
def test_daemon_presses_sit_with_the_dataset_presses_of_their_object(tmp_path):
    # Quicker arm moves (0.1 s, not 0.5): the tactile data do not depend on how fast the arm
    # travels, and the twelve presses' moves took 6 of its 51 s.
    config = tmp_path / "sim.toml"
    tomledit.update(ROOT / "configs" / "sim.toml", config, {"runtime": {"move_time_s": 0.1}})
    report = run_consistency(("raw_kiri_mochi", "boiled_kiri_mochi", "raw_kabocha_squash"),
                             daemon_presses=2, dataset_presses=8, runs=2,
                             models=ROOT / "models", config=config, out=tmp_path / "out")
    print(report.markdown("test"))
    # Generous bounds for 2 presses per object and run (the full report's ratios for these
    # three: 0.4-1.5): a second copy of the press protocol put the daemon's presses 3-4 times
    # the dataset's spread away.
    doc = json.loads((tmp_path / "out" / "consistency.json").read_text())
    assert report.median_ratio <= 2.5
    assert doc["reid_daemon"] >= doc["loo_dataset"] - 0.34
    assert [r["seed"] for r in doc["runs"]] == [0, 1]
    for obj in doc["objects"]:
        assert len(obj["ratio_runs"]) == 2
        assert obj["ratio_min"] <= obj["ratio"] <= obj["ratio_max"]
    # New presses in each run: the dataset's spreads differ between the runs.
    spreads = [[o["dataset_spread"] for o in r["objects"]] for r in doc["runs"]]
    assert spreads[0] != spreads[1]
    md = (tmp_path / "out" / "consistency.md").read_text()
    assert "ratio per run" in md and "What noise alone gives" in md
    # The recorder against itself: one ratio per run, and near one.
    null = doc["recorder_null"]["median_ratio_runs"]
    assert len(null) == 2 and all(0.3 < x < 2.5 for x in null)
