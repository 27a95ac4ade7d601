"""Do the robot's presses embed where the dataset's do? (``vt-edge sim consistency``)

Presses of given objects through the daemon on the emulated robot (``vt-edge sim serve`` +
``vt-edge run``, driven over HTTP as a user does; the press file each episode stores) against
presses of the same objects made by the dataset recorder (with the transport timing the
shipped model's reference dataset was recorded with, from its manifest), all encoded by the
shipped model with the daemon's own analysis (:func:`edge.runtime.compute.analyse_press`,
offset 0).

Per object: the dataset's spread (median distance of its presses to their centroid), the
daemon presses' median distance to that centroid, and their ratio (1: the daemon's presses
are as close to the dataset's as the dataset's own). Per run: the median ratio over the
objects, the objects above :data:`OBJECT_RATIO_MAX`, and how often a daemon press's nearest
dataset press is of its own object, against the dataset's own leave-one-out 1-NN among the
same objects. The measurement is repeated ``runs`` times with new presses on both sides (run
``k``: dataset seed ``seed + k``, the emulated robot's next draws), so each object's ratio
comes with its spread between runs, and the targets must hold in every run. Beside them, what
noise alone gives: each run's dataset presses against the next run's recorder presses in place
of the daemon's.

How many presses: on the shipped model, subsets of one 3-run measurement gave the median
ratio a standard deviation of 0.23 at 5 daemon against 10 dataset presses (5-95 % 0.96-1.71:
the 1.1-1.6 seen between runs), 0.34 at 3 against 6, and 0.06 between the 3 runs at the
default 10 against 20. A single object's ratio stays noisy at 10 presses (ranges over 3 runs
of 0.4-1.2); the recorder's own presses against another seed's gave one object 2.4.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from edge.core import recording
from edge.core.atomic import atomic_write_text
from edge.core.backoff import Backoff
from edge.core.errors import EdgeError
from edge.core.model import ModelRef, model_ref, read_manifest
from edge.core.preprocess import DEFAULT_WINDOW, WindowSpec
from edge.core.progress import Progress
from edge.lab.record import DEFAULT_TRANSPORT, record_press
from edge.lab.stack import http_json, sim_stack
from edge.runtime.compute import analyse_press
from edge.runtime.store import EpisodeStore
from edge.sim.catalogue import get
from edge.sim.virtual import Transport

log = logging.getLogger(__name__)

OBJECTS = ("raw_kiri_mochi", "boiled_kiri_mochi", "raw_kabocha_squash",
           "boiled_kabocha_squash", "macaron", "resin_replica_macaron", "canele",
           "resin_replica_canele")
DAEMON_PRESSES = 10  # per object and run
DATASET_PRESSES = 20  # per object and run
RUNS = 3
RECOGNIZE_TIMEOUT_S = 60.0
# A press that fails (a stream stalled or a status packet lost on a loaded host) is tried
# again after a pause, doubled each time, that lets a burst of load pass; a press that fails
# every try is left out (and counted) rather than losing the whole measurement.
DAEMON_TRIES = 5
DAEMON_RETRY_PAUSE_S = 2.0
# The longest pause: the fourth, before the fifth and last try (2, 4, 8, 16 s).
DAEMON_RETRY_MAX_PAUSE_S = 16.0
PRESS_FILE = "press.press.npz"
# Targets (issue 19), held in every run: the daemon's presses sit about as close to the
# dataset's as those do to each other, none far off, and are re-identified about as often.
RATIO_TARGET = 1.3
OBJECT_RATIO_MAX = 2.0
REID_MARGIN = 0.10


@dataclass(frozen=True)
class ObjectRow:
    name: str
    dataset_spread: float
    daemon_distance: float

    @property
    def ratio(self) -> float:
        return self.daemon_distance / max(self.dataset_spread, 1e-12)


@dataclass(frozen=True)
class Run:
    """One measurement: new presses on both sides."""

    seed: int  # the dataset presses'
    rows: list[ObjectRow]
    reid_daemon: float  # daemon presses whose 1-NN dataset press is of their object
    loo_dataset: float  # dataset presses' leave-one-out 1-NN among the same objects

    @property
    def median_ratio(self) -> float:
        return float(np.median([r.ratio for r in self.rows]))

    @property
    def above(self) -> list[str]:
        """The objects whose ratio is above :data:`OBJECT_RATIO_MAX`."""
        return [r.name for r in self.rows if r.ratio > OBJECT_RATIO_MAX]

    @property
    def passed(self) -> bool:
        return (self.median_ratio <= RATIO_TARGET and not self.above
                and self.reid_daemon >= self.loo_dataset - REID_MARGIN)

    def to_json(self) -> dict:
        return {"seed": self.seed,
                "objects": [asdict(r) | {"ratio": r.ratio} for r in self.rows],
                "median_ratio": self.median_ratio, "objects_above_max": self.above,
                "reid_daemon": self.reid_daemon, "loo_dataset": self.loo_dataset,
                "passed": self.passed}


@dataclass(frozen=True)
class Report:
    runs: list[Run]
    daemon_presses: int  # per object and run
    dataset_presses: int  # per object and run
    stop_latency_ms: dict[str, float]  # the daemon's, p50/p99 over every run
    wall_s: float  # the whole measurement
    daemon_failed_tries: int = 0  # daemon presses that failed and were pressed again
    daemon_left_out: int = 0  # daemon presses that failed every try
    # The recorder against itself: run k's dataset presses against the next run's in place
    # of the daemon's, the ratios noise alone gives (empty with one run).
    recorder_null: list[Run] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        return [r.name for r in self.runs[0].rows]

    def _per_object(self, attr: str) -> np.ndarray:
        """(runs, objects) of an :class:`ObjectRow` attribute."""
        return np.array([[getattr(r, attr) for r in run.rows] for run in self.runs])

    @property
    def median_ratio(self) -> float:
        """The median over the objects of each object's mean ratio over the runs."""
        return float(np.median(self._per_object("ratio").mean(axis=0)))

    @property
    def passed(self) -> bool:
        return all(run.passed for run in self.runs)

    def to_json(self) -> dict:
        ratios = self._per_object("ratio")
        spread = self._per_object("dataset_spread").mean(axis=0)
        dist = self._per_object("daemon_distance").mean(axis=0)
        objects = [{"name": name, "dataset_spread": float(spread[i]),
                    "daemon_distance": float(dist[i]), "ratio": float(ratios[:, i].mean()),
                    "ratio_runs": ratios[:, i].tolist(), "ratio_min": float(ratios[:, i].min()),
                    "ratio_max": float(ratios[:, i].max())}
                   for i, name in enumerate(self.names)]
        return {"objects": objects,
                "daemon_presses_per_object": self.daemon_presses,
                "dataset_presses_per_object": self.dataset_presses,
                "median_ratio": self.median_ratio,
                "median_ratio_runs": [run.median_ratio for run in self.runs],
                "objects_above_max": sorted({n for run in self.runs for n in run.above}),
                "reid_daemon": float(np.mean([run.reid_daemon for run in self.runs])),
                "loo_dataset": float(np.mean([run.loo_dataset for run in self.runs])),
                "runs": [run.to_json() for run in self.runs],
                "stop_latency_ms": self.stop_latency_ms,
                "daemon_failed_tries": self.daemon_failed_tries,
                "daemon_left_out": self.daemon_left_out,
                "recorder_null": {
                    "median_ratio_runs": [r.median_ratio for r in self.recorder_null],
                    "max_object_ratio_runs": [max(x.ratio for x in r.rows)
                                              for r in self.recorder_null]},
                "wall_s": self.wall_s,
                "targets": {"median_ratio_max": RATIO_TARGET,
                            "object_ratio_max": OBJECT_RATIO_MAX,
                            "reid_min": f"loo_dataset - {REID_MARGIN}",
                            "held_in": "every run"},
                "passed": self.passed}

    def markdown(self, command: str) -> str:
        n = len(self.runs)
        ratios = self._per_object("ratio")
        spread = self._per_object("dataset_spread").mean(axis=0)
        dist = self._per_object("daemon_distance").mean(axis=0)
        lines = [
            "# The robot's presses against the dataset's",
            "",
            f"Produced by `{command}` in {self.wall_s / 60:.1f} min. {n} run{'s' * (n != 1)}, "
            f"each with new presses: {self.daemon_presses} presses per object through "
            "`vt-edge run` on the emulated robot (`vt-edge sim serve`), against "
            f"{self.dataset_presses} presses per object made by the dataset recorder "
            "(`vt-edge sim record`: the same press controller on the virtual clock, with the "
            "transport timing of the model's reference dataset), all encoded by the shipped "
            "model at offset 0.",
            "",
            "| object | dataset spread (median distance to its centroid) | daemon presses' "
            "median distance to that centroid | ratio, mean of the runs | ratio per run |",
            "|---|---:|---:|---:|---|",
        ]
        lines += [f"| {name} | {spread[i]:.3f} | {dist[i]:.3f} | {ratios[:, i].mean():.2f} "
                  f"({ratios[:, i].min():.2f}-{ratios[:, i].max():.2f}) | "
                  + " / ".join(f"{x:.2f}" for x in ratios[:, i]) + " |"
                  for i, name in enumerate(self.names)]
        lines += [
            "",
            f"| run (dataset seed) | median ratio (<= {RATIO_TARGET}) | objects above "
            f"{OBJECT_RATIO_MAX} | re-identification | dataset leave-one-out | targets |",
            "|---|---:|---|---:|---:|---|",
        ]
        lines += [f"| {k + 1} ({run.seed}) | {run.median_ratio:.2f} | "
                  f"{', '.join(run.above) or 'none'} | {run.reid_daemon:.0%} | "
                  f"{run.loo_dataset:.0%} | {'met' if run.passed else 'NOT met'} |"
                  for k, run in enumerate(self.runs)]
        medians = [run.median_ratio for run in self.runs]
        verdict = "met in every run" if self.passed else "NOT met in every run"
        lines += [
            "",
            f"Median ratio **{self.median_ratio:.2f}** (of each object's mean; per run "
            f"{min(medians):.2f}-{max(medians):.2f}, target <= {RATIO_TARGET} in every run, "
            f"and no object above {OBJECT_RATIO_MAX}). Re-identification: a daemon press's "
            "nearest dataset press is of its own object; target: at least the dataset's own "
            f"leave-one-out 1-NN among these objects less {REID_MARGIN:.2f} (chance "
            f"{1 / len(self.names):.0%}). Targets {verdict}.",
            "",
            f"The daemon's stop latency (frame over x_th -> stop packet): p50 "
            f"{self.stop_latency_ms['p50']:.2f} ms, p99 {self.stop_latency_ms['p99']:.2f} ms; "
            f"{self.daemon_failed_tries} daemon presses failed (a loaded host) and were "
            f"pressed again; {self.daemon_left_out} failed every try and are left out.",
            "",
        ]
        if self.recorder_null:
            lines[-1:-1] = [
                "",
                "What noise alone gives: the recorder's presses of the next run in place of "
                "the daemon's, median ratio "
                + " / ".join(f"{r.median_ratio:.2f}" for r in self.recorder_null)
                + ", largest object ratio "
                + " / ".join(f"{max(x.ratio for x in r.rows):.2f}" for r in self.recorder_null)
                + "."]
        return "\n".join(lines)


def daemon_recordings(objects: Sequence[str], presses: int, runs: int, config: str | Path,
                      bar: Progress | None = None
                      ) -> tuple[list[dict[str, list[recording.Recording]]], int, int]:
    """``presses`` recognitions of each object through the daemon in each of ``runs`` runs
    (one emulated robot and daemon for all): the press each stored, how many presses failed
    and were pressed again, and how many failed every try (left out)."""
    out: list[dict[str, list[recording.Recording]]] = []
    failed = left_out = 0
    with sim_stack(config, objects[0]) as stack:
        for run in range(runs):
            out.append({})
            for name in objects:
                out[run][name] = []
                for i in range(presses):
                    ep, tries = daemon_press(stack, name, objects)
                    failed += tries - 1
                    if ep is None:
                        left_out += 1
                        log.warning("daemon press %d of %s failed %d times in a row: left out",
                                    i + 1, name, DAEMON_TRIES)
                    else:
                        path = EpisodeStore(stack.state / "episodes").file(ep["id"], PRESS_FILE)
                        out[run][name].append(recording.load(path))
                    if bar is not None:
                        bar.update(note=f"run {run + 1}/{runs}, {name}")
                if not out[run][name]:
                    raise EdgeError(f"every daemon press of {name} in run {run + 1} failed "
                                    f"{DAEMON_TRIES} times: is the host overloaded?")
    return out, failed, left_out


def daemon_press(stack, name: str, objects: Sequence[str]) -> tuple[dict | None, int]:
    """One recognition of ``name`` (a new draw of it, as a person puts it back) and the
    tries it took; a press that fails is tried again, up to ``DAEMON_TRIES``."""
    backoff = Backoff(DAEMON_RETRY_PAUSE_S, DAEMON_RETRY_MAX_PAUSE_S)
    for tries in range(1, DAEMON_TRIES + 1):
        if tries > 1:
            time.sleep(backoff.next_s())
        stack.place(name)
        ep = http_json("POST", f"{stack.api}/v1/recognize",
                       {"candidates": list(objects), "wait": True,
                        "timeout_s": RECOGNIZE_TIMEOUT_S}, timeout=RECOGNIZE_TIMEOUT_S + 5)
        if "http_status" not in ep and ep.get("status") != "failed":
            return ep, tries
        log.warning("daemon press of %s failed: %s", name, ep.get("error") or ep)
    return None, DAEMON_TRIES


def dataset_transport(models: str | Path) -> Transport:
    """The transport timing the model's reference dataset was recorded with (the manifest's
    ``training.dataset.transport``); the recorder's default for a manifest without one."""
    manifest = read_manifest(models)
    raw = manifest.get("training", {}).get("dataset", {}).get("transport")
    if raw is None:
        return DEFAULT_TRANSPORT
    known = {f.name for f in fields(Transport)}
    if not isinstance(raw, dict) or not set(raw) <= known:
        raise EdgeError(f"{Path(models) / 'manifest.json'}: training.dataset.transport "
                        f"{raw!r} is not a transport ({', '.join(sorted(known))})")
    return Transport(**raw)


def _dataset_press(job: tuple[str, int, int, int, Transport, WindowSpec]) -> recording.Recording:
    name, object_index, index, seed, transport, window = job
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xC0, object_index, index]))
    return record_press(name, rng, transport=transport, window=window).recording


def dataset_recordings(objects: Sequence[str], presses: int, seeds: Sequence[int],
                       transport: Transport = DEFAULT_TRANSPORT,
                       window: WindowSpec = DEFAULT_WINDOW, workers: int = 2,
                       bar: Progress | None = None
                       ) -> list[dict[str, list[recording.Recording]]]:
    """``presses`` recorder presses of each object for each seed (one run per seed)."""
    jobs = [(name, oi, i, seed, transport, window) for seed in seeds
            for oi, name in enumerate(objects) for i in range(presses)]
    recs = []
    with ProcessPoolExecutor(workers) as pool:
        for rec in pool.map(_dataset_press, jobs):
            recs.append(rec)
            if bar is not None:
                bar.update()
    per_run = len(objects) * presses
    return [{name: recs[k * per_run + oi * presses:k * per_run + (oi + 1) * presses]
             for oi, name in enumerate(objects)} for k in range(len(seeds))]


def embed(ref: ModelRef, recs: Sequence[recording.Recording]) -> np.ndarray:
    return np.array([analyse_press(ref, rec).z for rec in recs])


def compare(daemon: dict[str, np.ndarray], dataset: dict[str, np.ndarray], seed: int = 0
            ) -> Run:
    rows = []
    for name, z in dataset.items():
        centroid = z.mean(axis=0)
        spread = float(np.median(np.linalg.norm(z - centroid, axis=1)))
        dist = float(np.median(np.linalg.norm(daemon[name] - centroid, axis=1)))
        rows.append(ObjectRow(name, spread, dist))
    names = list(dataset)
    ref_z = np.concatenate([dataset[n] for n in names])
    ref_y = np.concatenate([[i] * len(dataset[n]) for i, n in enumerate(names)])
    hits = []
    for i, n in enumerate(names):
        for z in daemon[n]:
            hits.append(ref_y[np.argmin(np.linalg.norm(ref_z - z, axis=1))] == i)
    d = np.linalg.norm(ref_z[:, None] - ref_z[None], axis=2)
    np.fill_diagonal(d, np.inf)
    loo = float(np.mean(ref_y[np.argmin(d, axis=1)] == ref_y))
    return Run(seed, rows, float(np.mean(hits)), loo)


def run_consistency(objects: Sequence[str] | None = None, daemon_presses: int = DAEMON_PRESSES,
                    dataset_presses: int = DATASET_PRESSES, seed: int = 0,
                    models: str | Path = "models", config: str | Path = "configs/sim.toml",
                    out: str | Path | None = None, command: str = "vt-edge sim consistency",
                    runs: int = RUNS, progress: bool = True) -> Report:
    """Measure (progress on stderr); write consistency.md/.json into ``out`` if given."""
    started = time.monotonic()
    objects = tuple(objects or OBJECTS)
    for name in objects:
        get(name)  # an unknown name fails here, before anything starts
    if len(objects) < 2:
        raise EdgeError("consistency needs at least two objects (re-identification)")
    for what, n in (("--presses", daemon_presses), ("--dataset-presses", dataset_presses),
                    ("--runs", runs)):
        if n < 1:
            raise EdgeError(f"consistency {what} must be at least 1, got {n}")
    if dataset_presses < 2:
        raise EdgeError("consistency --dataset-presses must be at least 2 (a spread)")
    ref = model_ref(models)
    seeds = [seed + k for k in range(runs)]
    with Progress("consistency: dataset recorder", runs * len(objects) * dataset_presses,
                  "presses", enabled=progress) as bar:
        dataset = dataset_recordings(objects, dataset_presses, seeds, dataset_transport(models),
                                     ref.window, bar=bar)
    with Progress("consistency: daemon on the emulated robot",
                  runs * len(objects) * daemon_presses, "presses", enabled=progress) as bar:
        daemon, failed, left_out = daemon_recordings(objects, daemon_presses, runs, config, bar)
    latencies = [r.extra["stop_latency_s"] * 1e3 for run in daemon for recs in run.values()
                 for r in recs if r.extra.get("stop_latency_s") is not None]
    stop_ms = {"p50": float(np.percentile(latencies, 50)),
               "p99": float(np.percentile(latencies, 99))}
    ds_z = [{n: embed(ref, r) for n, r in ds.items()} for ds in dataset]
    results = [compare({n: embed(ref, r) for n, r in dm.items()}, zs, s)
               for dm, zs, s in zip(daemon, ds_z, seeds, strict=True)]
    null = [compare({n: z[:daemon_presses] for n, z in ds_z[(k + 1) % runs].items()}, ds_z[k],
                    seeds[k]) for k in range(runs)] if runs > 1 else []
    report = Report(results, daemon_presses, dataset_presses, stop_ms,
                    time.monotonic() - started, failed, left_out, null)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "consistency.md", report.markdown(command))
        atomic_write_text(out / "consistency.json",
                          json.dumps(report.to_json(), indent=2) + "\n")
    return report
