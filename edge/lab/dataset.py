"""A collected dataset directory: ``DIR/dataset.json`` and ``DIR/<label>/<label>_NNN.press.npz``
(a press's photo beside it: ``<label>_NNN.jpg``).

``dataset.json`` keeps the recorder's keys (``dataset``; ``classes`` with ``label``,
``split``, ``description``, ``x_th``, ``rate_hz``) plus ``recorder`` (a sentence), ``origin``
(as in a model's manifest), ``plan_sha256`` and, per class, ``presses`` (planned), ``photo``
and ``failed`` (the presses collect did not keep, with their reasons). ``rate_hz`` is the
median over the class's kept presses of the rate xela_server sent at over the crop window
(:func:`edge.core.preprocess.fresh_rate`).

:func:`summarize` (``vt-edge dataset summary DIR``) reads it all back per class and flags
what looks wrong. A press's "peak" is its peak norm (:func:`edge.core.preprocess.peak_norm`),
the figure collect prints and episodes keep.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from edge import __version__
from edge.core import preprocess, recording
from edge.core.atomic import atomic_write_text
from edge.core.errors import ConfigError
from edge.core.preprocess import DEFAULT_WINDOW, WindowSpec
from edge.core.recording import DATASET_INDEX

if TYPE_CHECKING:
    from edge.lab.plan import Plan

PHOTO_SUFFIX = ".jpg"


def photo_path(press: Path) -> Path:
    """The photo of the press at ``press``: the same stem, ``.jpg``."""
    return press.with_name(press.name[: -len(recording.SUFFIX)] + PHOTO_SUFFIX)


def existing_presses(out: Path, label: str) -> dict[int, Path]:
    """The kept presses of ``label`` in ``out`` by number."""
    pattern = re.compile(rf"{re.escape(label)}_(\d+){re.escape(recording.SUFFIX)}")
    found = {}
    folder = out / label
    if folder.is_dir():
        for path in folder.iterdir():
            m = pattern.fullmatch(path.name)
            if m:
                found[int(m.group(1))] = path
    return dict(sorted(found.items()))


def read_index(out: Path) -> dict[str, Any] | None:
    """``out/dataset.json``, or None where there is none; ConfigError naming the file."""
    path = out / DATASET_INDEX
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot read: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("classes"), list):
        raise ConfigError(f"{path}: not a dataset index (no \"classes\" list)")
    return data


def class_rate(out: Path, label: str) -> float | None:
    """``rate_hz`` of ``label`` in ``out``: the median of its kept presses' window rates
    (None: none measured)."""
    return median_rate(preprocess.recording_rate(recording.load(p)).window_hz
                       for p in existing_presses(out, label).values())


def median_rate(rates: Iterable[float | None]) -> float | None:
    """The median of the rates measured (None among them: not measured), to 0.1 Hz."""
    measured = [r for r in rates if r is not None]
    return round(float(np.median(measured)), 1) if measured else None


def write_index(out: Path, index: dict[str, Any]) -> None:
    atomic_write_text(out / DATASET_INDEX, json.dumps(index, indent=2) + "\n")


def new_index(name: str, recorder: str, origin: dict[str, Any], plan_sha256: str
              ) -> dict[str, Any]:
    return {"dataset": name, "recorder": recorder, "origin": origin,
            "plan_sha256": plan_sha256, "software_version": __version__, "classes": []}


def same_origin(a: dict[str, Any] | None, b: dict[str, Any] | None) -> bool:
    """Whether two origins are one robot and sensor (who pressed may differ)."""
    def key(o: dict[str, Any] | None) -> tuple:
        o = o or {}
        sensor = o.get("sensor") or {}
        return o.get("kind"), o.get("robot"), sensor.get("model")
    return key(a) == key(b)


# A press stopped late when a frame over its x_th came this many frame periods before the
# stop: the stop follows the first such frame within one period.
LATE_PERIODS = 2.0
# A gap between received frames longer than this many frame periods, inside the model's
# crop window, leaves the window short of samples.
GAP_PERIODS = 3.0


@dataclass(frozen=True)
class PressCheck:
    path: Path
    x_th: float
    peak: float  # the press's peak norm (tactile units)
    stop_latency_ms: float | None
    flags: tuple[str, ...]
    rate_hz: float | None = None  # the stream's rate over the crop window (frames/s)


@dataclass(frozen=True)
class ClassSummary:
    label: str
    split: str
    x_th: float | None  # what dataset.json (or the plan) says
    planned: int | None
    failed: dict[str, int]  # result -> count, from dataset.json
    presses: tuple[PressCheck, ...]
    problems: tuple[str, ...]  # what makes the summary exit non-zero

    @property
    def thresholds(self) -> list[float]:
        return sorted({p.x_th for p in self.presses})

    @property
    def rate_hz(self) -> float | None:
        return median_rate(p.rate_hz for p in self.presses)


@dataclass(frozen=True)
class Summary:
    directory: Path
    dataset: str
    origin: dict[str, Any] | None
    classes: tuple[ClassSummary, ...]

    @property
    def problems(self) -> list[str]:
        return [f"{c.label}: {p}" for c in self.classes for p in c.problems]


def check_press(path: Path, window: WindowSpec = DEFAULT_WINDOW) -> PressCheck:
    rec = recording.load(path)
    norms = preprocess.norm(preprocess.recording_units(rec))
    flags = []
    # Late is judged by when the first frame over x_th came, not by how far past x_th the
    # norm is: on a rigid object one frame period takes it from below x_th to 10x and more
    # (glass, steel), and the hold's squeeze goes on past that by design.
    over = rec.recv_time[(norms > rec.threshold) & (rec.recv_time <= rec.t_stop)]
    if len(over) and rec.t_stop - over[0] > LATE_PERIODS * window.period_s:
        flags.append(f"the stop came {(rec.t_stop - over[0]) * 1e3:.0f} ms after the first "
                     "frame over x_th (stopped late?)")
    t0, t1 = rec.t_stop - window.before_s, rec.t_stop + window.after_s
    t = rec.recv_time
    if not len(t) or t[0] > t0 + window.period_s or t[-1] < t1 - window.period_s:
        flags.append("the recording does not cover the crop window")
    else:
        inside = t[(t >= t0 - window.period_s) & (t <= t1 + window.period_s)]
        gaps = np.diff(inside)
        if len(gaps) and gaps.max() > GAP_PERIODS * window.period_s:
            at = float(inside[int(gaps.argmax())] - rec.t_stop)
            flags.append(f"stream gap of {gaps.max() * 1e3:.0f} ms in the crop window "
                         f"({at * 1e3:+.0f} ms from the stop)")
    latency = rec.extra.get("stop_latency_s")
    return PressCheck(path, rec.threshold, preprocess.recording_peak(rec),
                      None if latency is None else float(latency) * 1e3, tuple(flags),
                      preprocess.recording_rate(rec, window).window_hz)


def summarize(out: str | Path, plan: Plan | None = None) -> Summary:
    """Every class of ``out`` (and of ``plan``): what was kept and what looks wrong."""
    out = Path(out)
    index = read_index(out) or {"classes": []}
    entries = {c["label"]: c for c in index["classes"] if isinstance(c, dict) and "label" in c}
    planned_classes = {c.label: c for c in plan.classes} if plan is not None else {}
    labels = list(entries) + [label for label in planned_classes if label not in entries]
    classes = []
    for label in labels:
        entry = entries.get(label, {})
        pc = planned_classes.get(label)
        planned = pc.presses if pc is not None else entry.get("presses")
        # A class of the plan not collected yet: its split and x_th as the plan says.
        split, x_th = (pc.split, pc.x_th) if pc is not None else ("?", None)
        presses = tuple(check_press(p) for p in existing_presses(out, label).values())
        failed: dict[str, int] = {}
        for f in entry.get("failed", []):
            failed[f.get("result", "?")] = failed.get(f.get("result", "?"), 0) + 1
        problems = []
        thresholds = Counter(p.x_th for p in presses)
        if len(thresholds) > 1:
            usual = thresholds.most_common(1)[0][0]
            odd = [p.path.name for p in presses if p.x_th != usual]
            problems.append(f"mixes thresholds {', '.join(f'{x:g}' for x in sorted(thresholds))}"
                            f" ({', '.join(odd)} unlike the class's {usual:g})")
            presses = tuple(
                p if p.x_th == usual else replace(p, flags=(*p.flags, f"x_th {p.x_th:g} unlike "
                                                         f"the class's {usual:g}"))
                for p in presses)
        if planned is not None and len(presses) < planned:
            problems.append(f"{len(presses)} of {planned} planned presses")
        classes.append(ClassSummary(label, entry.get("split", split), entry.get("x_th", x_th),
                                    planned, failed, presses, tuple(problems)))
    return Summary(out, str(index.get("dataset", out.name)), index.get("origin"),
                   tuple(_check_rates(classes)))


def _check_rates(classes: list[ClassSummary]) -> list[ClassSummary]:
    """A class whose stream rate is off the dataset's (the median of the classes') has a
    problem: its crops are interpolated from a different number of frames, and ``vt-train
    build`` refuses the mix."""
    usual = median_rate(c.rate_hz for c in classes)
    if usual is None:
        return classes
    return [c if (why := preprocess.rate_problem(c.rate_hz, usual)) is None else replace(
        c, problems=(*c.problems, f"stream at {why}, the dataset's rate: re-collect it at "
                     f"the others' rate ({preprocess.RATE_SETTING})")) for c in classes]


def _describe_origin(origin: dict[str, Any] | None) -> str:
    if not origin:
        return "not recorded (an older dataset: the emulated robot)"
    sensor = origin.get("sensor") or {}
    where = "the emulated robot" if origin.get("kind") == "emulated" else (
        f"robot {origin.get('robot')}")
    pads = f", {sensor.get('model')} pads" if sensor.get("model") else ""
    serials = f" ({', '.join(sensor['serials'])})" if sensor.get("serials") else ""
    return f"{where}{pads}{serials}, pressed by {origin.get('recorder', '?')}"


def format_summary(summary: Summary) -> str:
    lines = [f"dataset {summary.dataset} in {summary.directory}",
             f"origin: {_describe_origin(summary.origin)}", "",
             f"{'class':<24} {'split':<5} {'kept':>9} {'failed':>6} {'x_th':>8} "
             f"{'peak median':>11} {'IQR':>7} {'stop ms':>7} {'rate Hz':>7}"]
    flagged = []
    for c in summary.classes:
        peaks = [p.peak for p in c.presses]
        lat = [p.stop_latency_ms for p in c.presses if p.stop_latency_ms is not None]
        kept = f"{len(c.presses)}/{c.planned}" if c.planned is not None else str(len(c.presses))
        x_th = ",".join(f"{x:g}" for x in c.thresholds) or (
            f"{c.x_th:g}" if c.x_th is not None else "-")
        if peaks:
            q1, med, q3 = np.percentile(peaks, [25, 50, 75])
            peak = f"{med:11.4f} {q3 - q1:7.4f}"
        else:
            peak = f"{'-':>11} {'-':>7}"
        latency = f"{np.median(lat):7.2f}" if lat else f"{'-':>7}"
        rate = f"{c.rate_hz:7.1f}" if c.rate_hz is not None else f"{'-':>7}"
        lines.append(f"{c.label:<24} {c.split:<5} {kept:>9} {sum(c.failed.values()):>6} "
                     f"{x_th:>8} {peak} {latency} {rate}")
        off_grid = preprocess.rate_problem(c.rate_hz, DEFAULT_WINDOW.rate_hz)
        if off_grid is not None:
            flagged.append(f"{c.label}: stream at {off_grid}, the crop's grid and the shipped "
                           "model's rate: recognise these presses with a model built from "
                           f"presses at this rate ({preprocess.RATE_SETTING})")
        if c.failed:
            flagged.append(f"{c.label}: not kept: " + ", ".join(
                f"{n} {why}" for why, n in sorted(c.failed.items())))
        flagged += [f"{p.path.name}: {f}" for p in c.presses for f in p.flags]
    if flagged:
        lines += ["", "look at:"] + [f"  {f}" for f in flagged]
    problems = summary.problems
    lines += ["", "peak: a press's peak norm over its tare, closing to opening (the hold "
              "included)", "rate: the frames/s xela_server sent at over a press's crop window"]
    lines += ["", "problems:" if problems else "no problems: every class complete, one "
              "threshold per class, one stream rate"] + [f"  {p}" for p in problems]
    return "\n".join(lines)
