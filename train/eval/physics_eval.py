"""The physics features (:mod:`train.learn.physics`) on the emulated robot's sets, beside the
shipped model and the trivial feature.

``python -m train.eval.physics_eval --out models/eval/physics`` evaluates, through
:func:`train.eval.evaluate.evaluate` (the same protocol and retrieval as ``eval.md``), the
shipped encoder, the trivial baseline, ``physics`` and ``mean+physics`` on the release's
reference set (LOO 1-NN, validation classes' 1-NN) and its unseen sets (top-3 consistency),
with a noise figure for each: the binomial standard error of a 1-NN share and, for
consistency, the spread of the mean over the unseen classes resampled (bootstrap). It also
measures what the stiffness feature assumes: how constant the gripper's closing speed is
before the stop, and how the feature ranks beside the Present Current the gripper draws
during the hold (which it does not read). Files: ``physics.md`` and ``physics.json`` in
``--out``, the evaluation's tables (``eval.md``, ``eval.json``) in ``--out/eval``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import spearmanr

from edge.core import preprocess, recording
from edge.core.atomic import atomic_write_text
from edge.core.errors import RecordingError
from edge.core.model import load_model
from train.eval import evaluate
from train.learn import physics
from train.learn.data import PressSet, Splits, load_presses

log = logging.getLogger(__name__)

VARIANTS = ("vq", "baseline", "physics", "mean+physics")
FIGURES = (("loo_1nn", "LOO 1-NN among reference classes"),
           ("loo_1nn_val_classes", "1-NN validation classes"),
           ("top3_consistency", "unseen top-3 consistency"))
BOOTSTRAP = 2000
# The closing phase read for the speed: the window's lead before the stop.
CLOSING_S = preprocess.DEFAULT_WINDOW.before_s


def closing_speed(rec: recording.Recording) -> tuple[float, float, float]:
    """The gripper's mean closing speed (m/s) over the ``CLOSING_S`` before the stop, its
    coefficient of variation between the gripper's samples, and the speed over the second
    half of that span relative to the first (1: no slowing as the load builds)."""
    t = rec.gripper_time - rec.t_stop
    sel = (t >= -CLOSING_S) & (t <= 0)
    t, w = t[sel], rec.gripper_width_m[sel]
    if len(t) < 4:
        raise RecordingError(f"{rec.label}: {len(t)} gripper samples in the {CLOSING_S:g} s "
                             "before the stop; the closing speed needs 4 at least")
    speed = -np.diff(w) / np.diff(t)
    mid = len(t) // 2
    first = (w[0] - w[mid]) / (t[mid] - t[0])
    second = (w[mid] - w[-1]) / (t[-1] - t[mid])
    return float(speed.mean()), float(speed.std() / speed.mean()), float(second / first)


def hold_current(rec: recording.Recording) -> float:
    """The median Present Current (mA) over the hold (the stop to ``physics.HOLD_S`` on)."""
    t = rec.gripper_time - rec.t_stop
    return float(np.median(rec.gripper_current_ma[(t > 0) & (t <= physics.HOLD_S)]))


def assumptions(reference: PressSet) -> dict[str, Any]:
    """The closing speed's constancy and the features' rank correlation with the hold's
    Present Current, over the reference presses."""
    recs = [recording.load(p) for p in reference.paths]
    speeds = np.array([closing_speed(r) for r in recs])
    current = np.array([hold_current(r) for r in recs])
    feats = physics.features(reference.inputs(0))
    return {
        "closing_speed_mm_s": {"median": float(np.median(speeds[:, 0]) * 1e3),
                               "min": float(speeds[:, 0].min() * 1e3),
                               "max": float(speeds[:, 0].max() * 1e3)},
        "closing_speed_cv": {"median": float(np.median(speeds[:, 1])),
                             "max": float(speeds[:, 1].max())},
        "second_half_over_first": {"median": float(np.median(speeds[:, 2])),
                                   "min": float(speeds[:, 2].min()),
                                   "max": float(speeds[:, 2].max())},
        "spearman_with_hold_current": {
            name: float(spearmanr(feats[:, i], current).statistic)
            for i, name in enumerate(physics.FEATURES)},
        "presses": len(recs),
    }


def noise(row: dict[str, Any], reference: PressSet, splits: Splits, seed: int
          ) -> dict[str, float]:
    """A standard error per figure of ``row``."""
    n_val = sum(reference.labels.count(c) for c in splits.val)
    p, pv = row["loo_1nn"], row.get("loo_1nn_val_classes")
    per_class = np.array([c["top3"] for c in row["consistency_per_class"].values()])
    rng = np.random.default_rng(seed)
    boot = per_class[rng.integers(0, len(per_class), (BOOTSTRAP, len(per_class)))].mean(1)
    return {"loo_1nn": float(np.sqrt(p * (1 - p) / len(reference))),
            "loo_1nn_val_classes": (float(np.sqrt(pv * (1 - pv) / n_val))
                                    if pv is not None else float("nan")),
            "top3_consistency": float(boot.std())}


def run(model_dir: Path, reference_dir: Path, unseen_dirs: list[Path], out: Path,
        command: str, seed: int = 0) -> dict[str, Any]:
    started = time.perf_counter()
    model = load_model(model_dir)
    splits = Splits.of_dataset(reference_dir)
    reference = load_presses(reference_dir, splits.classes).select(splits.classes)
    unseen = PressSet.concat(*(load_presses(d) for d in unseen_dirs))
    x_ref = np.concatenate([reference.x[:, o] for o in range(reference.x.shape[1])])
    codebook = model.database.codebook
    embedders = {"vq": (evaluate.onnx_embedder(model.encoder, codebook), codebook),
                 **{name: (make(x_ref), None)
                    for name, make in evaluate.FEATURE_EMBEDDERS.items()}}
    # The evaluation's tables are kept; its pictures and retrieval list are the shipped
    # model's, as in models/eval, so they are written aside and dropped.
    with tempfile.TemporaryDirectory() as scratch:
        report = evaluate.evaluate(embedders, reference, splits, unseen, scratch, seed=seed)
        (out / "eval").mkdir(parents=True, exist_ok=True)
        for name in ("eval.md", "eval.json"):
            atomic_write_text(out / "eval" / name, (Path(scratch) / name).read_text())
    rows = {r["variant"]: r for r in report["rows"] if r["space"] == "z"}
    result = {
        "command": command,
        "reference": {"presses": len(reference), "classes": len(reference.classes),
                      "val_classes": list(splits.val)},
        "unseen": {"presses": len(unseen), "classes": len(unseen.classes)},
        "features": list(physics.FEATURES),
        "variants": {v: {"title": evaluate.VARIANT_TITLES[v],
                         **{k: rows[v].get(k) for k, _ in FIGURES},
                         "se": noise(rows[v], reference, splits, seed)} for v in VARIANTS},
        "assumptions": assumptions(reference),
    }
    result["seconds"] = round(time.perf_counter() - started, 1)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "physics.json", json.dumps(result, indent=1, sort_keys=True) + "\n")
    atomic_write_text(out / "physics.md", markdown(result))
    return result


def markdown(r: dict[str, Any]) -> str:
    a = r["assumptions"]
    lines = [
        "# The press's physics on the emulated robot's sets", "",
        f"Command: `{r['command']}` ({r['seconds']:.0f} s).", "",
        f"Reference: {r['reference']['presses']} presses of {r['reference']['classes']} "
        f"classes ({len(r['reference']['val_classes'])} validation classes); unseen: "
        f"{r['unseen']['presses']} presses of {r['unseen']['classes']} classes. The protocol "
        "of `models/eval/eval.md` (`eval/eval.md` here: that evaluation's full table). Features: "
        + ", ".join(r["features"]) + " (`train/learn/physics.py`). The emulated objects are "
        "made of what these features read (`edge/sim/`: stiffness, relaxation, the contact "
        "patch), so these figures flatter them; `docs/method.md` sets them beside PHAC-2's.",
        "",
        "Value (standard error: binomial for the 1-NN shares, the bootstrap over the unseen "
        "classes for consistency).", "",
        "| variant | " + " | ".join(t for _, t in FIGURES) + " |",
        "|---" * (len(FIGURES) + 1) + "|",
    ]
    for name, v in r["variants"].items():
        lines.append(f"| `{name}` | " + " | ".join(
            f"{v[k]:.3f} ({v['se'][k]:.3f})" for k, _ in FIGURES) + " |")
    lines += ["", "Variants: " + "; ".join(f"`{n}`: {v['title']}"
                                            for n, v in r["variants"].items()) + ".", "",
              "## What the stiffness feature assumes", "",
              f"Closing speed over the {CLOSING_S:g} s before the stop, {a['presses']} "
              f"reference presses: median {a['closing_speed_mm_s']['median']:.2f} mm/s "
              f"(presses {a['closing_speed_mm_s']['min']:.2f}-"
              f"{a['closing_speed_mm_s']['max']:.2f}); its coefficient of variation between "
              f"the gripper's samples within a press: median "
              f"{a['closing_speed_cv']['median']:.3f}, largest "
              f"{a['closing_speed_cv']['max']:.3f}; the second half's speed over the "
              f"first's: median {a['second_half_over_first']['median']:.3f} (presses "
              f"{a['second_half_over_first']['min']:.3f}-"
              f"{a['second_half_over_first']['max']:.3f}). The rise per second is the rise per "
              "millimetre times that speed.", "",
              "Rank correlation (Spearman) of each feature with the median Present Current "
              "during the hold (which the features do not read): " + ", ".join(
                  f"{k} {v:+.2f}" for k, v in a["spearman_with_hold_current"].items()) + ".",
              ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m train.eval.physics_eval",
                                description=__doc__.splitlines()[0])
    p.add_argument("--model", default="models")
    p.add_argument("--reference", default="runs/release/recordings/reference")
    p.add_argument("--unseen", nargs="+", default=["runs/release/recordings/foodreplica",
                                                   "runs/release/recordings/cube"])
    p.add_argument("--out", default="models/eval/physics")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    command = ("python -m train.eval.physics_eval --model " + args.model + " --reference "
               + args.reference + " --unseen " + " ".join(args.unseen) + " --out " + args.out)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    result = run(Path(args.model), Path(args.reference), [Path(d) for d in args.unseen],
                 Path(args.out), command, args.seed)
    print((Path(args.out) / "physics.md").read_text())
    log.info("physics evaluation in %.0f s", result["seconds"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
