import json
import subprocess
import sys

import numpy as np

from train.eval import evaluate
from train.learn.model import PAPER
from train.learn.trainer import Progress
from train.ship.release import ReleaseConfig, release

from .conftest import PRESSES, SEED


def test_auc_and_pairs():
    assert evaluate.auc(np.array([0.0, 1.0]), np.array([2.0, 3.0])) == 1.0
    assert evaluate.auc(np.array([2.0, 3.0]), np.array([0.0, 1.0])) == 0.0
    assert evaluate.auc(np.array([1.0]), np.array([1.0])) == 0.5
    rng = np.random.default_rng(0)
    sep = evaluate.pair_auc(rng.normal(0, 1, (10, 4)), rng.normal(5, 1, (10, 4)))
    assert sep["auc"] == 1.0 and sep["separation"] > 3
    assert evaluate.pairs_of(["raw_kiri_mochi", "boiled_kiri_mochi", "canele",
                              "resin_replica_canele", "konjac"]) == [
        ("canele", "canele", "resin_replica_canele"),
        ("kiri_mochi", "raw_kiri_mochi", "boiled_kiri_mochi")]


def test_release_writes_model_eval_files_and_manifest(released):
    for name in evaluate.FILES:
        assert (released / "eval" / name).stat().st_size > 0, name
    manifest = json.loads((released / "manifest.json").read_text())
    assert set(manifest["files"]) == {"encoder.onnx", "database.npz", "database.json"}
    m = manifest["metrics"]
    assert 0.0 <= m["kiri_mochi_auc"] <= 1.0
    assert set(m["comparison"]) == {"vq/z", "vq/z_q", "vq_paper/z", "vq_paper/z_q",
                                    "vq_zeros/z", "vq_zeros/z_q", "beta/z", "baseline/z"}
    assert manifest["training"]["vq"]["config"]["model"]["decoder"] == "teacher"
    # The paper's configuration is trained and measured beside the shipped one.
    assert manifest["training"]["vq"]["config"]["model"] | PAPER \
        == manifest["training"]["vq_paper"]["config"]["model"]
    assert manifest["encoder"]["outputs"]["z"] == ["batch", 16]
    assert manifest["training"]["vq_zeros"]["config"]["model"]["decoder"] == "zeros"
    assert manifest["database"]["references"] == 32 * PRESSES * 5
    assert manifest["database"]["offsets"] == [0, 1, 2, 3, 4]
    assert manifest["encoder"]["parity"]["max_abs_diff_z"] < 1e-5
    assert {"torch", "onnxruntime", "vtzero"} <= set(manifest["versions"])
    assert manifest["origin"] == {"kind": "emulated", "robot": None, "sensor": None,
                                  "recorder": manifest["training"]["dataset"]["recorder"]}
    report = json.loads((released / "eval" / "eval.json").read_text())
    assert len(report["rows"]) == 8
    assert report["references"] == 32 * PRESSES * 5 and report["query_offset"] == 0
    md = (released / "eval" / "eval.md").read_text()
    assert "| vq | z |" in md and "| vq_zeros | z |" in md and "| baseline | z |" in md
    assert "## The encoder against the trivial baseline" in md
    assert "## The shipped configuration against the paper's" in md
    base = next(r for r in report["rows"] if r["variant"] == "baseline")
    assert set(base["unseen_neighbours"]) == set(report["unseen_classes"])
    assert "`vq`: VQ-VAE, the paper's decoder" in md
    for block in md.split("\n\n"):  # every Markdown table has as many cells as its header
        rows = [line for line in block.splitlines() if line.startswith("|")]
        assert len({line.count("|") for line in rows}) <= 1, block
    retrieval = json.loads((released / "eval" / "retrieval.json").read_text())
    assert len(retrieval) == 26 * PRESSES and len(retrieval[0]["topk"]) == 3
    total = sum(p.stat().st_size for p in released.rglob("*") if p.is_file())
    assert total < 1_000_000


def test_release_is_deterministic(released, work, tmp_path):
    out = tmp_path / "again"
    release(ReleaseConfig(out=out, work=work / "run_b", recordings=work / "recordings",
                          seed=SEED, presses=PRESSES, unseen_presses=PRESSES, max_epochs=3,
                          workers=2), Progress(enabled=False))
    a = json.loads((released / "manifest.json").read_text())
    b = json.loads((out / "manifest.json").read_text())
    assert a["metrics"] == b["metrics"]
    assert a["files"] == b["files"]  # same encoder and database, byte for byte


def test_cli_runs_as_a_module():
    out = subprocess.run([sys.executable, "-m", "train", "--help"], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0 and "release" in out.stdout


def test_cli_eval_and_db_add(released, model_copy, work, tmp_path, capsys):
    from train.cli import main

    rec = work / "recordings"
    assert main(["eval", "--model", str(released), "--reference", str(rec / "reference"),
                 "--unseen", str(rec / "cube"), "--out", str(tmp_path / "ev")]) == 0
    assert (tmp_path / "ev" / "confusion.png").exists()
    assert "kiri mochi AUC" in capsys.readouterr().out
    model_dir = model_copy
    assert main(["db", "add", "--model", str(model_dir), "--recordings",
                 str(rec / "cube" / "raw_kiri_mochi"), "--label", "dried_mochi",
                 "--description", "a hard dried rice cake"]) == 2
    assert "says how the object feels (hard)" in capsys.readouterr().err
    assert main(["db", "add", "--model", str(model_dir), "--recordings",
                 str(rec / "cube" / "raw_kiri_mochi"), "--label", "dried_mochi",
                 "--description", "dried kiri mochi (a Japanese rice cake)",
                 "--relabel"]) == 0
    assert main(["db", "add", "--model", str(tmp_path / "nowhere"), "--recordings",
                 str(rec / "cube"), "--label", "x", "--description", "y"]) == 2


def test_loo_leaves_out_every_reference_of_the_press():
    # Two classes, two presses each, five references per press: the query's own five
    # references sit on it (distance 0) and must never be its neighbours.
    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0], [10.0, 0.0]])
    labels = ["a", "a", "b", "b"]
    queries = np.array([centres[0], centres[0] + 4.0, centres[1], centres[1]])
    refs = np.repeat(queries, 5, axis=0) + rng.normal(0, 0.01, (20, 2))
    knn = evaluate.loo_knn(queries, labels, refs=refs, per_press=5)
    # Press 1 of "a" sits 4 from "a"'s other press and further from "b": right; if its own
    # references counted, every press would be right trivially; here press 0 of "a" has
    # press 1 (at 4 + noise) as nearest, also "a".
    assert knn["loo_1nn"] == 1.0 and knn["loo_top3"] == 1.0
    # Move press 1 of "a" next to "b": now it is wrong, whatever its own references say.
    queries[1] = centres[1] + 0.5
    refs = np.repeat(queries, 5, axis=0)
    knn = evaluate.loo_knn(queries, labels, refs=refs, per_press=5)
    assert knn["loo_1nn"] == 0.5  # press 0 of "a" and press 1 of "a" both go to "b"
    import pytest
    with pytest.raises(ValueError, match="19 references for 4 presses x 5"):
        evaluate.loo_knn(queries, labels, refs=refs[:19], per_press=5)
