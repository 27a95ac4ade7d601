"""`vt-edge sim teaching` on a tiny configuration (2 unseen classes, k = 1, 2 fresh presses;
the full one writes models/eval/teaching/), and the figures it is made of on inputs whose
answer is known."""

import json

import pytest

from edge.cli import main
from edge.core import tomledit
from edge.core.model import load_model
from edge.lab.teaching_eval import agree_margin, roc_auc
from tests.support.daemon import ROOT


def test_roc_auc_counts_pairs_ordered_and_ties_half():
    assert roc_auc([3, 4], [1, 2]) == 1.0
    assert roc_auc([1, 2], [3, 4]) == 0.0
    assert roc_auc([100, 100], [100, 50]) == 0.75  # one tie of four pairs, three above
    assert roc_auc([2], [1, 2, 3]) == 0.5


def test_two_shares_may_differ_by_what_noise_allows():
    # Two shares of 1.0 from 10 presses each: one press either way (the continuity term).
    assert agree_margin(1.0, 10, 1.0, 10) == pytest.approx(0.1)
    # 0.5 of 10 against 0.5 of 10: 1.96 * sqrt(0.25 * 0.2) + 0.1.
    assert agree_margin(0.5, 10, 0.5, 10) == pytest.approx(0.5383, abs=1e-3)
    # More presses, less room.
    assert agree_margin(0.5, 100, 0.5, 100) < agree_margin(0.5, 10, 0.5, 10)


def test_a_class_of_the_model_is_refused_in_one_line(capsys):
    assert main(["sim", "teaching", "--classes", "wood_cube", "macaron"]) == 2
    err = capsys.readouterr().err
    assert "'wood_cube' is not an unseen class of the model" in err and "macaron" in err


def test_bad_counts_are_refused_before_anything_starts(capsys):
    assert main(["sim", "teaching", "--ks", "0", "--classes", "macaron"]) == 2
    assert "--ks must be presses of at least 1" in capsys.readouterr().err


def test_an_unknown_measurement_to_make_alone_is_refused_before_anything_starts(capsys):
    assert main(["sim", "teaching", "--only", "curve", "--classes", "macaron"]) == 2
    assert "teaching --only 'curve': one of familiarity" in capsys.readouterr().err


@pytest.mark.integration  # the recorder's presses and a daemon on the emulated robot: ~40 s
def test_teaching_moves_the_nearest_class_through_both_paths(tmp_path, capsys):
    # Quicker arm moves (0.1 s, not 0.5): the tactile data do not depend on how fast the arm
    # travels.
    config = tmp_path / "sim.toml"
    tomledit.update(ROOT / "configs" / "sim.toml", config, {"runtime": {"move_time_s": 0.1}})
    out = tmp_path / "out"
    rc = main(["sim", "teaching", "--classes", "konjac", "boiled_kiri_mochi",
               "--e2e-classes", "konjac", "boiled_kiri_mochi", "--ks", "1",
               "--fresh", "2", "--reference-presses", "2", "--held-out", "1",
               "--models", str(ROOT / "models"), "--config", str(config), "--out", str(out)])
    printed = capsys.readouterr().out
    print(printed)
    doc = json.loads((out / "teaching.json").read_text())
    md = (out / "teaching.md").read_text()
    assert rc == (0 if doc["end_to_end"]["agree"] else 1)
    assert md.strip() == printed.strip()
    assert "simulated, not a real one" in md and " min " in md
    curve = doc["curve"]
    assert [r["name"] for r in curve["classes"]] == ["konjac", "boiled_kiri_mochi"]
    for row in curve["classes"]:
        assert set(row["alone"]) == set(row["together"]) == {"1"}
        # Unknown, the presses land on some reference class, never the untaught one.
        assert row["k0_nearest"] and all(x["label"] != row["name"] for x in row["k0_nearest"])
        assert sum(x["share"] for x in row["k0_nearest"]) == pytest.approx(1.0)
    # One taught press moves the nearest class: some fresh press now finds its own class
    # (the recorder's presses are the same for a seed: 1 of 2 classes, both presses).
    assert curve["overall"]["alone"]["0"] == 0.0
    assert curve["overall"]["alone"]["1"] >= 0.25
    assert curve["overall"]["together"]["1"] >= 0.25
    vlm = curve["vlm"]["overall"]
    assert set(vlm) == {"0", "1_alone", "1_together"}
    assert all(0.0 <= v <= 1.0 for v in vlm.values())
    fam = doc["familiarity"]
    assert fam["unseen_presses"] == 2 * 3 and fam["held_out_presses"] == 32
    assert fam["baseline_reference_presses"] == 64
    assert set(fam["unseen_median_by_class"]) == {"konjac", "boiled_kiri_mochi"}
    # Chosen on FoodReplica (konjac) against half the known classes, reported on Cube
    # (boiled_kiri_mochi) against the other half, and all together.
    assert {k: v["presses"] for k, v in fam["splits"].items()} == {
        "choosing": [3, 16], "reporting": [3, 16], "all": [6, 32]}
    # The daemon's figure is the report's headline. How well it tells unseen presses apart is
    # the full measurement's (models/eval/teaching: 0.58 on 260 against 160 presses); on 6
    # against 32 it is noise (0.39 to 0.85 between models), so only its range is checked here,
    # and tests/core/test_familiarity.py checks the ranking on data whose answer is known.
    assert 0.0 <= fam["auc"] <= 1.0 and fam["auc"] == fam["splits"]["all"]["familiarity"]
    assert 0.0 <= fam["nearest_distance_auc"] <= 1.0
    assert 0.0 <= fam["embedding_ratio_auc"] <= 1.0
    # The daemon's figure, in the space its database allows; the report names it.
    assert fam["space"] == ("channel means" if load_model(ROOT / "models").database.feature
                            is not None else "embedding ratio")
    assert "familiarity (the daemon's)" in md
    assert 0.0 <= fam["baseline_auc"] <= 1.0
    e2e = doc["end_to_end"]
    assert [r["name"] for r in e2e["classes"]] == ["konjac", "boiled_kiri_mochi"]
    assert all(r["presses"] == [2, 2] for r in e2e["classes"])
    taught = e2e["seconds_per_taught_press"]
    assert len(taught["all"]) == 2 and 0 < taught["min"] <= taught["median"] <= taught["max"]
    # Taught through the daemon, a class is found again there (the recorder path's pooled
    # share here: 0.5).
    assert e2e["daemon"] >= 0.25
