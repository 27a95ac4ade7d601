"""What teaching buys, from one command (``vt-edge sim teaching``): the teaching curve, the
familiarity figure's ROC AUC and teaching end to end through the running daemon.

- **Teaching curve.** Each unseen class (FoodReplica and Cube: the catalogue's classes the
  shipped model's database does not hold) is taught k presses of the dataset recorder (the
  robot's own press controller on the virtual clock) through the daemon's teaching code
  (:func:`edge.runtime.compute.teach_press` into a references overlay in a temporary state
  directory), k growing as a lab would teach more; then fresh presses of it are looked up as
  every recognition is (:func:`edge.runtime.compute.analyse_press`): the share whose nearest
  reference class is the taught one. Two ways: each class taught *alone* (the one new object
  of a lab), and all of them taught *together* (a lab that taught its whole set, where a food
  and its replica compete). At k = 0 the class is unknown: the share is 0, and where its
  presses land instead (the top-1 spread) is reported.
- **Table I style** at k = 0 and the largest k with the simulated VLM
  (:func:`edge.sim.standin_vlm.decide`, asked in this process): Table I's candidates (the
  set's labels), the simulated camera's photo, the touch sentence the daemon builds from the
  nearest classes of the taught database. It is not a real VLM.
- **Familiarity.** Its ROC AUC for telling presses of the unseen classes from held-out presses
  of the reference classes (the shipped database, nothing taught): the daemon's figure (what
  :func:`edge.runtime.compute.analyse_press` reports: the channel-mean space where the
  database has features), beside the embedding's ratio (the daemon's figure on a database
  without features), the nearest embedding distance it replaced, and the trivial baseline's:
  the nearest distance on each channel's mean over the model input, standardised, among the
  recorder's reference presses (train/eval/evaluate.py's baseline). The daemon's figure and
  the baseline differ only in their references (the database's presses at every offset; the
  recorder's at offset 0). Three ways: FoodReplica against the held-out presses
  of every other reference class from the first (where the familiarity was chosen), Cube
  against the rest, and all together. ``--only familiarity`` measures it alone.
- **End to end.** Classes taught through ``POST /v1/teach`` on ``vt-edge run`` on the emulated
  robot (:func:`edge.lab.stack.sim_stack`), then recognised through ``POST /v1/recognize``:
  their nearest-class share against the recorder path's for the same classes taught together
  with the same number of presses, and the seconds each taught press took on the daemon.
"""

from __future__ import annotations

import json
import logging
import math
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edge.core import preprocess, recording
from edge.core.atomic import atomic_write_text
from edge.core.descriptions import tactile_words
from edge.core.errors import EdgeError
from edge.core.model import (
    Familiarity,
    ModelRef,
    ReferenceDatabase,
    model_ref,
    rank_percentile,
)
from edge.core.progress import Progress
from edge.lab.consistency import (
    daemon_press,
    dataset_recordings,
    dataset_transport,
)
from edge.lab.stack import http_json, sim_stack
from edge.runtime.compute import Analysis, analyse_press, model_for, teach_press
from edge.runtime.references import Source
from edge.sim.camera import render
from edge.sim.catalogue import DATASETS, get
from edge.sim.standin_vlm import DEFAULT as VLM_PROFILE
from edge.sim.standin_vlm import decide

log = logging.getLogger(__name__)

UNSEEN_SETS = ("foodreplica", "cube")
KS = (1, 2, 5)
FRESH_PRESSES = 5  # per unseen class, after teaching
REFERENCE_PRESSES = 10  # per reference class, the trivial baseline's reference presses
HELD_OUT_PRESSES = 5  # per reference class, fresh presses of known objects
E2E_CLASSES = ("macaron", "boiled_kiri_mochi")
# What ``--only`` may name: the familiarity's AUC alone (no teaching, no daemon).
ONLY = ("familiarity",)
# Who taught, in each reference's entry.
SOURCE: Source = "cli"
# One teaching through the daemon: each press, with its arm moves, takes a few seconds.
TEACH_PRESS_TIMEOUT_S = 60.0
# A z of 1.96: two shares "agree" when they differ by less than this many standard errors
# of their difference (with Yates' continuity correction, so that two shares of 1.0 from a
# few presses still allow one press either way).
AGREE_Z = 1.96


def unseen_classes(ref: ModelRef) -> list[str]:
    """The catalogue's FoodReplica and Cube classes that the model's database lacks."""
    known = set(model_for(ref).database.labels)
    return [c.name for s in UNSEEN_SETS for c in DATASETS[s] if c.name not in known]


def set_of(name: str) -> str:
    return get(name).split


def description_of(name: str) -> str:
    """What a lab teaching ``name`` says it is: the catalogue's description, or (the unseen
    classes have none) its name in words, less those the description rule refuses as saying
    how it feels ("raw kabocha squash" -> "raw kabocha")."""
    if get(name).description:
        return get(name).description
    words = name.split("_")
    feel = set(tactile_words(" ".join(words)))
    return " ".join(w for w in words if w not in feel)


def candidates_of(name: str) -> list[str]:
    """Table I's candidates for a press of ``name``: its set's labels."""
    return [c.name for c in DATASETS[set_of(name)]]


def roc_auc(positive: Sequence[float], negative: Sequence[float]) -> float:
    """The probability that a positive scores above a negative (ties count half)."""
    p = np.asarray(positive, dtype=np.float64)[:, None]
    n = np.asarray(negative, dtype=np.float64)[None, :]
    return float(((p > n).sum() + 0.5 * (p == n).sum()) / (p.size * n.size))


def agree_margin(p1: float, n1: int, p2: float, n2: int) -> float:
    """The largest difference between two shares (of ``n1`` and ``n2`` presses) that noise
    allows: :data:`AGREE_Z` standard errors of the pooled share, plus the continuity
    correction."""
    pooled = (p1 * n1 + p2 * n2) / (n1 + n2)
    return (AGREE_Z * math.sqrt(pooled * (1 - pooled) * (1 / n1 + 1 / n2))
            + 0.5 * (1 / n1 + 1 / n2))


def _model_input(rec: recording.Recording, spec: preprocess.WindowSpec) -> np.ndarray:
    """The model's input at offset 0, as :func:`analyse_press` cuts it."""
    window = preprocess.crop(rec.recv_time, preprocess.recording_units(rec), rec.t_stop, spec)
    return preprocess.subsample(window, 0, spec)


def baseline_percentiles(references: Sequence[recording.Recording],
                         queries: Sequence[recording.Recording],
                         spec: preprocess.WindowSpec) -> np.ndarray:
    """The familiarity percentile on the trivial baseline's features: each query's nearest
    reference distance among the references' own leave-one-out nearest distances."""
    ref_f = np.array([_model_input(r, spec).mean(axis=0, dtype=np.float64) for r in references])
    mean, std = ref_f.mean(axis=0), ref_f.std(axis=0)
    std[std <= 0] = 1.0  # a channel that never moves is left unscaled
    ref_f = (ref_f - mean) / std
    q_f = (np.array([_model_input(r, spec).mean(axis=0, dtype=np.float64)
                     for r in queries]) - mean) / std
    d = np.linalg.norm(ref_f[:, None] - ref_f[None], axis=2)
    np.fill_diagonal(d, np.inf)
    loo = np.sort(d.min(axis=1))
    return rank_percentile(loo, np.linalg.norm(q_f[:, None] - ref_f[None], axis=2).min(axis=1))


@dataclass(frozen=True)
class Looked:
    """The fresh presses of one class looked up at one k."""

    nearest: list[str]  # each press's nearest reference class
    vlm: list[str] | None = None  # the simulated VLM's answers, where asked

    def share(self, label: str) -> float:
        return float(np.mean([n == label for n in self.nearest]))

    def vlm_share(self, label: str) -> float | None:
        return None if self.vlm is None else float(np.mean([a == label for a in self.vlm]))


def look_up(ref: ModelRef, name: str, recs: Sequence[recording.Recording], ask: bool
            ) -> Looked:
    analyses: list[Analysis] = [analyse_press(ref, r) for r in recs]
    answers = None
    if ask:
        photo = render(name)
        answers = [decide(VLM_PROFILE, photo, a.description, candidates_of(name)).label
                   for a in analyses]
    return Looked([a.topk[0][0] for a in analyses], answers)


class Teacher:
    """Presses taught into one references overlay, a few at a time (the first of a label
    as a new class with its description, the next appended)."""

    def __init__(self, models: str | Path, directory: Path) -> None:
        self.ref = model_ref(models, directory)
        self.taught: Counter[str] = Counter()

    def teach(self, name: str, recs: Sequence[recording.Recording]) -> None:
        for rec in recs:
            teach_press(self.ref, rec, name, description_of(name), SOURCE,
                        append=self.taught[name] > 0)
            self.taught[name] += 1


def teaching_curve(models: str | Path, classes: Sequence[str], ks: Sequence[int],
                   teach: dict[str, list[recording.Recording]],
                   fresh: dict[str, list[recording.Recording]], tmp: Path,
                   step: Callable[[str], None]) -> dict:
    """The curve, both ways (see the module's docstring), the simulated VLM asked at k = 0
    and the largest k."""
    base = model_ref(models)
    k0 = {c: look_up(base, c, fresh[c], ask=True) for c in classes}
    step("k = 0")
    out: dict[str, dict[str, dict[int, Looked]]] = {"alone": {}, "together": {}}
    for c in classes:
        teacher, done = Teacher(models, tmp / "alone" / c), 0
        out["alone"][c] = {}
        for k in ks:
            teacher.teach(c, teach[c][done:k])
            done = k
            out["alone"][c][k] = look_up(teacher.ref, c, fresh[c], ask=k == ks[-1])
        step(f"{c} alone")
    teacher, done = Teacher(models, tmp / "together"), 0
    for k in ks:
        for c in classes:
            teacher.teach(c, teach[c][done:k])
        done = k
        for c in classes:
            out["together"].setdefault(c, {})[k] = look_up(teacher.ref, c, fresh[c],
                                                           ask=k == ks[-1])
        step(f"together k = {k}")
    rows = []
    for c in classes:
        spread = Counter(k0[c].nearest).most_common()
        rows.append({
            "name": c, "set": set_of(c),
            "k0_nearest": [{"label": lab, "share": n / len(k0[c].nearest)}
                           for lab, n in spread],
            "alone": {str(k): out["alone"][c][k].share(c) for k in ks},
            "together": {str(k): out["together"][c][k].share(c) for k in ks},
            "vlm": {"0": k0[c].vlm_share(c),
                    f"{ks[-1]}_alone": out["alone"][c][ks[-1]].vlm_share(c),
                    f"{ks[-1]}_together": out["together"][c][ks[-1]].vlm_share(c)}})

    def overall(key: str, k: int) -> float:
        return float(np.mean([r[key][str(k)] for r in rows]))

    def vlm(key: str, names: Sequence[str]) -> float:
        return float(np.mean([r["vlm"][key] for r in rows if r["name"] in names]))

    sets = {s: [c for c in classes if set_of(c) == s] for s in UNSEEN_SETS}
    vlm_keys = ("0", f"{ks[-1]}_alone", f"{ks[-1]}_together")
    return {"classes": rows,
            "overall": {"alone": {"0": 0.0, **{str(k): overall("alone", k) for k in ks}},
                        "together": {"0": 0.0, **{str(k): overall("together", k)
                                                  for k in ks}}},
            "vlm": {"profile": VLM_PROFILE.model,
                    "overall": {key: vlm(key, classes) for key in vlm_keys},
                    "per_set": {s: {key: vlm(key, names) for key in vlm_keys}
                                for s, names in sets.items() if names}}}


def nearest_percentiles(db: ReferenceDatabase, zs: Sequence[np.ndarray]) -> np.ndarray:
    """The first familiarity figure: each query's nearest reference distance in the
    embedding among the references' own nearest distances to another press."""
    loo = db.nearest_other_press().min(axis=1)
    loo = np.sort(loo[np.isfinite(loo)])
    return rank_percentile(loo, [db.topk(z, 1)[0][1] for z in zs])


def familiarity_auc(models: str | Path, unseen: dict[str, list[recording.Recording]],
                    held_out: dict[str, list[recording.Recording]],
                    references: Sequence[recording.Recording]) -> dict:
    """The daemon's familiarity's ROC AUC (nothing taught) beside the embedding's ratio, the
    nearest embedding distance and the trivial baseline's, on the choosing split
    (FoodReplica against the held-out presses of the reference classes at even places), the
    reporting one (Cube against the odd ones) and all together; and each unseen class's
    median percentile."""
    ref = model_ref(models)
    db = model_for(ref).database
    names = list(held_out)
    splits = {"choosing": ([c for c in unseen if set_of(c) == "foodreplica"], names[0::2]),
              "reporting": ([c for c in unseen if set_of(c) == "cube"], names[1::2]),
              "all": (list(unseen), names)}
    groups = {**unseen, **held_out}
    recs = [r for recs in groups.values() for r in recs]
    looked = [analyse_press(ref, r, agreement=False) for r in recs]
    zs = [np.asarray(a.z) for a in looked]
    ratio = Familiarity(db, embedding=True)
    scores = {"familiarity": np.array([a.familiarity for a in looked], dtype=np.float64),
              "embedding_ratio": np.array([ratio.percentile(z) for z in zs], dtype=np.float64),
              "nearest_distance": nearest_percentiles(db, zs),
              "baseline": baseline_percentiles(references, recs, ref.window)}
    at, start = {}, 0
    for c, rs in groups.items():
        at[c] = slice(start, start + len(rs))
        start += len(rs)

    def pooled(score: str, classes: Sequence[str]) -> np.ndarray:
        return np.concatenate([scores[score][at[c]] for c in classes]) if classes \
            else np.zeros(0)

    auc = {}
    for split, (pos, neg) in splits.items():
        if pos and neg:
            auc[split] = {score: roc_auc(pooled(score, pos), pooled(score, neg))
                          for score in scores}
            auc[split]["presses"] = [sum(len(unseen[c]) for c in pos),
                                     sum(len(held_out[c]) for c in neg)]
    flat_u, flat_h = list(unseen), names
    return {"space": "channel means" if db.feature is not None else "embedding ratio",
            "auc": auc["all"]["familiarity"],
            "embedding_ratio_auc": auc["all"]["embedding_ratio"],
            "nearest_distance_auc": auc["all"]["nearest_distance"],
            "baseline_auc": auc["all"]["baseline"], "splits": auc,
            "unseen_presses": sum(len(v) for v in unseen.values()),
            "held_out_presses": sum(len(v) for v in held_out.values()),
            "baseline_reference_presses": len(references),
            "median_percentile": {
                key: {"unseen": float(np.median(pooled(key, flat_u))),
                      "held_out": float(np.median(pooled(key, flat_h)))} for key in scores},
            "flagged_at_95": {"unseen": float(np.mean(pooled("familiarity", flat_u) >= 95)),
                              "held_out": float(np.mean(pooled("familiarity", flat_h) >= 95))},
            "unseen_median_by_class": {
                c: {"familiarity": float(np.median(scores["familiarity"][at[c]])),
                    "baseline": float(np.median(scores["baseline"][at[c]]))}
                for c in unseen}}


def end_to_end(classes: Sequence[str], presses: int, fresh: int, config: str | Path,
               step: Callable[[str], None]) -> dict:
    """Each class taught ``presses`` presses through ``POST /v1/teach`` on the running
    daemon, then ``fresh`` recognitions of each: their nearest classes and the seconds of
    each taught press."""
    nearest: dict[str, list[str]] = {}
    press_s: list[float] = []
    with sim_stack(config, classes[0]) as stack:
        for c in classes:
            stack.place(c)
            run = http_json("POST", f"{stack.api}/v1/teach",
                            {"label": c, "description": description_of(c),
                             "presses": presses, "pause_s": 0, "wait": True},
                            timeout=presses * TEACH_PRESS_TIMEOUT_S)
            if run.get("status") != "done":
                raise EdgeError(f"teaching {c} through the daemon failed: "
                                f"{run.get('error') or run}")
            press_s += run["press_s"]
            step(f"{c} taught")
        for c in classes:
            nearest[c] = []
            for _ in range(fresh):
                ep, _tries = daemon_press(stack, c, candidates_of(c))
                if ep is None:
                    raise EdgeError(f"recognising {c} on the daemon failed every try: is the "
                                    "host overloaded?")
                nearest[c].append(ep["topk"][0]["label"])
            step(f"{c} recognised")
    return {"nearest": nearest, "press_s": press_s}


def compare_paths(classes: Sequence[str], daemon: dict[str, list[str]],
                  recorder: dict[str, Looked], presses: int, press_s: Sequence[float]) -> dict:
    rows = []
    for c in classes:
        n_d, n_r = len(daemon[c]), len(recorder[c].nearest)
        p_d = float(np.mean([x == c for x in daemon[c]]))
        p_r = recorder[c].share(c)
        rows.append({"name": c, "daemon": p_d, "recorder": p_r, "presses": [n_d, n_r],
                     "daemon_nearest": daemon[c], "recorder_nearest": recorder[c].nearest})
    n_d = sum(r["presses"][0] for r in rows)
    n_r = sum(r["presses"][1] for r in rows)
    p_d = sum(r["daemon"] * r["presses"][0] for r in rows) / n_d
    p_r = sum(r["recorder"] * r["presses"][1] for r in rows) / n_r
    margin = agree_margin(p_d, n_d, p_r, n_r)
    return {"classes": rows, "taught_presses": presses, "daemon": p_d, "recorder": p_r,
            "allowed_difference": margin, "agree": abs(p_d - p_r) <= margin,
            "seconds_per_taught_press": {
                "median": float(np.median(press_s)), "min": float(np.min(press_s)),
                "max": float(np.max(press_s)), "all": [round(s, 3) for s in press_s]}}


def run_teaching(classes: Sequence[str] | None = None, ks: Sequence[int] = KS,
                 fresh: int = FRESH_PRESSES, reference_presses: int = REFERENCE_PRESSES,
                 held_out: int = HELD_OUT_PRESSES, e2e: Sequence[str] | None = None,
                 seed: int = 0, models: str | Path = "models",
                 config: str | Path = "configs/sim.toml", out: str | Path | None = None,
                 command: str = "vt-edge sim teaching", workers: int = 2,
                 progress: bool = True, only: str | None = None) -> dict:
    """Measure (progress on stderr); write teaching.md/.json into ``out`` if given. ``only``
    (one of :data:`ONLY`) measures that alone."""
    started = time.monotonic()
    ref = model_ref(models)
    unknown = unseen_classes(ref)
    classes = list(classes or unknown)
    for c in classes:
        if c not in unknown:
            raise EdgeError(f"teaching: {c!r} is not an unseen class of the model (one of "
                            f"{', '.join(unknown)})")
    if only is not None and only not in ONLY:
        raise EdgeError(f"teaching --only {only!r}: one of {', '.join(ONLY)}")
    ks = sorted(set(ks))
    if not ks or ks[0] < 1:
        raise EdgeError(f"teaching --ks must be presses of at least 1, got {ks}")
    for what, n, least in (("--fresh", fresh, 1), ("--reference-presses", reference_presses, 2),
                           ("--held-out", held_out, 1)):
        if n < least:
            raise EdgeError(f"teaching {what} must be at least {least}, got {n}")
    e2e = [c for c in E2E_CLASSES if c in classes] or classes[:2] if e2e is None else list(e2e)
    if only is not None:
        e2e = []
    for c in e2e:
        if c not in classes:
            raise EdgeError(f"teaching --e2e-classes: {c!r} is not among the classes measured")
    references = list(model_for(ref).database.labels)
    per_unseen, per_ref = ks[-1] + fresh, reference_presses + held_out
    objects = classes + references
    with Progress("teaching: dataset recorder", len(objects) * max(per_unseen, per_ref),
                  "presses", enabled=progress) as bar:
        recs = dataset_recordings(objects, max(per_unseen, per_ref), [seed],
                                  dataset_transport(models), ref.window, workers, bar)[0]
    teach = {c: recs[c][:ks[-1]] for c in classes}
    fresh_recs = {c: recs[c][ks[-1]:per_unseen] for c in classes}
    curve, recorder_e2e = None, {}
    if only is None:
        curve, recorder_e2e = _curve_and_recorder(models, classes, ks, teach, fresh_recs, e2e,
                                                  progress)
    familiarity = familiarity_auc(
        models, {c: recs[c][:per_unseen] for c in classes},
        {c: recs[c][reference_presses:per_ref] for c in references},
        [r for c in references for r in recs[c][:reference_presses]])
    e2e_report = None
    if e2e:
        with Progress("teaching: daemon on the emulated robot", 2 * len(e2e), "steps",
                      enabled=progress) as bar:
            daemon = end_to_end(e2e, ks[-1], fresh, config, lambda note: bar.update(note=note))
        e2e_report = compare_paths(e2e, daemon["nearest"], recorder_e2e, ks[-1],
                                   daemon["press_s"])
    report = {"command": command, "model": {"directory": str(ref.directory),
                                            "digest": ref.digest},
              "seed": seed, "only": only, "ks": ks, "fresh_presses": fresh,
              "reference_presses": reference_presses, "held_out_presses": held_out,
              "transport": "the model's reference dataset's (its manifest)",
              "curve": curve, "familiarity": familiarity, "end_to_end": e2e_report,
              "simulated_vlm": "edge/sim/standin_vlm.py: a stand-in, not a real VLM",
              "wall_s": time.monotonic() - started}
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "teaching.md", markdown(report))
        atomic_write_text(out / "teaching.json", json.dumps(report, indent=2) + "\n")
    return report


def _curve_and_recorder(models: str | Path, classes: Sequence[str], ks: Sequence[int],
                        teach: dict[str, list[recording.Recording]],
                        fresh: dict[str, list[recording.Recording]], e2e: Sequence[str],
                        progress: bool) -> tuple[dict, dict[str, Looked]]:
    """The teaching curve, and the recorder path's lookups of the classes taught through
    the daemon too (taught together, as the daemon does)."""
    with tempfile.TemporaryDirectory(prefix="vtzero-teaching-") as tmp, \
            Progress("teaching: taught and looked up", len(classes) + len(ks) + 1, "steps",
                     enabled=progress) as bar:
        curve = teaching_curve(models, classes, ks, teach, fresh, Path(tmp),
                               lambda note: bar.update(note=note))
        recorder: dict[str, Looked] = {}
        if e2e:
            teacher = Teacher(models, Path(tmp) / "e2e")
            for c in e2e:
                teacher.teach(c, teach[c])
            recorder = {c: look_up(teacher.ref, c, fresh[c], ask=False) for c in e2e}
    return curve, recorder


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:.0%}"


def markdown(r: dict) -> str:
    fam, e2e = r["familiarity"], r["end_to_end"]
    lines = [
        "# Teaching the robot: the curve, familiarity and the daemon",
        "",
        f"Produced by `{r['command']}` in {r['wall_s'] / 60:.1f} min (model digest "
        f"`{r['model']['digest'][:12]}`, recorder seed {r['seed']}). The presses are the "
        "dataset recorder's (the robot's press controller on the virtual clock, with the "
        "transport timing of the model's reference dataset); they are taught through the "
        "daemon's teaching code (`teach_press` into a references overlay in a temporary "
        "state directory) and looked up as every recognition is (`analyse_press`)."
        + (f" Only the {r['only']} was measured here." if r["only"] else ""),
        "",
        "**The VLM here is simulated, not a real one** (`edge/sim/standin_vlm.py`: it "
        "compares the photo with each candidate's picture and knows by name how much objects "
        "give). Its figures check the chain press -> taught database -> touch sentence -> "
        "label; they say nothing about any real VLM.",
        "",
    ]
    if r["curve"] is not None:
        lines += _curve_lines(r)
    lines += _familiarity_lines(fam)
    if e2e is not None:
        s = e2e["seconds_per_taught_press"]
        lines += [
            "## End to end: teaching through the running daemon",
            "",
            f"{', '.join(row['name'] for row in e2e['classes'])}: each taught "
            f"{e2e['taught_presses']} press{'es' * (e2e['taught_presses'] != 1)} through "
            "`POST /v1/teach` on `vt-edge run` on "
            "the emulated robot (`vt-edge sim serve`), then recognised through "
            "`POST /v1/recognize`; beside them the recorder path with the same classes "
            "taught together, the same number of presses.",
            "",
            "| class | daemon: nearest is the taught class | recorder path |",
            "|---|---:|---:|",
        ]
        lines += [f"| {row['name']} | {_pct(row['daemon'])} ({row['presses'][0]} presses) | "
                  f"{_pct(row['recorder'])} ({row['presses'][1]} presses) |"
                  for row in e2e["classes"]]
        lines += [
            "",
            f"Pooled: daemon {_pct(e2e['daemon'])}, recorder {_pct(e2e['recorder'])}; noise "
            f"allows a difference of {e2e['allowed_difference']:.2f} ({AGREE_Z} standard "
            "errors of the pooled share's difference plus the continuity correction): "
            f"**{'they agree' if e2e['agree'] else 'they do NOT agree'}**.",
            "",
            f"Seconds per taught press on the daemon (its start to its reference written): "
            f"median {s['median']:.2f} s ({s['min']:.2f}-{s['max']:.2f} s over "
            f"{len(s['all'])} presses, pauses between presses 0 s).",
            "",
        ]
    return "\n".join(lines)


def _curve_lines(r: dict) -> list[str]:
    ks, curve = r["ks"], r["curve"]
    kmax = ks[-1]
    n = len(curve["classes"])
    lines = [
        "## Teaching curve",
        "",
        f"{n} unseen classes; each taught k presses, then {r['fresh_presses']} fresh presses "
        "of it looked up: the share whose nearest reference class is the taught one. *Alone*: "
        "only that class taught; *together*: every class of the table taught (a food and its "
        "replica compete). At k = 0 the class is unknown (share 0); the last column says where "
        "its presses land then.",
        "",
        "| class | set | " + " | ".join(f"alone k={k}" for k in ks) + " | "
        + " | ".join(f"together k={k}" for k in ks) + " | k = 0: nearest class (share) |",
        "|---|---|" + "---:|" * (2 * len(ks)) + "---|",
    ]
    for row in curve["classes"]:
        spread = ", ".join(f"{x['label']} ({x['share']:.0%})" for x in row["k0_nearest"][:3])
        lines.append(f"| {row['name']} | {row['set']} | "
                     + " | ".join(_pct(row["alone"][str(k)]) for k in ks) + " | "
                     + " | ".join(_pct(row["together"][str(k)]) for k in ks)
                     + f" | {spread} |")
    ov = curve["overall"]
    lines += [
        "| **all** | | " + " | ".join(f"**{_pct(ov['alone'][str(k)])}**" for k in ks) + " | "
        + " | ".join(f"**{_pct(ov['together'][str(k)])}**" for k in ks) + " | |",
        "",
        "Overall, k = 0 / " + " / ".join(str(k) for k in ks) + ": alone "
        + " / ".join(_pct(ov["alone"][k]) for k in ov["alone"]) + ", together "
        + " / ".join(_pct(ov["together"][k]) for k in ov["together"]) + ".",
        "",
        f"### Table I style, simulated VLM (`{curve['vlm']['profile']}`)",
        "",
        "One question per fresh press: candidates as Table I (the press's set's labels), the "
        "simulated camera's photo, the touch sentence (the descriptions of the three nearest "
        "classes of the database, taught ones included). Asked in this process "
        "(`standin_vlm.decide`), not over HTTP.",
        "",
        f"| set | k = 0 | k = {kmax}, alone | k = {kmax}, together |",
        "|---|---:|---:|---:|",
    ]
    keys = ("0", f"{kmax}_alone", f"{kmax}_together")
    for s, v in curve["vlm"]["per_set"].items():
        lines.append(f"| {s} | " + " | ".join(_pct(v[k]) for k in keys) + " |")
    lines += ["| **all** | " + " | ".join(f"**{_pct(curve['vlm']['overall'][k])}**"
                                        for k in keys) + " |", ""]
    return lines


def _familiarity_lines(fam: dict) -> list[str]:
    splits, med = fam["splits"], fam["median_percentile"]
    titles = {"choosing": "FoodReplica against half the known classes (where it was chosen)",
              "reporting": "Cube against the other half", "all": "all together"}
    space = ("in the channel-mean space (`edge.core.model.Familiarity`: the press's nearest "
             "reference distance on each channel's mean over the model input, standardised "
             "with the references', among every reference's nearest distance to another "
             "press)" if fam["space"] == "channel means" else
             "in the embedding: this database has no features, so the daemon ranks the "
             "*embedding ratio*")
    names = (("familiarity", "familiarity (the daemon's)"),
             ("embedding_ratio", "embedding ratio"), ("nearest_distance", "nearest distance"),
             ("baseline", "baseline"))
    lines = [
        "## Familiarity",
        "",
        "ROC AUC for telling presses of the unseen classes from held-out presses of the "
        "reference classes (fresh presses, nothing taught). *Familiarity* is the daemon's "
        f"percentile, {space}; the *embedding ratio* how much nearer the nearest class is "
        "than the eighth nearest in the embedding, ranked among the references' own (each "
        "reference's press left out); *nearest distance* the nearest reference's embedding "
        "distance among the references' nearest distances to another press; the trivial "
        "baseline the daemon's channel-mean figure with other references: "
        f"{fam['baseline_reference_presses']} presses of the dataset recorder at offset 0 "
        "instead of the database's presses at every offset.",
        "",
        "| presses | unseen / held-out | familiarity (the daemon's) | embedding ratio | "
        "nearest distance | baseline |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    lines += [f"| {titles[k]} | {v['presses'][0]} / {v['presses'][1]} | "
              f"**{v['familiarity']:.3f}** | {v['embedding_ratio']:.3f} | "
              f"{v['nearest_distance']:.3f} | {v['baseline']:.3f} |"
              for k, v in splits.items()]
    lines += [
        "",
        "Median percentile unseen / held-out: "
        + "; ".join(f"{name} {med[key]['unseen']:.0f} / {med[key]['held_out']:.0f}"
                    for key, name in names)
        + f". Flagged unfamiliar at the default 95th percentile: "
        f"{_pct(fam['flagged_at_95']['unseen'])} of the unseen presses, "
        f"{_pct(fam['flagged_at_95']['held_out'])} of the known objects' fresh ones.",
        "",
        "Unseen classes whose median percentile is at or below the held-out presses' (they "
        "look as familiar as known objects): "
        + (", ".join(f"{c} ({v['familiarity']:.0f})"
                     for c, v in fam["unseen_median_by_class"].items()
                     if v["familiarity"] <= med["familiarity"]["held_out"]) or "none")
        + ".",
        "",
    ]
    return lines


__all__ = ["ONLY", "Looked", "Teacher", "agree_margin", "baseline_percentiles",
           "familiarity_auc", "nearest_percentiles", "roc_auc", "run_teaching",
           "unseen_classes"]
