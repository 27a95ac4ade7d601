"""The encoder and retrieval phases: the robot's encoder (onnxruntime, through
:mod:`edge.core.model`) on one sequence, and top-k on the shipped database and on 1,000,000
synthetic references against plain numpy brute force.

The same encoder in torch eager is timed on the training side (``vt-train bench``), which
has torch: the robot's side never imports it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from edge.bench.figures import figure, ratio_figure, target, timed_in_blocks
from edge.bench.results import PhaseResult, progress
from edge.bench.settings import MODELS, Settings
from edge.core.model import load_model, synthetic_database, synthetic_inputs


def timed(fn: Callable[[int], Any], n: int, warmup: int = 20) -> list[float]:
    for i in range(warmup):
        fn(i)
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out.append(1e3 * (time.perf_counter() - t0))
    return out


def encode_phase(s: Settings) -> PhaseResult:
    """onnxruntime with the robot's session options, one sequence per call."""
    model = load_model(MODELS)
    xs = synthetic_inputs(model.manifest)
    progress(f"encoder: {s.encode_n} single-sequence encodes: onnxruntime (1 thread, the "
             "robot's options)")
    times = timed_in_blocks({"ort": model.encode}, xs, s.encode_n)
    return PhaseResult({"encode_ms": figure(
        times["ort"], "ms", target(("p50", "<=", 0.3)),
        what="edge.core.model Model.encode of one (25, 96) sequence, onnxruntime CPU, 1 "
             "intra-op thread")})


def numpy_topk(refs: np.ndarray, labels: np.ndarray, q: np.ndarray, k: int) -> list[int]:
    """Plain numpy: every distance, argsort, first k distinct classes."""
    d = np.sqrt(((refs - q) ** 2).sum(axis=1))
    order = np.argsort(d)
    _, first = np.unique(labels[order], return_index=True)
    return [int(labels[order[i]]) for i in np.sort(first)[:k]]


def retrieval_phase(s: Settings) -> PhaseResult:
    notes: list[str] = []
    figs: dict[str, Any] = {}
    shipped = load_model(MODELS).database
    dbs = [("shipped", shipped)]
    progress(f"retrieval: building a synthetic database of {s.retrieval_refs:,} "
             f"references, {s.retrieval_classes} classes")
    dbs.append(("1m", synthetic_database(s.retrieval_refs, s.retrieval_classes)))
    rng = np.random.default_rng(1)
    for name, db in dbs:
        # The embeddings topk compares (its space), grouped by class like label_index.
        refs, labels = (db.z if db.space == "z" else db.z_q), db.label_index
        if name == "shipped":
            qs = refs[rng.integers(0, len(refs), s.retrieval_queries)] + \
                rng.normal(0, 0.05 * refs.std(), (s.retrieval_queries, db.dim))
        else:
            qs = rng.standard_normal((s.retrieval_queries, db.dim))
        qs = qs.astype(np.float32)
        n_brute = s.retrieval_queries if name == "shipped" else s.brute_queries_1m
        progress(f"retrieval ({name}, {len(db):,} refs): {s.retrieval_queries} top-k "
                 f"queries, {n_brute} numpy brute-force queries")
        fast = timed(lambda i, db=db, qs=qs: db.topk(qs[i % len(qs)], 3),
                     s.retrieval_queries, warmup=3)
        brute = timed(lambda i, r=refs, lb=labels, qs=qs: numpy_topk(r, lb, qs[i % len(qs)], 3),
                      n_brute, warmup=1)
        names = db.labels
        mismatch = sum(
            [label for label, _ in db.topk(q, 3)] != [names[c] for c in numpy_topk(
                refs, labels, q, 3)] for q in qs[:n_brute])
        ships = name == "1m"
        key = "retrieval_ms_1m" if ships else "retrieval_ms_shipped"
        figs[key] = figure(fast, "ms", target(("p50", "<=", 5.0)) if ships else None,
                           references=len(db), classes=len(db.classes),
                           what="ReferenceDatabase.topk (k = 3 distinct classes), one query")
        figs[f"retrieval_numpy_ms_{name}"] = figure(
            brute, "ms", None, references=len(db), answer_mismatches=mismatch,
            what="plain numpy: all L2 distances, argsort, first 3 distinct classes")
        figs[f"retrieval_speedup_{name}"] = ratio_figure(
            figs[f"retrieval_numpy_ms_{name}"], figs[key],
            what="numpy brute force time / topk time (statistic by statistic)")
        if mismatch:
            notes.append(f"retrieval ({name}): top-3 differs from numpy brute force on "
                         f"{mismatch} of {n_brute} queries (ties?)")
    return PhaseResult(figs, notes)
