"""``vt-train transfer``: does touch transfer to objects the embedding never saw?

The method stands on one premise: a press of an unseen object lands near reference objects
that feel like it. This measures it on any labelled set (the robot's press recordings, other
sensors' sequences of :mod:`train.learn.sequences`, or PHAC-2 files read directly), leaving
one object out at a time:

- for each object O and seed: each candidate embedding is fitted on the other objects (the
  seen ones) alone, their presses become the database (every offset, as the robot's), and
  each of O's presses (offset 0, as the robot computes) retrieves its first neighbour and its
  top 3 distinct objects through the robot's retrieval (:class:`edge.core.model.
  ReferenceDatabase`);
- scored against a partner file the user writes before looking at any result: which objects
  feel like which. **sensible first neighbour**: the share of O's presses whose nearest seen
  object is one of O's partners; **partner in top 3**: the share whose top 3 hold one;
  averaged over the objects with partners. Chance: the same shares for a neighbour drawn at
  random among the seen objects;
- **LOO 1-NN among seen**: within the seen objects, each press classified by the nearest
  reference of another press (:func:`train.eval.evaluate.loo_knn`), averaged over the folds;
  chance is one over the number of seen objects.

Candidates: ``shipped`` (the shipped training configuration: z of 16 and the metric term),
``paper`` (the paper's: z of 4, reconstruction only, :data:`train.learn.model.PAPER`) and
``mean`` (the trivial baseline of :mod:`train.eval.evaluate`: each channel's mean over the
window, standardised; no training, so one value whatever the seed), ``physics`` (the press's
peak, stiffness, relaxation and spread, :mod:`train.learn.physics`, standardised) and
``mean+physics`` (both side by side), numpy features like ``mean``. The networks train with
no validation classes (one object left out leaves too few to hold some back for early
stopping), so early stopping watches the training loss, within ``max_epochs``. Every figure is
given per seed (mean, lowest, highest over the seeds), and a difference between two
candidates whose seed ranges overlap is said to be inside the spread.

The partner file is JSON, one object name to the names of the objects that feel like it::

    {"acrylic": ["steel_vase"], "black_foam": ["car_sponge", "kitchen_sponge"]}

Not made symmetric: write both directions where both hold. An object the file does not name
is held out and reported but not scored. Names the data does not hold are refused.

Files: ``transfer.md`` and ``transfer.json`` in ``--out`` (written atomically).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from edge.core.atomic import atomic_write_text
from edge.core.errors import RecordingError
from edge.core.progress import Progress as Bar
from train.eval import evaluate
from train.learn import phac2
from train.learn.data import (
    STD_FLOOR_FRACTION,
    PressSet,
    Splits,
    load_presses,
    press_set,
    training_data_of,
)
from train.learn.model import PAPER, ModelConfig
from train.learn.trainer import Progress, TrainConfig, embed, train
from train.ship import database

log = logging.getLogger(__name__)

REPORT_MD = "transfer.md"
REPORT_JSON = "transfer.json"
FORMATS = ("presses", "phac2")
# Candidate embeddings: what changes from the shipped model configuration (None: no network).
CANDIDATES: dict[str, dict[str, Any] | None] = {
    "shipped": {}, "paper": PAPER, "mean": None, "physics": None, "mean+physics": None}
# The numpy candidates (no network): fitted on the seen presses' windows.
FEATURE_CANDIDATES: dict[str, Callable[[np.ndarray], evaluate.Embedder]] = {
    "mean": evaluate.baseline_embedder, **evaluate.FEATURE_EMBEDDERS}
TITLES = {"shipped": "shipped configuration (z of 16, the metric term)",
          "paper": "paper's configuration (z of 4, reconstruction only)",
          "mean": "trivial baseline (each channel's mean over the window)",
          "physics": "the press's physics (peak, stiffness, relaxation, spread)",
          "mean+physics": "channel means and the press's physics side by side"}
METRICS = (("first", "sensible first neighbour"), ("top3", "partner in top 3"),
           ("loo_1nn", "LOO 1-NN among seen"))
TOP = 3
QUERY_OFFSET = 0
PHAC2_CREDIT = ("PHAC-2 data: the Penn Haptic Adjective Corpus 2 (Chu et al., University of "
                "Pennsylvania GRASP Laboratory), BioTac squeezes by a PR2 robot.")


@dataclass(frozen=True)
class TransferConfig:
    data: Path
    partners: Path
    out: Path
    format: str = "presses"
    candidates: tuple[str, ...] = ("shipped", "paper", "mean")
    seeds: int = 5
    max_epochs: int = 300
    patience: int = 25
    std_floor: float = STD_FLOOR_FRACTION
    threads: int = 1

    def __post_init__(self) -> None:
        unknown = [c for c in self.candidates if c not in CANDIDATES]
        if unknown or not self.candidates:
            raise ValueError(f"unknown candidate {', '.join(unknown) or '(none given)'}; "
                             f"choose from {', '.join(CANDIDATES)}")
        if self.format not in FORMATS:
            raise ValueError(f"unknown format {self.format!r}; choose from "
                             f"{', '.join(FORMATS)}")
        if self.seeds < 1:
            raise ValueError(f"--seeds must be at least 1, got {self.seeds}")

    def command(self) -> str:
        return (f"vt-train transfer --data {self.data} --format {self.format} --partners "
                f"{self.partners} --out {self.out} --candidates {','.join(self.candidates)} "
                f"--seeds {self.seeds} --max-epochs {self.max_epochs} --patience "
                f"{self.patience} --std-floor {self.std_floor:g}")


def read_data(path: str | Path, fmt: str = "presses") -> PressSet:
    """A labelled set: press recordings and ``.seq.npz`` sequences, or PHAC-2 files."""
    if fmt == "phac2":
        return press_set([(str(p), phac2.read(p)) for p in phac2.find(path)])
    return load_presses(path)


def read_partners(path: str | Path, objects: list[str]) -> dict[str, tuple[str, ...]]:
    """The partner file: object -> objects that feel like it, every name one of ``objects``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read the partner file: {exc.strerror or exc}"
                             ) from None
    except json.JSONDecodeError as exc:
        raise RecordingError(f"{path}: the partner file is not JSON: {exc}") from None
    if not isinstance(data, dict) or not all(
            isinstance(v, list) and all(isinstance(n, str) for n in v) for v in data.values()):
        raise RecordingError(f"{path}: the partner file maps each object to a list of objects "
                             'that feel like it, e.g. {"acrylic": ["steel_vase"]}')
    named = list(dict.fromkeys([*data, *(n for v in data.values() for n in v)]))
    unknown = [n for n in named if n not in objects]
    if unknown:
        raise RecordingError(f"{path}: {', '.join(unknown)} not among the data's objects "
                             f"({', '.join(objects)})")
    selves = [k for k, v in data.items() if k in v]
    if selves:
        raise RecordingError(f"{path}: {', '.join(selves)} named as its own partner (a held-"
                             "out object is never among the seen ones)")
    partners = {k: tuple(dict.fromkeys(v)) for k, v in data.items() if v}
    if not partners:
        raise RecordingError(f"{path}: no object has a partner: nothing to score")
    return partners


def fit(name: str, seen: PressSet, seed: int, cfg: TransferConfig
        ) -> tuple[evaluate.Embedder, dict]:
    """Candidate ``name`` fitted on the ``seen`` presses: its embedder and what training did."""
    change = CANDIDATES[name]
    if change is None:
        return FEATURE_CANDIDATES[name](database.reference_inputs(seen)), {}
    shape = seen.x.shape  # (presses, offsets, steps, channels)
    model = replace(ModelConfig(), steps=shape[2], channels=shape[3], **change)
    config = TrainConfig(model=model, seed=seed, max_epochs=cfg.max_epochs,
                         patience=cfg.patience, threads=cfg.threads)
    data = training_data_of(seen, Splits(tuple(seen.classes), (), {}), cfg.std_floor)
    result = train(data, config, None, Progress(enabled=False))
    return ((lambda x: embed(result.model, result.norm, x)),
            {"epochs": result.epochs, "best_epoch": result.best_epoch})


def fold(embedder: evaluate.Embedder, seen: PressSet, held: PressSet, partners: tuple[str, ...],
         seed: int) -> dict[str, Any]:
    """One held-out object against the seen ones: each press's first neighbour and top 3
    (the robot's retrieval over every offset of the seen presses), and LOO 1-NN among them."""
    offsets = database.offsets_of(seen)
    z_all, _ = embedder(database.reference_inputs(seen))
    splits = Splits(tuple(seen.classes), (), {c: c for c in seen.classes})
    # The labels stand in for descriptions: no VLM reads them, so no wording is checked.
    db = database.from_embeddings(seen, splits, z_all, None, k=TOP, tactile_words_ok=True)
    z_held, _ = embedder(held.inputs(QUERY_OFFSET))
    tops = [[label for label, _ in db.topk(z, TOP)] for z in z_held]
    knn = evaluate.loo_knn(z_all[QUERY_OFFSET::len(offsets)], seen.labels, seed, refs=z_all,
                           per_press=len(offsets))
    out: dict[str, Any] = {"first": [t[0] for t in tops], "top3": tops,
                           "loo_1nn": knn["loo_1nn"]}
    if partners:
        out["first_sensible"] = float(np.mean([t[0] in partners for t in tops]))
        out["top3_sensible"] = float(np.mean([bool(set(t) & set(partners)) for t in tops]))
    return out


def chance(objects: list[str], partners: dict[str, tuple[str, ...]]) -> dict[str, float]:
    """The scores of a neighbour drawn at random among the seen objects."""
    n = len(objects) - 1
    k = min(TOP, n)
    scored = [o for o in objects if o in partners]
    first = [len(partners[o]) / n for o in scored]
    top3 = [1 - math.comb(n - len(partners[o]), k) / math.comb(n, k) for o in scored]
    return {"first": float(np.mean(first)), "top3": float(np.mean(top3)), "loo_1nn": 1 / n}


def spread(values: list[float]) -> dict[str, float]:
    arr = np.asarray(values, dtype=np.float64)
    return {"mean": float(arr.mean()), "min": float(arr.min()), "max": float(arr.max()),
            "std": float(arr.std())}


def run(cfg: TransferConfig, progress: bool = True) -> dict[str, Any]:
    """Leave each object out for each seed and candidate; write the reports; return the
    JSON report."""
    started = time.perf_counter()
    presses = read_data(cfg.data, cfg.format)
    objects = presses.classes
    if len(objects) < 3:
        raise RecordingError(f"{cfg.data}: {len(objects)} objects; leaving one out needs at "
                             "least 3 (two seen ones to tell apart)")
    partners = read_partners(cfg.partners, objects)
    seeds = list(range(cfg.seeds))
    networks = [c for c in cfg.candidates if CANDIDATES[c] is not None]
    results: dict[str, dict[str, Any]] = {}
    with Bar("transfer", len(objects) * (len(seeds) * len(networks)
                                         + len(cfg.candidates) - len(networks)),
             "folds", enabled=progress) as bar:
        for name in cfg.candidates:
            # A numpy feature has no seed: one fold per object stands for every seed.
            runs = seeds if CANDIDATES[name] is not None else seeds[:1]
            per_seed: list[dict[str, Any]] = []
            for seed in runs:
                folds = {}
                for held_out in objects:
                    bar.update(0, note=f"{name} seed {seed}, {held_out} held out")
                    seen = presses.select([o for o in objects if o != held_out])
                    embedder, trained = fit(name, seen, seed, cfg)
                    folds[held_out] = fold(embedder, seen, presses.select([held_out]),
                                           partners.get(held_out, ()), seed) | trained
                    bar.update()
                per_seed.append({"seed": seed, "folds": folds, **_averages(folds)})
            if len(runs) < len(seeds):
                per_seed = [per_seed[0] | {"seed": s} for s in seeds]
            results[name] = {"title": TITLES[name], "seeds": per_seed,
                             **{key: spread([s[key] for s in per_seed]) for key, _ in METRICS}}
    report = {
        "command": cfg.command(), "config": {k: str(v) if isinstance(v, Path) else v
                                             for k, v in asdict(cfg).items()},
        "objects": {o: presses.labels.count(o) for o in objects},
        "partners": {o: list(p) for o, p in partners.items()},
        "not_scored": [o for o in objects if o not in partners],
        "window": {"offsets": presses.x.shape[1], "steps": presses.x.shape[2],
                   "channels": presses.x.shape[3]},
        "chance": chance(objects, partners),
        "candidates": results,
        "neighbours": _neighbours(results, objects),
        "differences": differences(results, len(seeds)),
        "seconds": round(time.perf_counter() - started, 1),
    }
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / REPORT_JSON, json.dumps(report, indent=1, sort_keys=True) + "\n")
    atomic_write_text(out / REPORT_MD, markdown(report))
    log.info("transfer: %d objects x %d seeds in %.0f s; report %s", len(objects),
             len(seeds), report["seconds"], out / REPORT_MD)
    return report


def _averages(folds: dict[str, dict[str, Any]]) -> dict[str, float]:
    scored = [f for f in folds.values() if "first_sensible" in f]
    return {"first": float(np.mean([f["first_sensible"] for f in scored])),
            "top3": float(np.mean([f["top3_sensible"] for f in scored])),
            "loo_1nn": float(np.mean([f["loo_1nn"] for f in folds.values()]))}


def _neighbours(results: dict[str, dict[str, Any]], objects: list[str]
                ) -> dict[str, dict[str, list]]:
    """Per candidate and held-out object: its first neighbours, most frequent first, with the
    share of its presses over all seeds."""
    out: dict[str, dict[str, list]] = {}
    for name, res in results.items():
        out[name] = {}
        for obj in objects:
            firsts = Counter(n for s in res["seeds"] for n in s["folds"][obj]["first"])
            total = sum(firsts.values())
            out[name][obj] = [[n, round(c / total, 3)] for n, c in firsts.most_common()]
    return out


def differences(results: dict[str, dict[str, Any]], seeds: int) -> list[str]:
    """A plain sentence per pair of candidates and figure: beyond the seed spread or not (a
    network's spread needs two seeds at least; the numpy features have none)."""
    lines = []
    names = list(results)
    for key, title in METRICS:
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                sa, sb = results[a][key], results[b][key]
                hi, lo = (a, b) if sa["mean"] >= sb["mean"] else (b, a)
                h, lw = results[hi][key], results[lo][key]
                gap = h["mean"] - lw["mean"]
                if round(gap, 2) == 0 and h["min"] == lw["min"] and h["max"] == lw["max"]:
                    lines.append(f"{title}: {a} and {b} are level at {h['mean']:.2f}, seed for "
                                 "seed.")
                elif all(CANDIDATES[n] is None for n in (a, b)):
                    lines.append(f"{title}: {hi} {h['mean']:.2f} against {lo} "
                                 f"{lw['mean']:.2f}: neither depends on a seed, so no spread "
                                 f"to judge the difference of {gap:.2f} by.")
                elif seeds < 2 and any(CANDIDATES[n] is not None for n in (a, b)):
                    lines.append(f"{title}: {hi} {h['mean']:.2f} against {lo} "
                                 f"{lw['mean']:.2f}: one seed, so no spread to judge the "
                                 f"difference of {gap:.2f} by (--seeds).")
                elif h["min"] > lw["max"]:
                    lines.append(f"{title}: {hi} {h['mean']:.2f} is above {lo} "
                                 f"{lw['mean']:.2f} by {gap:.2f}, beyond the seed spread (every "
                                 f"seed of {hi} at or above {h['min']:.2f}, every seed of {lo} "
                                 f"at or below {lw['max']:.2f}).")
                else:
                    lines.append(f"{title}: {hi} {h['mean']:.2f} against {lo} "
                                 f"{lw['mean']:.2f}: the difference of {gap:.2f} is inside the "
                                 f"seed spread ({hi} {h['min']:.2f}-{h['max']:.2f}, {lo} "
                                 f"{lw['min']:.2f}-{lw['max']:.2f}): this data does not tell "
                                 "them apart.")
    return lines


def _cell(s: dict[str, float]) -> str:
    if s["min"] == s["max"]:
        return f"{s['mean']:.2f}"
    return f"{s['mean']:.2f} ({s['min']:.2f}-{s['max']:.2f})"


def markdown(report: dict[str, Any]) -> str:
    cfg = report["config"]
    objects = report["objects"]
    lines = [
        "# Does touch transfer? Leave one object out", "",
        f"Data: `{cfg['data']}` ({cfg['format']}): {len(objects)} objects, "
        f"{sum(objects.values())} presses ("
        + ", ".join(f"{o} {n}" for o, n in objects.items()) + f"); windows of "
        f"{report['window']['steps']} steps x {report['window']['channels']} channels, "
        f"{report['window']['offsets']} offsets per press.",
        f"Seeds: {cfg['seeds']}; training: at most {cfg['max_epochs']} epochs, patience "
        f"{cfg['patience']}, on the training loss (no validation classes); normaliser floor "
        f"{cfg['std_floor']:g} x the RMS of the channels' spreads. Wall time "
        f"{report['seconds']:.0f} s.", "",
        f"Command: `{report['command']}`", "",
        *([PHAC2_CREDIT, ""] if cfg["format"] == "phac2" else []),
        "Partners (written before the run): " + "; ".join(
            f"{o} -> {', '.join(p)}" for o, p in report["partners"].items()) + "."
        + (f" Not scored (no partner written): {', '.join(report['not_scored'])}."
           if report["not_scored"] else ""), "",
        "Mean over the seeds (lowest-highest seed in brackets).", "",
        "| candidate | " + " | ".join(title for _, title in METRICS) + " |",
        "|---" * (len(METRICS) + 1) + "|",
    ]
    names = list(cfg["candidates"])  # in the order asked (the JSON's keys are sorted)
    for res in (report["candidates"][n] for n in names):
        lines.append(f"| {res['title']} | "
                     + " | ".join(_cell(res[key]) for key, _ in METRICS) + " |")
    lines.append("| chance | " + " | ".join(f"{report['chance'][key]:.2f}"
                                             for key, _ in METRICS) + " |")
    lines += ["", "## Inside or beyond the seed spread", ""]
    lines += [f"- {line}" for line in report["differences"]]
    lines += ["", "## First neighbours of each held-out object (share of its presses over the "
              "seeds)", "", "| held out | partners | " + " | ".join(names) + " |",
              "|---" * (len(names) + 2) + "|"]
    for obj in objects:
        cells = [", ".join(f"{n} {share:.2f}" for n, share in report["neighbours"][c][obj][:2])
                 for c in names]
        lines.append(f"| {obj} | {', '.join(report['partners'].get(obj, ())) or '-'} | "
                     + " | ".join(cells) + " |")
    lines.append("")
    return "\n".join(lines)
