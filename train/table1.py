"""``vt-train table1``: the paper's Table I in one command, against any endpoint or the
simulated VLM.

Rows: vision only, the method (VQ-VAE, top-3), top-1 instead of top-3, the beta-VAE, for a
first model (the paper's GPT-4V rows) and a second one (the paper's LLaVA rows); columns:
FoodReplica and Cube accuracy, with the paper's own numbers beside ours. Extra rows when their
checkpoint exists: the zero-input decoder (``vq_zeros_top3``) and the tactile-adjective
ablation (``vq_top3_adjectives``).

Each model's questions are asked by :mod:`train.eval_vlm` (the robot's prompts and client,
answers cached in ``WORK/<model>/answers.jsonl``: an interrupted run continues, a finished
one asks nothing again) and this module adds one report over both: ``table1.md``,
``table1.json`` and the confusion matrices ``confusion_<model>_<set>.png`` in ``--out``.

With no ``--url`` the simulated VLM (:mod:`edge.sim.standin_vlm`) is started on loopback and
asked as ``simulated-vlm`` (first) and ``simulated-vlm-vision-led`` (second, which like the
paper's LLaVA hardly uses the touch text); its cache directories carry a digest of its
knowledge, so a changed stand-in never reuses another one's answers. Every title says
"simulated VLM": it checks the whole chain, it is not a result about any real model.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from edge.core.atomic import atomic_write_text
from edge.core.config import VLMConfig
from edge.core.errors import EvalVLMError
from edge.core.model import read_manifest
from train import eval_vlm
from train.eval_vlm import DATASET_TITLES, EvalVLMConfig

log = logging.getLogger(__name__)

REPORT_MD = "table1.md"
REPORT_JSON = "table1.json"
TABLE_CONDITIONS = ("vision_only", "vq_top3", "vq_top1", "beta_top3")
EXTRA_CONDITIONS = ("vq_zeros_top3", "vq_top3_adjectives")
SETS = ("foodreplica", "cube")

# The paper's Table I, percent (FoodReplica, Cube); LLaVA has only two rows.
PAPER: dict[str, dict[str, tuple[float, float]]] = {
    "GPT-4V": {"vision_only": (53.6, 50.0), "vq_top3": (58.9, 65.0),
               "vq_top1": (58.4, 52.5), "beta_top3": (52.5, 50.0)},
    "LLaVA": {"vision_only": (39.0, 25.0), "vq_top3": (39.1, 25.0)},
}
PAPER_MODELS = ("GPT-4V", "LLaVA")  # what our first and second model stand beside


@dataclass(frozen=True)
class Table1Config:
    first: VLMConfig  # an endpoint and model; base_url "" = the simulated VLM
    out: Path
    work: Path
    unseen: tuple[Path, ...]
    second: VLMConfig | None = None
    model_dir: Path = Path("models")
    reference: Path | None = None
    beta: Path | None = None
    zeros: Path | None = None
    images: Path | None = None
    limit: int | None = None
    concurrency: int = eval_vlm.DEFAULT_CONCURRENCY
    extras: bool = True  # add the extra rows whose checkpoints exist

    @property
    def standin(self) -> bool:
        return not self.first.configured

    def conditions(self) -> tuple[str, ...]:
        have = {"beta_top3": self.beta, "vq_zeros_top3": self.zeros}
        out = []
        for name in (*TABLE_CONDITIONS, *(EXTRA_CONDITIONS if self.extras else ())):
            if name in have:
                path = have[name]
                if path is None or not path.exists() or self.reference is None \
                        or not self.reference.exists():
                    log.warning("%s skipped: no checkpoint (%s) or reference recordings "
                                "(%s); `vt-train release` makes both", name, path,
                                self.reference)
                    continue
            out.append(name)
        return tuple(out)


def _cache_dir(work: Path, model: str, standin: bool) -> Path:
    if standin:
        from edge.sim.standin_vlm import knowledge_digest

        return work / f"{eval_vlm.slug(model)}@{knowledge_digest()[:12]}"
    return work / eval_vlm.slug(model)


async def _run_models(cfg: Table1Config, models: Sequence[VLMConfig], progress: bool
                      ) -> list[tuple[VLMConfig, dict[str, Any]]]:
    conditions = cfg.conditions()
    reports = []
    for vlm in models:
        ecfg = EvalVLMConfig(
            vlm=vlm, out=_cache_dir(cfg.work, vlm.model, cfg.standin), unseen=cfg.unseen,
            model_dir=cfg.model_dir, conditions=conditions, reference=cfg.reference,
            beta=cfg.beta, zeros=cfg.zeros, images=cfg.images, limit=cfg.limit,
            concurrency=cfg.concurrency)
        log.info("Table I: asking %s (%s)", vlm.model, vlm.base_url)
        reports.append((vlm, await eval_vlm.run(ecfg, progress=progress)))
    return reports


async def run(cfg: Table1Config, *, progress: bool = True) -> dict[str, Any]:
    """Ask both models (starting the simulated VLM if no endpoint is given), write the
    report."""
    if cfg.standin:
        from edge.sim.standin_vlm import DEFAULT, VISION_LED, server

        async with server() as srv:
            base = dataclasses.replace(cfg.first, base_url=srv.base_url)
            models = [dataclasses.replace(base, model=DEFAULT.model),
                      dataclasses.replace(base, model=VISION_LED.model)]
            reports = await _run_models(cfg, models, progress)
    else:
        models = [cfg.first] + ([cfg.second] if cfg.second is not None else [])
        reports = await _run_models(cfg, models, progress)
    return await asyncio.to_thread(write_report, cfg, reports)


def _cell(r: Mapping[str, Any] | None) -> str:
    if r is None or not r["n"]:
        return "n/a"
    return f"{100 * r['accuracy']:.1f} % ({r['correct']}/{r['n']})"


def summary(cfg: Table1Config, reports: Sequence[tuple[VLMConfig, Mapping[str, Any]]]
            ) -> dict[str, Any]:
    manifest = read_manifest(cfg.model_dir)
    models = []
    for i, (vlm, report) in enumerate(reports):
        paper_model = PAPER_MODELS[i] if i < len(PAPER_MODELS) else None
        rows = []
        for cond in report["conditions"]:
            row = {"condition": cond["name"], "title": cond["title"], "sets": {}}
            for name in SETS:
                r = report["results"].get(name, {}).get(cond["name"])
                paper = PAPER.get(paper_model or "", {}).get(cond["name"])
                row["sets"][name] = {
                    "accuracy": r["accuracy"] if r else None,
                    "correct": r["correct"] if r else None, "n": r["n"] if r else None,
                    "invalid_answer": r["invalid_answer"] if r else None,
                    "confusion": r["confusion"] if r else None,
                    "paper": paper[SETS.index(name)] if paper else None}
            rows.append(row)
        # The stand-in's loopback port changes every run: not part of the result.
        where = "simulated VLM, in process" if cfg.standin else vlm.base_url
        models.append({"model": vlm.model, "base_url": where,
                       "beside": paper_model, "rows": rows, "prompts": report["prompts"],
                       "images": report["images"]})
    return {
        "title": "Table I" + (" (simulated VLM)" if cfg.standin else ""),
        "simulated_vlm": cfg.standin,
        "protocol": "one query per unseen press (offset-0 input), candidates = the set's "
                    "labels, temperature 0; invalid answers count as wrong",
        "tactile_model": {"dir": str(cfg.model_dir), "created_by": manifest.get("created_by"),
                          "decoder": manifest.get("training", {}).get("vq", {}).get(
                              "config", {}).get("model", {}).get("decoder"),
                          "database": manifest.get("database")},
        "limit": cfg.limit,
        "models": models,
        "paper": {m: {c: dict(zip(SETS, v, strict=True)) for c, v in rows.items()}
                  for m, rows in PAPER.items()},
    }


def markdown(s: Mapping[str, Any]) -> str:
    lines = [f"# {s['title']}", ""]
    if s["simulated_vlm"]:
        lines += [
            "**Simulated VLM, not a real model.** These answers come from "
            "`edge/sim/standin_vlm.py`: its sight compares the photo with each candidate's "
            "picture (a food and its replica look the same), and its only knowledge of touch "
            "is a reviewed table of how much objects give, by name "
            "(`edge/sim/common_sense.py`). It never reads the simulator's physics or the "
            "pressed object's label. `simulated-vlm` stands beside the paper's GPT-4V, "
            "`simulated-vlm-vision-led` (it keeps its sight's answer unless touch points "
            "clearly elsewhere) beside the paper's LLaVA, which hardly used the touch text. "
            "The table checks the chain press -> embedding -> names -> common sense -> label "
            "and how it moves with the encoder, the database and the descriptions; it says "
            "nothing about any real VLM.", ""]
    tm = s["tactile_model"]
    db = tm.get("database") or {}
    lines += [f"Tactile model `{tm['dir']}` (decoder `{tm['decoder']}`; database "
              f"{db.get('references')} references of {db.get('classes')} classes); "
              f"{s['protocol']}" + (f"; first {s['limit']} presses per set"
                                    if s["limit"] else "") + ".", "",
              "| model | method | FoodReplica | Cube | paper: FoodReplica | paper: Cube |",
              "| --- | --- | --- | --- | --- | --- |"]
    for m in s["models"]:
        for row in m["rows"]:
            ours = [row["sets"][name] for name in SETS]
            paper = [f"{v['paper']:.1f} % ({m['beside']})" if v["paper"] is not None
                     else "" for v in ours]
            lines.append(f"| `{m['model']}` | {row['title']} | "
                         + " | ".join(_cell(v if v["n"] else None) for v in ours)
                         + " | " + " | ".join(paper) + " |")
    lines += ["", "Invalid answers (not a candidate after the corrective retry; counted as "
              "wrong):", "", "| model | method | FoodReplica | Cube |", "| --- | --- | --- | --- |"]
    for m in s["models"]:
        for row in m["rows"]:
            lines.append(f"| `{m['model']}` | {row['title']} | " + " | ".join(
                str(row["sets"][name]["invalid_answer"]) for name in SETS) + " |")
    lines += _decoders(s)
    prompts = s["models"][0]["prompts"] if s["models"] else {}
    lines += ["", "Answers are a strict JSON enum of the candidates; the paper's GPT-4V and "
              "LLaVA answered in free text. The paper's objects were real, ours are "
              "simulated presses with a simulated camera. Prompt templates: " + ", ".join(
                  f"`{mode}` sha256 {p['sha256'][:12]}" for mode, p in prompts.items())
              + ". Confusion matrices: `table1.json` and `confusion_<model>_<set>.png`.", ""]
    return "\n".join(lines)


def _decoders(s: Mapping[str, Any]) -> list[str]:
    """One generated line per model setting the paper's decoder beside the zero-input one."""
    out = []
    for m in s["models"]:
        rows = {r["condition"]: r for r in m["rows"]}
        if "vq_top3" not in rows or "vq_zeros_top3" not in rows:
            continue
        pairs = ", ".join(
            f"{DATASET_TITLES[name]} {_cell(rows['vq_top3']['sets'][name])} against "
            f"{_cell(rows['vq_zeros_top3']['sets'][name])}" for name in SETS
            if rows["vq_top3"]["sets"][name]["n"])
        out.append(f"- `{m['model']}`, top-3, the paper's decoder against the zero-input "
                   f"one: {pairs}.")
    if not out:
        return []
    return ["", "Decoders (the shipped model has the paper's; retrieval figures in "
            "`../eval.md`, section Decoders):", "", *out]


def write_report(cfg: Table1Config, reports: Sequence[tuple[VLMConfig, Mapping[str, Any]]]
                 ) -> dict[str, Any]:
    s = summary(cfg, reports)
    cfg.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(cfg.out / REPORT_JSON, json.dumps(s, indent=1) + "\n")
    atomic_write_text(cfg.out / REPORT_MD, markdown(s))
    for vlm, report in reports:
        src_dir = _cache_dir(cfg.work, vlm.model, cfg.standin)
        for ds in report["datasets"]:
            src = src_dir / f"confusion_{eval_vlm.slug(ds['name'])}.png"
            dest = cfg.out / f"confusion_{eval_vlm.slug(vlm.model)}_{eval_vlm.slug(ds['name'])}.png"
            if src.resolve() != dest.resolve():
                with contextlib.suppress(FileNotFoundError):
                    shutil.copyfile(src, dest)
    log.info("Table I written to %s", cfg.out / REPORT_MD)
    return s


def validate(cfg: Table1Config) -> None:
    if cfg.second is not None and cfg.standin:
        raise EvalVLMError("--second-model needs --url (the simulated VLM brings its own "
                           "second model)")
    if cfg.first.configured and not cfg.first.model:
        raise EvalVLMError("--url needs --model")
    missing = [str(d) for d in cfg.unseen if not d.exists()]
    if missing:
        raise EvalVLMError(f"no recordings at {', '.join(missing)} (`vt-train release` "
                           "records them)")
    unknown = [d.name for d in cfg.unseen if d.name not in DATASET_TITLES]
    if unknown:
        log.warning("sets %s are not the paper's; their columns are left out of the table",
                    ", ".join(unknown))
