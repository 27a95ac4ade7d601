"""``vt-train table1``: the paper's Table I in one command, against any endpoint or the
simulated VLM.

Rows: vision only, the method (VQ-VAE, top-3), top-1 instead of top-3, the beta-VAE, for a
first model (the paper's GPT-4V rows) and a second one (the paper's LLaVA rows); columns: the
accuracy on each test set (any name: the recorder's FoodReplica and Cube, or a lab's own), with
the paper's own numbers beside a set named or mapped (``--paper-set lab_food=foodreplica``) to
FoodReplica or Cube. The report says where the presses came from (each set's ``dataset.json``
origin: the emulated robot, or which robot and sensor), which decoder the tactile model has,
and how to train a missing variant from the data the model was built from. Extra rows: the
zero-input decoder (``vq_zeros_top3``, when its checkpoint exists), the tactile-adjective
ablation (``vq_top3_adjectives``) and the weak-match ablation (``vq_top3_weak``: the method's
prompt, but where the press is unfamiliar by the daemon's flag (``edge.core.model.
Familiarity`` at the default ``[runtime] unfamiliar_percentile``) the touch sentence also says
that it matched the named objects only weakly; the paper's prompt never says so).
``Table1Config.rows`` asks only the rows named (a row and its paper twin, say).

Each model's questions are asked by :mod:`train.eval.eval_vlm` (the robot's prompts and client,
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
from edge.vlm.prompt import WEAK_MATCH
from train.eval import eval_vlm
from train.eval.eval_vlm.config import DEFAULT_CONCURRENCY, EvalVLMConfig
from train.eval.eval_vlm.paper import DATASET_TITLES, PAPER_SETS, paper_set, set_title
from train.eval.eval_vlm.provenance import (
    decoder_title,
    describe_origin,
    model_facts,
    variant_advice,
)
from train.eval.eval_vlm.report import slug
from train.ship.database import TEST_PRESSES_ADDED

log = logging.getLogger(__name__)

REPORT_MD = "table1.md"
REPORT_JSON = "table1.json"
TABLE_CONDITIONS = ("vision_only", "vq_top3", "vq_top1", "beta_top3")
EXTRA_CONDITIONS = ("vq_zeros_top3", "vq_top3_adjectives", "vq_top3_weak")
SETS = PAPER_SETS
# The comparison conditions and the `--variant` of vt-train build that trains their model.
VARIANT_OF = {"beta_top3": "beta", "vq_zeros_top3": "zeros"}

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
    concurrency: int = DEFAULT_CONCURRENCY
    extras: bool = True  # add the extra rows whose checkpoints exist
    paper_sets: Mapping[str, str] = dataclasses.field(default_factory=dict)  # ours -> paper's
    rows: tuple[str, ...] | None = None  # only these rows (None: every row that can run)

    @property
    def standin(self) -> bool:
        return not self.first.configured

    def missing(self) -> dict[str, str]:
        """The comparison rows that cannot run here, each with how to make its model."""
        have = {"beta_top3": self.beta, "vq_zeros_top3": self.zeros}
        wanted = self.wanted()
        facts = model_facts(read_manifest(self.model_dir))
        out = {}
        for name in wanted:
            if name not in have:
                continue
            path = have[name]
            if path is None or not path.exists() or self.reference is None \
                    or not self.reference.exists():
                out[name] = (f"no checkpoint ({path or 'none kept with the model'}) or "
                             f"reference recordings ({self.reference}); train it with "
                             + variant_advice(facts, self.model_dir, VARIANT_OF[name]))
        return out

    def wanted(self) -> tuple[str, ...]:
        """The rows asked for: ``rows``, or all (the extras unless left out)."""
        if self.rows is not None:
            return tuple(c for c in (*TABLE_CONDITIONS, *EXTRA_CONDITIONS) if c in self.rows)
        return (*TABLE_CONDITIONS, *(EXTRA_CONDITIONS if self.extras else ()))

    def conditions(self) -> tuple[str, ...]:
        missing = self.missing()
        for name, why in missing.items():
            log.warning("%s skipped: %s", name, why)
        return tuple(name for name in self.wanted() if name not in missing)


def _cache_dir(work: Path, model: str, standin: bool) -> Path:
    if standin:
        from edge.sim.standin_vlm import knowledge_digest

        return work / f"{slug(model)}@{knowledge_digest()[:12]}"
    return work / slug(model)


async def _run_models(cfg: Table1Config, models: Sequence[VLMConfig], progress: bool
                      ) -> list[tuple[VLMConfig, dict[str, Any]]]:
    conditions = cfg.conditions()
    reports = []
    for vlm in models:
        ecfg = EvalVLMConfig(
            vlm=vlm, out=_cache_dir(cfg.work, vlm.model, cfg.standin), unseen=cfg.unseen,
            model_dir=cfg.model_dir, conditions=conditions, reference=cfg.reference,
            beta=cfg.beta, zeros=cfg.zeros, images=cfg.images, limit=cfg.limit,
            concurrency=cfg.concurrency, paper_sets=cfg.paper_sets)
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
    facts = model_facts(manifest)
    datasets = reports[0][1]["datasets"] if reports else []
    names = [d["name"] for d in datasets]
    models = []
    for i, (vlm, report) in enumerate(reports):
        paper_model = PAPER_MODELS[i] if i < len(PAPER_MODELS) else None
        rows = []
        for cond in report["conditions"]:
            row = {"condition": cond["name"], "title": cond["title"], "sets": {}}
            for name in names:
                r = report["results"].get(name, {}).get(cond["name"])
                paper = PAPER.get(paper_model or "", {}).get(cond["name"])
                beside = paper_set(name, cfg.paper_sets)
                row["sets"][name] = {
                    "accuracy": r["accuracy"] if r else None,
                    "correct": r["correct"] if r else None, "n": r["n"] if r else None,
                    "invalid_answer": r["invalid_answer"] if r else None,
                    "confusion": r["confusion"] if r else None,
                    "paper": paper[SETS.index(beside)] if paper and beside else None}
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
                          "decoder": facts["decoder"], "origin": facts["origin"],
                          "database": manifest.get("database"),
                          "test_presses_added": manifest.get(TEST_PRESSES_ADDED, [])},
        "sets": [{"name": d["name"], "paper_set": paper_set(d["name"], cfg.paper_sets),
                  "origin": d.get("origin"), "presses": d["presses"]} for d in datasets],
        "images": reports[0][1]["images"] if reports else None,
        "missing": cfg.missing(),
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
    sets = s["sets"]
    names = [d["name"] for d in sets]
    mapping = {d["name"]: d["paper_set"] for d in sets if d["paper_set"]}
    beside = [d for d in sets if d["paper_set"]]
    titles = [set_title(n, mapping) for n in names]
    lines += [f"Tactile model `{tm['dir']}`: decoder `{tm['decoder']}` "
              f"({decoder_title(tm['decoder'])}), trained on "
              f"{describe_origin(tm.get('origin'))}; database "
              f"{db.get('references')} references of {db.get('classes')} classes; "
              f"{s['protocol']}" + (f"; first {s['limit']} presses per set"
                                    if s["limit"] else "") + ".", "",
              *_test_presses(tm.get("test_presses_added") or []),
              "| model | method | " + " | ".join(titles + [
                  f"paper: {DATASET_TITLES[d['paper_set']]}" for d in beside]) + " |",
              "| --- | --- |" + " --- |" * (len(names) + len(beside))]
    for m in s["models"]:
        for row in m["rows"]:
            ours = [row["sets"][name] for name in names]
            paper = [row["sets"][d["name"]]["paper"] for d in beside]
            lines.append(f"| `{m['model']}` | {row['title']} | "
                         + " | ".join([_cell(v if v["n"] else None) for v in ours] + [
                             f"{v:.1f} % ({m['beside']})" if v is not None else ""
                             for v in paper]) + " |")
    if not beside:
        lines += ["", "No set stands beside the paper's FoodReplica or Cube: map one with "
                  "`--paper-set NAME=foodreplica` (or `=cube`) to show the paper's columns."]
    lines += ["", "Invalid answers (not a candidate after the corrective retry; counted as "
              "wrong):", "", "| model | method | " + " | ".join(titles) + " |",
              "| --- | --- |" + " --- |" * len(names)]
    for m in s["models"]:
        for row in m["rows"]:
            lines.append(f"| `{m['model']}` | {row['title']} | " + " | ".join(
                str(row["sets"][name]["invalid_answer"]) for name in names) + " |")
    lines += _weak_match(s)
    lines += _decoders(s)
    if s.get("missing"):
        lines += ["", "Rows left out:", "", *(f"- `{name}`: {why}."
                                              for name, why in s["missing"].items())]
    prompts = s["models"][0]["prompts"] if s["models"] else {}
    lines += ["", "Answers are a strict JSON enum of the candidates; the paper's GPT-4V and "
              "LLaVA answered in free text. The paper's objects were real; here "
              + "; ".join(f"{d['name']} is {d['presses']} "
                          f"{describe_origin(d.get('origin'))}" for d in sets)
              + f"; images: {s.get('images')}. Prompt templates: " + ", ".join(
                  f"`{mode}` sha256 {p['sha256'][:12]}" for mode, p in prompts.items())
              + ". Confusion matrices: `table1.json` and `confusion_<model>_<set>.png`.", ""]
    return "\n".join(lines)


def _test_presses(added: Sequence[Mapping[str, Any]]) -> list[str]:
    """Lines saying the database holds presses of a test split (`db add --allow-test`)."""
    if not added:
        return []
    return ["**The database holds test presses**: " + "; ".join(
        f"{a['presses']} presses of {a['label']} from the test split of {a['dataset']}"
        for a in added) + " (`vt-train db add --allow-test`). A set that shares them scores "
        "on presses the database learned.", ""]


def _weak_match(s: Mapping[str, Any]) -> list[str]:
    """What the weak-match row can say here: against the simulated VLM, nothing."""
    if not any(r["condition"] == "vq_top3_weak" for m in s["models"] for r in m["rows"]):
        return []
    line = ("The weak-match row asks the method's question, but where the daemon flags the "
            "press unfamiliar the touch sentence ends \"" + WEAK_MATCH + "\".")
    if s["simulated_vlm"]:
        line += (" The simulated VLM reads only the object names in that sentence, so it "
                 "cannot react to it: the row equals the method's by the stand-in's "
                 "construction, not as evidence. Run it against a real VLM (`--url`).")
    return ["", line]


def _decoders(s: Mapping[str, Any]) -> list[str]:
    """One generated line per model setting the paper's decoder beside the zero-input one."""
    out = []
    for m in s["models"]:
        rows = {r["condition"]: r for r in m["rows"]}
        if "vq_top3" not in rows or "vq_zeros_top3" not in rows:
            continue
        pairs = ", ".join(
            f"{DATASET_TITLES.get(name, name)} {_cell(rows['vq_top3']['sets'][name])} against "
            f"{_cell(rows['vq_zeros_top3']['sets'][name])}" for name in rows["vq_top3"]["sets"]
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
            src = src_dir / f"confusion_{slug(ds['name'])}.png"
            dest = cfg.out / f"confusion_{slug(vlm.model)}_{slug(ds['name'])}.png"
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
    known = (*TABLE_CONDITIONS, *EXTRA_CONDITIONS)
    unknown = [row for row in cfg.rows or () if row not in known]
    if unknown or cfg.rows == ():
        raise EvalVLMError(f"unknown Table I row(s) {', '.join(unknown) or '(none given)'}; "
                           f"known: {', '.join(known)}")
    missing = [str(d) for d in cfg.unseen if not d.exists()]
    if missing:
        raise EvalVLMError(f"no recordings at {', '.join(missing)} (a dataset directory of "
                           "`vt-edge collect`; for the simulated sets `vt-train release`)")
    unmapped = [d.name for d in cfg.unseen
                if paper_set(d.name, cfg.paper_sets) is None]
    if unmapped:
        log.info("sets %s stand beside none of the paper's; --paper-set NAME=foodreplica (or "
                 "=cube) shows the paper's columns beside one", ", ".join(unmapped))
