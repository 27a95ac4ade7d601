"""The report: accuracy, invalid answers and confusion per set and condition
(``eval_vlm.json``), the table beside the paper's (``eval_vlm.md``) and the confusion
matrices (``confusion_<set>.png``)."""

from __future__ import annotations

import dataclasses
import io
import json
import re
import textwrap
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from edge.core.atomic import atomic_write_text
from edge.core.errors import EvalVLMError
from train.eval.eval_vlm.config import INVALID
from train.eval.eval_vlm.paper import DATASET_TITLES, PAPER, paper_set, set_title
from train.eval.eval_vlm.plan import Plan, sha256_hex
from train.eval.eval_vlm.provenance import describe_origin

REPORT_JSON = "eval_vlm.json"
REPORT_MD = "eval_vlm.md"
DPI = 80


def slug(text: str) -> str:
    """``text`` as a file name (a set's confusion picture, a VLM model's run directory)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._") or "model"


def summarise(plan: Plan, records: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Accuracy, invalid answers and confusion per dataset and condition (every job must
    have its answer in ``records``)."""
    missing = [job.key for job in plan.jobs if job.key not in records]
    if missing:
        raise EvalVLMError(f"{len(missing)} answers missing (first: {missing[0]})")
    results: dict[str, dict[str, Any]] = {}
    presses: dict[tuple[str, str], dict[str, Any]] = {}
    for ts in plan.sets:
        results[ts.name] = {}
        for cond in plan.conditions:
            columns = [*ts.candidates, INVALID]
            matrix = np.zeros((len(ts.candidates), len(columns)), dtype=np.int64)
            results[ts.name][cond.name] = {"matrix": matrix, "columns": columns}
    for job in plan.jobs:
        answer = records[job.key]["answer"]
        label = answer.get("label")
        if answer.get("status") != "ok" or label not in job.candidates:
            label = None
        row = results[job.dataset][job.condition.name]
        col = job.candidates.index(label) if label is not None else len(job.candidates)
        row["matrix"][job.candidates.index(job.label), col] += 1
        entry = presses.setdefault((job.dataset, job.press), {
            "dataset": job.dataset, "press": job.press, "label": job.label, "answers": {}})
        entry["answers"][job.condition.name] = {
            "label": label, "status": answer.get("status"), "correct": label == job.label,
            "topk": [lab for lab, _ in job.topk], "attempts": answer.get("attempts")}
    out: dict[str, Any] = {}
    for name, conds in results.items():
        out[name] = {}
        for cond_name, r in conds.items():
            m = r["matrix"]
            n = int(m.sum())
            correct = int(np.trace(m[:, :-1]))
            invalid = int(m[:, -1].sum())
            out[name][cond_name] = {
                "accuracy": correct / n if n else None, "correct": correct, "n": n,
                "invalid_answer": invalid, "valid": n - invalid,
                "confusion": {"rows": list(r["columns"][:-1]), "columns": r["columns"],
                              "matrix": m.tolist()}}
    cfg = plan.config
    return {
        "protocol": "Table I: one query per press (offset-0 input), candidates = the set's "
                    "labels, temperature 0; invalid answers count as wrong",
        "model": cfg.vlm.model, "base_url": cfg.vlm.base_url, "seed": cfg.vlm.seed,
        "model_dir": str(cfg.model_dir), "images": plan.images, "limit": cfg.limit,
        "conditions": [dataclasses.asdict(c) for c in plan.conditions],
        "prompts": {mode: {"source": t.source, "sha256": sha256_hex(t.text.encode("utf-8"))}
                    for mode, t in plan.templates.items()},
        "datasets": [{"name": ts.name, "directory": str(ts.directory),
                      "candidates": list(ts.candidates), "presses": len(ts.press_ids),
                      "origin": ts.origin, "paper_set": paper_set(ts.name, cfg.paper_sets)}
                     for ts in plan.sets],
        "results": out,
        "presses": list(presses.values()),
    }


def _pct(r: Mapping[str, Any]) -> str:
    if not r["n"]:
        return "n/a"
    return f"{100 * r['accuracy']:.1f} % ({r['correct']}/{r['n']})"


def markdown(report: Mapping[str, Any]) -> str:
    sets = [d["name"] for d in report["datasets"]]
    beside = {d["name"]: d.get("paper_set") for d in report["datasets"]}
    titles = [set_title(s, {k: v for k, v in beside.items() if v}) for s in sets]
    conds = report["conditions"]
    head = ["| method | " + " | ".join(titles) + " |", "| --- |" + " --- |" * len(sets)]
    lines = [
        "# VLM evaluation (the paper's Table I protocol)",
        "",
        f"VLM `{report['model']}` at `{report['base_url']}` (temperature 0, seed "
        f"{report['seed']}); tactile model `{report['model_dir']}`; images: "
        f"{report['images']}; one query per press (offset-0 input); candidates: the set's "
        "labels" + (f"; first {report['limit']} presses per set (round-robin over classes)"
                    if report["limit"] else "") + ".",
        "",
        "Accuracy (correct / presses):",
        "",
        *head,
    ]
    for c in conds:
        lines.append(f"| {c['title']} | " + " | ".join(
            _pct(report["results"][s][c["name"]]) for s in sets) + " |")
    lines += ["", "Invalid answers (not a candidate even after the corrective retry; counted "
              "as wrong, never mapped to a label):", "", *head]
    for c in conds:
        lines.append(f"| {c['title']} | " + " | ".join(
            str(report["results"][s][c["name"]]["invalid_answer"]) for s in sets) + " |")
    paper_rows = [c for c in conds if c["name"] in PAPER]
    paper_sets = [beside[s] for s in sets if beside.get(s)]
    if paper_rows and paper_sets:
        lines += ["", "The paper (GPT-4V, real objects), for comparison:", "",
                  "| method | " + " | ".join(DATASET_TITLES[s] for s in paper_sets) + " |",
                  "| --- |" + " --- |" * len(paper_sets)]
        for c in paper_rows:
            lines.append(f"| {c['title']} | " + " | ".join(
                f"{PAPER[c['name']][s]:.1f} %" for s in paper_sets) + " |")
    lines += ["", "The presses: " + "; ".join(
        f"{d['name']}: {describe_origin(d.get('origin'))}" for d in report["datasets"])
        + "."]
    lines += ["", "Answers are a strict JSON enum of the candidates (a label is always a "
              "candidate, or `invalid_answer`); the paper's GPT-4V and LLaVA answered in free "
              "text.", "", "Prompt templates: " + ", ".join(
        f"`{mode}` sha256 {p['sha256'][:12]}" for mode, p in report["prompts"].items())
        + ". Confusion matrices: `eval_vlm.json`, `confusion_<set>.png`.", ""]
    return "\n".join(lines)


def confusion_png(report: Mapping[str, Any], dataset: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conds = report["conditions"]
    ncols = min(2, len(conds))
    nrows = -(-len(conds) // ncols)
    n = len(next(d for d in report["datasets"] if d["name"] == dataset)["candidates"])
    side = 2.5 + 0.28 * n
    fig, axes = plt.subplots(nrows, ncols, figsize=(side * ncols, side * nrows),
                             squeeze=False)
    for ax in axes.flat[len(conds):]:
        ax.axis("off")
    for ax, cond in zip(axes.flat, conds, strict=False):
        r = report["results"][dataset][cond["name"]]
        conf = r["confusion"]
        m = np.asarray(conf["matrix"])
        ax.imshow(m, cmap="Blues", vmin=0, vmax=max(1, int(m.max())))
        ax.set_xticks(range(len(conf["columns"])), conf["columns"], rotation=90, fontsize=6)
        ax.set_yticks(range(len(conf["rows"])), conf["rows"], fontsize=6)
        ax.axvline(len(conf["rows"]) - 0.5, color="0.4", lw=0.8)
        if n <= 8:
            for (i, j), v in np.ndenumerate(m):
                if v:
                    ax.text(j, i, str(v), ha="center", va="center", fontsize=7,
                            color="white" if v > m.max() / 2 else "black")
        ax.set_xlabel("answer", fontsize=7)
        ax.set_ylabel("true class", fontsize=7)
        ax.set_title(f"{textwrap.fill(cond['title'], 40)}\n{_pct(r)}, "
                     f"{r['invalid_answer']} invalid",
                     fontsize=8)
    simulated = " (simulated VLM, no real model)" if str(report["model"]).startswith(
        "simulated-vlm") else ""
    fig.suptitle(f"{DATASET_TITLES.get(dataset, dataset)}: VLM {report['model']}{simulated}",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97))  # room for the title
    save_png(fig, path)
    plt.close(fig)


# Colours kept in a saved figure: a confusion matrix of 22 classes x 6 conditions is 300 kB
# in full colour and under a third of that in this many, with no visible difference.
PNG_COLOURS = 64


def save_png(fig: Any, path: Path, dpi: int = DPI) -> None:
    """A figure as a palette PNG, written atomically (the reports ship in models/)."""
    from PIL import Image

    from edge.core.atomic import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    buf.seek(0)
    with Image.open(buf) as img:
        small = img.convert("RGB").quantize(PNG_COLOURS, method=Image.Quantize.MEDIANCUT)
        out = io.BytesIO()
        small.save(out, format="PNG", optimize=True)
    atomic_write_bytes(path, out.getvalue())


def write_report(plan: Plan, records: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    out = plan.config.out
    report = summarise(plan, records)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / REPORT_JSON, json.dumps(report, indent=1) + "\n")
    atomic_write_text(out / REPORT_MD, markdown(report))
    for ts in plan.sets:
        confusion_png(report, ts.name, out / f"confusion_{slug(ts.name)}.png")
    return report
