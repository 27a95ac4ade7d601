"""Tactile retrieval quality: what the encoder and database give the VLM.

Queries are recognition-time inputs (offset 0 of each press, the one input the robot
computes); the databases hold every offset of every reference press (5 per press, as shipped),
and retrieval runs through the robot's own code (:class:`edge.core.model.ReferenceDatabase`).
Rows of the comparison, one per model variant and embedding space: the VQ-VAE with the
paper's decoder (``vq``: z_q and X, teacher-forced) on z and on z_q, the VQ-VAE with the
zero-input decoder (``vq_zeros``) on z and z_q, and the beta-VAE (``beta``) on z (its
posterior mean). Metrics:

- ``loo_1nn`` / ``loo_5nn``: on the reference presses, leave one press out (all five of its
  references), classify its offset-0 query by the nearest remaining reference (majority of
  the 5 nearest). ``loo_top3``: the true class is among the first 3 distinct classes.
  Equal distances (z_q puts many references on the same code) are broken by a seeded random
  order, never by class order.
- ``top3_consistency``: on the unseen classes (FoodReplica, Cube), the share of pairs of
  presses of the same class whose top-3 reference classes are the same set (order ignored);
  ``top1_consistency`` the same for the nearest class; ``top3_overlap`` the mean share of
  classes two such top-3 sets have in common (1/3 steps).
- pair AUCs: for each real/replica pair (FoodReplica) and raw/boiled pair (Cube), the ROC AUC
  of a 1-D score separating the two classes: ``score(x) = |x - c_a| - |x - c_b|`` with
  ``c_a``, ``c_b`` the two classes' centroids in embedding space computed *without* x (leave
  one out, so the score never saw the press it scores). 0.5 is chance; 1.0 perfect. With 10
  presses per class, one AUC step is 0.01, and a pair the embedding cannot tell apart can
  score below 0.5 (leaving one out pulls its own centroid away).

A trivial baseline row (``baseline``) is always set beside the encoder, on the same presses
and the same protocol: each channel's mean over the crop window (the 25 steps of an input),
standardised with the statistics of the reference (press, offset) inputs, L2 nearest
neighbours. The report says where the primary encoder row does worse than it.

Files: ``eval.json`` (all metrics), ``eval.md`` (the tables), ``retrieval.json`` (top-k per
unseen press with its description sentence), ``confusion.png`` (leave-one-out 1-NN on the
reference classes), ``embedding_pca.png`` (2-D PCA of the embedding space: reference classes
and the unseen pairs), ``traces.png`` (example presses: the tactile norm with the crop window
and t_stop marked).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import rankdata

from edge.core import preprocess, recording
from edge.core.atomic import atomic_write_text
from edge.core.consistency import consistency
from edge.core.model import OnnxEncoder, ReferenceDatabase, Space
from train.learn import physics, sequences
from train.learn.data import PressSet, Splits
from train.ship import database

log = logging.getLogger(__name__)

# x_units (N, steps, channels) -> z (N, D), z_q (N, D) or None
Embedder = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]]

FILES = ("eval.json", "eval.md", "retrieval.json", "confusion.png", "embedding_pca.png",
         "traces.png")
TRACE_CLASSES = ("stainless_cube", "sponge_cube", "raw_kiri_mochi", "boiled_kiri_mochi")
DPI = 80
QUERY_OFFSET = 0
VARIANT_TITLES = {
    "vq": "VQ-VAE, the paper's decoder (z_q and X, teacher-forced), z of 16 and the metric "
          "term (the shipped configuration)",
    "vq_paper": "the same VQ-VAE in the paper's configuration: z of 4, reconstruction loss "
                "only",
    "vq_zeros": "VQ-VAE, zero-input decoder (z_q alone)",
    "beta": "beta-VAE (paper's decoder), posterior mean",
    "mean": "the trivial feature as deployed (vt-train build --embedding mean): each "
            "channel's mean over the crop window of the input after the training classes' "
            "normaliser, L2 nearest neighbours",
    "baseline": "trivial baseline: each channel's mean over the crop window, standardised "
                "with the reference presses' statistics, L2 nearest neighbours",
    "physics": "the press's physics (train/learn/physics.py: peak load, stiffness, "
               "relaxation over the hold, spread across the channels), each standardised "
               "with the reference presses' statistics, L2 nearest neighbours",
    "mean+physics": "the trivial baseline's channel means and the physics features side by "
                    "side, each block weighted alike, L2 nearest neighbours",
}
BASELINE = "baseline"
NEIGHBOURS = 3  # per unseen class in the report: the most frequent nearest classes
# The headline figures the encoder is held against the baseline on (key, name in the report).
VERSUS_BASELINE = (("loo_1nn", "LOO 1-NN"), ("loo_top3", "LOO top-3"),
                   ("top3_consistency", "unseen top-3 consistency"),
                   ("mean_auc_real_vs_replica", "mean AUC real/replica"),
                   ("mean_auc_raw_vs_boiled", "mean AUC raw/boiled"))


@dataclass(frozen=True)
class Row:
    variant: str
    space: Space
    z_ref: np.ndarray  # reference queries (offset 0 of each press) in this space
    z_all: np.ndarray  # every reference (press, offset), press-major, in this space
    z_unseen: np.ndarray  # unseen embeddings in this space (pair AUCs)
    queries: np.ndarray  # what the robot hands topk: the continuous z
    db: ReferenceDatabase


def onnx_embedder(encoder: OnnxEncoder, codebook: np.ndarray) -> Embedder:
    """The robot's encoder as an embedder: z and z_q = codebook[code] from the graph."""
    def embed(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z, code = encoder(x)
        return z, codebook[code]
    return embed


def baseline_embedder(x_reference: np.ndarray) -> Embedder:
    """Each channel's mean over the window, standardised with the statistics of
    ``x_reference`` (N, steps, channels); a channel that never moves is left unscaled."""
    features = x_reference.mean(axis=1, dtype=np.float64)
    mean = features.mean(axis=0)
    std = features.std(axis=0)
    std[std <= 0] = 1.0

    def embed(x: np.ndarray) -> tuple[np.ndarray, None]:
        return ((x.mean(axis=1, dtype=np.float64) - mean) / std).astype(np.float32), None
    return embed


def physics_embedder(x_reference: np.ndarray) -> Embedder:
    """The press's physics features (:mod:`train.learn.physics`), standardised with the
    statistics of ``x_reference`` (N, steps, channels)."""
    apply = physics.standardised(x_reference)

    def embed(x: np.ndarray) -> tuple[np.ndarray, None]:
        return apply(x).astype(np.float32), None
    return embed


def mean_physics_embedder(x_reference: np.ndarray) -> Embedder:
    """The channel means and the physics features side by side. Each block is divided by the
    root of its length, so each adds the same expected squared distance: 4 features beside
    96 channel means would otherwise weigh next to nothing."""
    means, phys = baseline_embedder(x_reference), physics.standardised(x_reference)

    def embed(x: np.ndarray) -> tuple[np.ndarray, None]:
        m, p = means(x)[0], phys(x)
        return np.concatenate([m / np.sqrt(m.shape[1]), p / np.sqrt(p.shape[1])],
                              axis=1).astype(np.float32), None
    return embed


# The numpy candidates fitted on reference inputs (N, steps, channels), by name.
FEATURE_EMBEDDERS: dict[str, Callable[[np.ndarray], Embedder]] = {
    "physics": physics_embedder, "mean+physics": mean_physics_embedder}


def pairs_of(labels: Sequence[str]) -> list[tuple[str, str, str]]:
    """(name, a, b): real vs resin replica, raw vs boiled, for classes present in labels."""
    have = set(labels)
    out = []
    for label in sorted(have):
        if f"resin_replica_{label}" in have:
            out.append((label, label, f"resin_replica_{label}"))
        if label.startswith("raw_") and f"boiled_{label[4:]}" in have:
            out.append((label[4:], label, f"boiled_{label[4:]}"))
    return out


def auc(negative: np.ndarray, positive: np.ndarray) -> float:
    """ROC AUC (Mann-Whitney, ties count half) of scores: positive above negative."""
    scores = np.concatenate([negative, positive])
    ranks = rankdata(scores)
    n_neg, n_pos = len(negative), len(positive)
    return float((ranks[n_neg:].sum() - n_pos * (n_pos + 1) / 2) / (n_neg * n_pos))


def pair_auc(za: np.ndarray, zb: np.ndarray) -> dict[str, float]:
    """Leave-one-out distance-to-centroids score for one pair; b is the positive class."""
    def loo_centroids(z: np.ndarray) -> np.ndarray:
        n = len(z)
        return (z.sum(0, keepdims=True) - z) / max(n - 1, 1)

    ca, cb = za.mean(0), zb.mean(0)
    ca_loo, cb_loo = loo_centroids(za), loo_centroids(zb)
    score_a = np.linalg.norm(za - ca_loo, axis=1) - np.linalg.norm(za - cb, axis=1)
    score_b = np.linalg.norm(zb - ca, axis=1) - np.linalg.norm(zb - cb_loo, axis=1)
    within = np.sqrt(0.5 * (za.var(0).sum() + zb.var(0).sum()))
    return {"auc": auc(score_a, score_b),
            "centroid_distance": float(np.linalg.norm(ca - cb)),
            "separation": float(np.linalg.norm(ca - cb) / within) if within > 0 else float("inf"),
            "n": [len(za), len(zb)]}


def _distances(q: np.ndarray, refs: np.ndarray) -> np.ndarray:
    return np.sqrt(np.maximum(((q[:, None, :] - refs[None, :, :]) ** 2).sum(-1), 0.0))


def loo_knn(z: np.ndarray, labels: Sequence[str], seed: int = 0,
            refs: np.ndarray | None = None, per_press: int = 1) -> dict[str, Any]:
    """Leave-one-press-out k-NN on the reference presses.

    ``z`` (P, D): one query per press. ``refs`` (P * per_press, D), press-major: the
    references (default: the queries themselves); the ``per_press`` references of the
    query's own press are left out.
    """
    labels_arr = np.asarray(labels)
    classes = list(dict.fromkeys(labels))
    refs = z if refs is None else refs
    if len(refs) != len(z) * per_press:
        raise ValueError(f"{len(refs)} references for {len(z)} presses x {per_press}")
    ref_labels = np.repeat(labels_arr, per_press)
    d = _distances(z, refs)
    own = np.repeat(np.arange(len(z)), per_press)
    d[own[None, :] == np.arange(len(z))[:, None]] = np.inf
    tiebreak = np.random.default_rng(seed).permutation(len(refs))
    order = np.lexsort((np.broadcast_to(tiebreak, d.shape), d), axis=1)
    kept = len(refs) - per_press  # the left-out press sorts last (infinite distance)
    pred1 = ref_labels[order[:, 0]]
    pred5 = []
    top3 = []
    for i in range(len(z)):
        near = ref_labels[order[i, :5]]
        votes = {c: 0 for c in dict.fromkeys(near)}
        for c in near:
            votes[c] += 1
        pred5.append(max(votes, key=lambda c: votes[c]))  # ties: the nearest class wins
        distinct = list(dict.fromkeys(ref_labels[order[i, :kept]]))[:3]
        top3.append(labels_arr[i] in distinct)
    idx = {c: j for j, c in enumerate(classes)}
    confusion = np.zeros((len(classes), len(classes)), dtype=np.int64)
    for true, pred in zip(labels_arr, pred1, strict=True):
        confusion[idx[true], idx[pred]] += 1
    return {"loo_1nn": float(np.mean(pred1 == labels_arr)),
            "loo_5nn": float(np.mean(np.asarray(pred5) == labels_arr)),
            "loo_top3": float(np.mean(top3)),
            "confusion": confusion, "classes": classes}


def evaluate(embedders: Mapping[str, tuple[Embedder, np.ndarray | None]],
             reference: PressSet, splits: Splits, unseen: PressSet | None,
             out_dir: str | Path, primary: tuple[str, Space] = ("vq", "z"), k: int = 3,
             seed: int = 0) -> dict[str, Any]:
    """Evaluate every (variant, space) and the trivial baseline; write the files of the
    primary row and the tables.

    ``embedders`` maps a variant name to (embedder, codebook or None). Without ``unseen``
    presses only the reference (leave-one-out) figures are measured.
    """
    if unseen is None:
        unseen = PressSet(reference.x[:0], reference.x_bar[:0], (), ())
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    offsets = database.offsets_of(reference)
    per_press = len(offsets)
    at_query = offsets.index(QUERY_OFFSET)
    x_all, x_uns = database.reference_inputs(reference, offsets), unseen.inputs(QUERY_OFFSET)
    embedders = {**embedders, BASELINE: (baseline_embedder(x_all), None)}
    rows: list[Row] = []
    for variant, (embedder, codebook) in embedders.items():
        z_all, zq_all = embedder(x_all)
        z_uns, zq_uns = embedder(x_uns) if len(x_uns) else (
            z_all[:0], None if zq_all is None else zq_all[:0])
        spaces: list[Space] = ["z"] if zq_all is None else ["z", "z_q"]
        for space in spaces:
            db = database.from_embeddings(reference, splits, z_all, codebook, space=space,
                                          offsets=offsets)
            in_space = z_all if space == "z" else zq_all
            assert in_space is not None
            rows.append(Row(variant, space, in_space[at_query::per_press], in_space,
                            z_uns if space == "z" else zq_uns, z_uns, db))
    pairs = pairs_of(unseen.labels)
    uns_labels = np.asarray(unseen.labels)
    report: dict[str, Any] = {"k": k, "reference_presses": len(reference),
                              "reference_classes": len(reference.classes),
                              "references": len(reference) * per_press,
                              "unseen_presses": len(unseen), "unseen_classes": unseen.classes,
                              "database_offsets": list(offsets),
                              "query_offset": QUERY_OFFSET, "rows": []}
    primary_row = None
    for row in rows:
        knn = loo_knn(row.z_ref, reference.labels, seed, refs=row.z_all, per_press=per_press)
        # Queries go through the database exactly as on the robot: z in (a z_q database
        # quantises it itself).
        retrieved = [row.db.topk(q, k) for q in row.queries]
        cons = consistency([[lab for lab, _ in r] for r in retrieved], unseen.labels)
        pair_metrics = {name: pair_auc(row.z_unseen[uns_labels == a],
                                       row.z_unseen[uns_labels == b])
                        for name, a, b in pairs}
        replica = [pair_metrics[name]["auc"] for name, _, b in pairs
                   if b.startswith("resin_replica_")]
        cooked = [pair_metrics[name]["auc"] for name, _, b in pairs if b.startswith("boiled_")]
        split_acc = _split_accuracy(knn, splits)
        metrics = {
            "variant": row.variant, "space": row.space,
            "loo_1nn": knn["loo_1nn"], "loo_5nn": knn["loo_5nn"], "loo_top3": knn["loo_top3"],
            **split_acc,
            "top3_consistency": cons["top3_consistency"],
            "top1_consistency": cons["top1_consistency"],
            "top3_overlap": cons["top3_overlap"],
            "mean_auc_real_vs_replica": float(np.mean(replica)) if replica else None,
            "mean_auc_raw_vs_boiled": float(np.mean(cooked)) if cooked else None,
            "pair_auc": {name: m["auc"] for name, m in pair_metrics.items()},
            "pairs": pair_metrics,
            "consistency_per_class": cons["per_class"],
            "unseen_neighbours": neighbours(retrieved, unseen.labels),
        }
        report["rows"].append(metrics)
        if (row.variant, row.space) == primary:
            primary_row = (row, knn, retrieved)
    if primary_row is None:
        raise ValueError(f"primary row {primary} was not evaluated")
    row, knn, retrieved = primary_row
    report["primary"] = {"variant": primary[0], "space": primary[1]}
    retrieval = [{"press": Path(path).name, "label": label,
                  "topk": [[lab, round(d, 6)] for lab, d in r],
                  "description": row.db.describe(lab for lab, _ in r)}
                 for path, label, r in zip(unseen.paths, unseen.labels, retrieved, strict=True)]
    # One press per line: readable, diffable, small.
    atomic_write_text(out / "retrieval.json", "[\n" + ",\n".join(
        json.dumps(r) for r in retrieval) + "\n]\n")
    report["confusion"] = {"classes": knn["classes"], "matrix": knn["confusion"].tolist()}
    atomic_write_text(out / "eval.json", json.dumps(report, indent=2, sort_keys=True) + "\n")
    atomic_write_text(out / "eval.md", markdown(report, pairs))
    _pictures(out, row, knn, reference, unseen)
    return report


def neighbours(retrieved: Sequence[list[tuple[str, float]]], labels: Sequence[str]
               ) -> dict[str, dict[str, Any]]:
    """Per unseen class: the (up to) ``NEIGHBOURS`` reference classes that came first most
    often, and those most often in the top-k, with their counts, most frequent first."""
    out: dict[str, dict[str, Any]] = {}
    for cls in dict.fromkeys(labels):
        mine = [r for r, lab in zip(retrieved, labels, strict=True) if lab == cls]
        first: dict[str, int] = {}
        anywhere: dict[str, int] = {}
        for r in mine:
            first[r[0][0]] = first.get(r[0][0], 0) + 1
            for lab, _ in r:
                anywhere[lab] = anywhere.get(lab, 0) + 1
        out[cls] = {"presses": len(mine),
                    "first": sorted(first.items(), key=lambda kv: (-kv[1], kv[0]))[:NEIGHBOURS],
                    "topk": sorted(anywhere.items(),
                                   key=lambda kv: (-kv[1], kv[0]))[:NEIGHBOURS]}
    return out


def _split_accuracy(knn: dict[str, Any], splits: Splits) -> dict[str, float]:
    classes = knn["classes"]
    conf = knn["confusion"]
    out = {}
    for name, members in (("train", splits.train), ("val", splits.val)):
        idx = [classes.index(c) for c in members if c in classes]
        if idx:
            out[f"loo_1nn_{name}_classes"] = float(conf[idx, idx].sum() / conf[idx].sum())
    return out


def _against(rows: Sequence[dict[str, Any]], other: str, who: str
             ) -> tuple[str, str] | None:
    """``vq`` beside ``other`` (called ``who``), retrieval in z, on the headline figures: the
    figures side by side and a sentence naming those ``other`` does better on; None if
    either row is missing."""
    by = {(r["variant"], r["space"]): r for r in rows}
    vq, that = by.get(("vq", "z")), by.get((other, "z"))
    if vq is None or that is None:
        return None
    better = [name for key, name in VERSUS_BASELINE
              if vq[key] is not None and that[key] is not None and that[key] > vq[key]]
    parts = ", ".join(f"{name} {_fmt(vq[key])} against {_fmt(that[key])}"
                      for key, name in VERSUS_BASELINE)
    return parts, f"{who} does better on {', '.join(better) if better else 'none of them'}"


def _paper_comparison(rows: Sequence[dict[str, Any]]) -> list[str]:
    """A paragraph setting the shipped configuration (``vq``) beside the paper's
    (``vq_paper``), from this report's own numbers."""
    found = _against(rows, "vq_paper", "The paper's configuration")
    if found is None:
        return []
    parts, verdict = found
    return ["", "## The shipped configuration against the paper's", "",
            "Both have the paper's encoder, VQ bottleneck (K = 32) and decoder. The paper's "
            "(`vq_paper`) has z of 4 numbers and reconstruction loss only: its decoder sees "
            "X[t-1] and needs little from z, so z keeps little of what tells objects apart. "
            "The shipped one (`vq`) has z of 16 and adds the metric term (a batch-hard "
            "triplet loss on z over the training classes, margin 1, weight 1): presses of "
            "one class nearer each other than other classes' presses, in the L2 distance "
            "retrieval uses. Its LOO 1-NN over the training classes is therefore not a "
            "held-out figure; `1-NN val classes` (5 classes it never learned labels of; "
            "they stop the training early) and the unseen figures are. Retrieval in z, "
            f"shipped against the paper's: {parts}. {verdict}."]


def _decoder_comparison(rows: Sequence[dict[str, Any]]) -> list[str]:
    """A paragraph setting the paper's decoder (``vq``) beside the zero-input one
    (``vq_zeros``), retrieval in z, from this report's own numbers."""
    found = _against(rows, "vq_zeros", "The zero-input decoder")
    if found is None:
        return []
    parts, verdict = found
    return ["", "## Decoders", "",
            f"The paper's decoder (`vq`: z_q and X, teacher-forced) against the zero-input one "
            f"(`vq_zeros`, otherwise the same configuration), retrieval in z: {parts}. "
            f"{verdict}. The paper's decoder is the shipped default; what each gives the VLM "
            "is in Table I (`table1/table1.md`, rows `vq_zeros_top3`)."]


def _versus_baseline(report: dict[str, Any]) -> list[str]:
    """Where the primary encoder row loses to the trivial baseline, said plainly, and each
    unseen class's nearest reference classes for both."""
    rows = report["rows"]
    p = report.get("primary", {"variant": "vq", "space": "z"})
    by = {(r["variant"], r["space"]): r for r in rows}
    enc, base = by.get((p["variant"], p["space"])), by.get((BASELINE, "z"))
    if enc is None or base is None:
        return []
    name = f"{enc['variant']}/{enc['space']}"
    lost = [f"{label} ({_fmt(enc[key])} against {_fmt(base[key])})"
            for key, label in VERSUS_BASELINE
            if enc[key] is not None and base[key] is not None and base[key] > enc[key]]
    won = [label for key, label in VERSUS_BASELINE
           if enc[key] is not None and base[key] is not None and enc[key] > base[key]]
    pairs = [pair for pair, auc_ in enc["pair_auc"].items() if base["pair_auc"][pair] > auc_]
    lines = ["", "## The encoder against the trivial baseline", ""]
    if lost:
        lines.append(f"The encoder (`{name}`) does worse than the trivial baseline on "
                     f"{'; '.join(lost)}.")
    else:
        lines.append(f"The encoder (`{name}`) does no worse than the trivial baseline on any "
                     "headline figure.")
    if won:
        lines.append(f"It does better on {', '.join(won)}.")
    if pairs:
        lines.append(f"Pairs the baseline separates better (higher AUC): {', '.join(pairs)}.")
    lines += ["", "Unseen classes' nearest reference classes (how many of the class's presses "
              "had it first; the most frequent in the top-k):", "",
              f"| unseen class | {name} first | {name} top-{report['k']} | baseline first "
              f"| baseline top-{report['k']} |", "| --- | --- | --- | --- | --- |"]

    def most(items: list, n: int) -> str:
        return ", ".join(f"{lab} {count}" for lab, count in items[:n])

    for cls, e in enc["unseen_neighbours"].items():
        b = base["unseen_neighbours"][cls]
        lines.append(f"| {cls} | {most(e['first'], 2)} | {most(e['topk'], 3)} | "
                     f"{most(b['first'], 2)} | {most(b['topk'], 3)} |")
    return lines


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def markdown(report: dict[str, Any], pairs: Sequence[tuple[str, str, str]]) -> str:
    rows = report["rows"]
    lines = [
        "# Tactile retrieval evaluation",
        "",
        f"Reference: {report['reference_presses']} presses of {report['reference_classes']} "
        f"classes, {report['references']} references (offsets "
        f"{', '.join(map(str, report['database_offsets']))} of every press); unseen: "
        f"{report['unseen_presses']} presses of {len(report['unseen_classes'])} classes; "
        f"queries at offset {report['query_offset']} (the recognition-time input); top-k "
        f"with k = {report['k']}.",
        "",
        "Variants: " + "; ".join(f"`{name}`: {title}" for name, title in
                                 VARIANT_TITLES.items()
                                 if any(r["variant"] == name for r in report["rows"])) + ".",
        "",
        "| variant | space | LOO 1-NN | LOO 5-NN | LOO top-3 | 1-NN val classes | "
        "top-3 consistency | top-3 overlap | top-1 consistency | AUC real/replica (mean) | "
        "AUC raw/boiled (mean) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['variant']} | {r['space']} | {_fmt(r['loo_1nn'])} | {_fmt(r['loo_5nn'])} | "
            f"{_fmt(r['loo_top3'])} | {_fmt(r.get('loo_1nn_val_classes'))} | "
            f"{_fmt(r['top3_consistency'])} | {_fmt(r['top3_overlap'])} | "
            f"{_fmt(r['top1_consistency'])} | "
            f"{_fmt(r['mean_auc_real_vs_replica'])} | {_fmt(r['mean_auc_raw_vs_boiled'])} |")
    lines += ["", "## Pair separation (ROC AUC, leave-one-out distance-to-centroids score)", "",
              "| pair | " + " | ".join(f"{r['variant']}/{r['space']}" for r in rows)
              + " | separation (primary) |",
              "| --- |" + " --- |" * (len(rows) + 1)]
    primary = next(r for r in rows if (r["variant"], r["space"])
                   == (report.get("primary", {}).get("variant", "vq"),
                       report.get("primary", {}).get("space", "z")))
    for name, a, b in pairs:
        sep = primary["pairs"][name]["separation"]
        lines.append(f"| {a} vs {b} | "
                     + " | ".join(_fmt(r["pair_auc"][name]) for r in rows)
                     + f" | {sep:.2f} |")
    lines += _paper_comparison(rows)
    lines += _decoder_comparison(rows)
    lines += _versus_baseline(report)
    lines += ["",
              "LOO: leave one reference press out (its five references), nearest remaining "
              "reference (5-NN: majority of the 5 nearest references). "
              "Consistency: share of same-class unseen press pairs whose top-3 classes are "
              "the same set (overlap: mean share of classes the two top-3 sets have in "
              "common). AUC: 0.5 is chance; below 0.5 means the leave-one-out centroids "
              "cannot tell the pair apart. Separation: centroid distance over the pooled "
              "within-class spread.", ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------
# Pictures


def _pictures(out: Path, row: Row, knn: dict[str, Any], reference: PressSet,
              unseen: PressSet) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meta = {"Software": None}
    # Confusion matrix
    conf = knn["confusion"]
    classes = knn["classes"]
    fig, ax = plt.subplots(figsize=(9, 8))
    ax.imshow(conf, cmap="Blues")
    ax.set_xticks(range(len(classes)), classes, rotation=90, fontsize=6)
    ax.set_yticks(range(len(classes)), classes, fontsize=6)
    ax.set_xlabel("nearest other press")
    ax.set_ylabel("true class")
    ax.set_title(f"Reference presses, leave-one-out 1-NN ({row.variant}, {row.space}): "
                 f"accuracy {knn['loo_1nn']:.2f}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "confusion.png", dpi=DPI, metadata=meta)
    plt.close(fig)

    # PCA of the embedding space (fit on the reference embeddings)
    mean = row.z_ref.mean(0)
    _, _, vt = np.linalg.svd(row.z_ref - mean, full_matrices=False)
    proj = vt[:2].T
    pr, pu = (row.z_ref - mean) @ proj, (row.z_unseen - mean) @ proj
    fig, axes = plt.subplots(1, 2, figsize=(13, 6))
    cmap = plt.get_cmap("tab20")
    ref_labels = np.asarray(reference.labels)
    for i, c in enumerate(reference.classes):
        pts = pr[ref_labels == c]
        axes[0].scatter(pts[:, 0], pts[:, 1], s=10, color=cmap(i % 20),
                        marker="o" if i < 20 else "^")
        axes[0].annotate(c, pts.mean(0), fontsize=6)
    axes[0].set_title("reference classes", fontsize=9)
    axes[1].scatter(pr[:, 0], pr[:, 1], s=6, color="0.85")
    uns_labels = np.asarray(unseen.labels)
    for i, (name, a, b) in enumerate(pairs_of(unseen.labels)):
        color = cmap(i % 20)
        for label, marker in ((a, "o"), (b, "x")):
            pts = pu[uns_labels == label]
            axes[1].scatter(pts[:, 0], pts[:, 1], s=14, color=color, marker=marker)
        axes[1].annotate(name, pu[uns_labels == a].mean(0), fontsize=6)
    axes[1].set_title("unseen pairs (o real / raw, x replica / boiled); grey: reference",
                      fontsize=9)
    for ax in axes:
        ax.set_xlabel("PC 1")
        ax.set_ylabel("PC 2")
    fig.tight_layout()
    fig.savefig(out / "embedding_pca.png", dpi=DPI, metadata=meta)
    plt.close(fig)

    # Example presses: tactile norm, crop window, t_stop
    paths = {**dict(zip(reference.labels, reference.paths, strict=True)),
             **dict(zip(unseen.labels, unseen.paths, strict=True))}
    chosen = [c for c in TRACE_CLASSES if c in paths] or list(paths)[:4]
    spec = preprocess.DEFAULT_WINDOW
    fig, axes = plt.subplots(len(chosen), 1, figsize=(8, 1.9 * len(chosen)), squeeze=False)
    for ax, label in zip(axes[:, 0], chosen, strict=True):
        if sequences.is_sequence(paths[label]):  # another sensor's press: no frames, no x_th
            seq = sequences.load(paths[label])
            own, times, stop = seq.window(spec)
            ax.plot(times - stop, preprocess.norm(seq.samples), lw=0.8, color="C0", label="|x|")
            ax.axvspan(-own.before_s, own.after_s, color="C2", alpha=0.12, label="crop window")
            ax.set_title(label, fontsize=8)
            continue
        rec = recording.load(paths[label])
        units = preprocess.recording_units(rec)
        t = rec.recv_time - rec.t_stop
        ax.plot(t, preprocess.norm(units), lw=0.8, color="C0", label="|x| (125 Hz frames)")
        window = preprocess.crop(rec.recv_time, units, rec.t_stop, spec)
        grid = spec.grid(rec.t_stop) - rec.t_stop
        ax.plot(grid[0::spec.subsample], preprocess.norm(window[0::spec.subsample]), ".",
                ms=4, color="C3", label="X (offset 0, 25 Hz)")
        ax.axvspan(-spec.before_s, spec.after_s, color="C2", alpha=0.12, label="crop window")
        ax.axvline(0.0, color="k", lw=0.8, ls="--", label="t_stop")
        ax.axhline(rec.threshold, color="0.5", lw=0.6, ls=":", label="x_th")
        ax.set_title(label, fontsize=8)
        ax.tick_params(labelsize=7)
    axes[-1, 0].set_xlabel("time from t_stop (s)")
    axes[0, 0].legend(fontsize=6, loc="upper left")
    fig.tight_layout()
    fig.savefig(out / "traces.png", dpi=DPI, metadata=meta)
    plt.close(fig)


def summary_metrics(report: dict[str, Any]) -> dict[str, Any]:
    """The headline numbers for the manifest."""
    rows = {f"{r['variant']}/{r['space']}": r for r in report["rows"]}
    p = report["primary"]
    primary = rows[f"{p['variant']}/{p['space']}"]
    return {
        "primary": f"{p['variant']}/{p['space']}",
        "kiri_mochi_auc": primary["pair_auc"].get("kiri_mochi"),
        "pair_auc": primary["pair_auc"],
        "loo_1nn": primary["loo_1nn"],
        "loo_top3": primary["loo_top3"],
        "top3_consistency": primary["top3_consistency"],
        "comparison": {name: {key: r[key] for key in (
            "loo_1nn", "loo_5nn", "loo_top3", "top3_consistency", "top3_overlap",
            "top1_consistency",
            "mean_auc_real_vs_replica", "mean_auc_raw_vs_boiled")} | {
                "kiri_mochi_auc": r["pair_auc"].get("kiri_mochi")}
            for name, r in rows.items()},
    }
