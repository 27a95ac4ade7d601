"""Do the robot's presses embed where the dataset's do? (``vt-edge sim consistency``)

Presses of given objects through the daemon on the emulated robot (``vt-edge sim serve`` +
``vt-edge run``, driven over HTTP as a user does; the press file each episode stores) against
presses of the same objects made by the dataset recorder, all encoded by the shipped model
with the daemon's own analysis (:func:`edge.daemon.compute.analyse_press`, offset 0).

Per object: the dataset's spread (median distance of its presses to their centroid), the
daemon presses' median distance to that centroid, and their ratio (1: the daemon's presses
are as close to the dataset's as the dataset's own). Overall: the median ratio, and how often
a daemon press's nearest dataset press is of its own object, against the dataset's own
leave-one-out 1-NN among the same objects.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from edge.core import recording
from edge.core.atomic import atomic_write_text
from edge.core.errors import EdgeError
from edge.core.model import model_ref
from edge.daemon.compute import analyse_press
from edge.daemon.store import EpisodeStore
from edge.sim.catalogue import get
from edge.tools.record import record_press
from edge.tools.stack import http_json, sim_stack

log = logging.getLogger(__name__)

OBJECTS = ("raw_kiri_mochi", "boiled_kiri_mochi", "raw_kabocha_squash",
           "boiled_kabocha_squash", "macaron", "resin_replica_macaron", "canele",
           "resin_replica_canele")
RECOGNIZE_TIMEOUT_S = 60.0
PRESS_FILE = "press.press.npz"
# Targets of the one-press issue: the daemon's presses sit about as close to the dataset's
# as those do to each other, and are re-identified about as often.
RATIO_TARGET = 1.5
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
class Report:
    rows: list[ObjectRow]
    daemon_presses: int  # per object
    dataset_presses: int  # per object
    reid_daemon: float  # daemon presses whose 1-NN dataset press is of their object
    loo_dataset: float  # dataset presses' leave-one-out 1-NN among the same objects
    stop_latency_ms: dict[str, float]  # the daemon's, p50/p99

    @property
    def median_ratio(self) -> float:
        return float(np.median([r.ratio for r in self.rows]))

    @property
    def passed(self) -> bool:
        return (self.median_ratio <= RATIO_TARGET
                and self.reid_daemon >= self.loo_dataset - REID_MARGIN)

    def to_json(self) -> dict:
        return {"objects": [asdict(r) | {"ratio": r.ratio} for r in self.rows],
                "daemon_presses_per_object": self.daemon_presses,
                "dataset_presses_per_object": self.dataset_presses,
                "median_ratio": self.median_ratio, "reid_daemon": self.reid_daemon,
                "loo_dataset": self.loo_dataset, "stop_latency_ms": self.stop_latency_ms,
                "targets": {"median_ratio_max": RATIO_TARGET,
                            "reid_min": f"loo_dataset - {REID_MARGIN}"},
                "passed": self.passed}

    def markdown(self, command: str) -> str:
        lines = [
            "# The robot's presses against the dataset's",
            "",
            f"Produced by `{command}`. {self.daemon_presses} presses per object through "
            "`vt-edge run` on the emulated robot (`vt-edge sim serve`), against "
            f"{self.dataset_presses} presses per object made by the dataset recorder "
            "(`vt-edge sim record`: the same press controller on the virtual clock), all "
            "encoded by the shipped model at offset 0.",
            "",
            "| object | dataset spread (median distance to its centroid) | daemon presses' "
            "median distance to that centroid | ratio |",
            "|---|---:|---:|---:|",
        ]
        lines += [f"| {r.name} | {r.dataset_spread:.3f} | {r.daemon_distance:.3f} | "
                  f"{r.ratio:.2f} |" for r in self.rows]
        verdict = "met" if self.passed else "NOT met"
        lines += [
            "",
            f"Median ratio **{self.median_ratio:.2f}** (target <= {RATIO_TARGET}). A daemon "
            f"press's nearest dataset press is of its own object in "
            f"**{self.reid_daemon:.0%}** of presses; the dataset's own leave-one-out 1-NN "
            f"among these objects: **{self.loo_dataset:.0%}** (target: at least that less "
            f"{REID_MARGIN:.2f}; chance {1 / len(self.rows):.0%}). Targets {verdict}.",
            "",
            f"The daemon's stop latency (frame over x_th -> stop packet): p50 "
            f"{self.stop_latency_ms['p50']:.2f} ms, p99 {self.stop_latency_ms['p99']:.2f} ms.",
            "",
        ]
        return "\n".join(lines)


def daemon_recordings(objects: Sequence[str], presses: int, config: str | Path,
                      progress: Callable[[str], None] = print
                      ) -> dict[str, list[recording.Recording]]:
    """``presses`` recognitions of each object through the daemon; the press each stored."""
    out: dict[str, list[recording.Recording]] = {}
    with sim_stack(config, objects[0]) as stack:
        for name in objects:
            out[name] = []
            for i in range(presses):
                stack.place(name)  # a new draw of the object, as a person puts it back
                ep = http_json("POST", f"{stack.api}/v1/recognize",
                               {"candidates": list(objects), "wait": True,
                                "timeout_s": RECOGNIZE_TIMEOUT_S},
                               timeout=RECOGNIZE_TIMEOUT_S + 5)
                if "http_status" in ep or ep.get("status") == "failed":
                    raise EdgeError(f"daemon press {i + 1} of {name} failed: "
                                    f"{ep.get('error') or ep}")
                path = EpisodeStore(stack.state / "episodes").file(ep["id"], PRESS_FILE)
                out[name].append(recording.load(path))
            progress(f"daemon: {presses} presses of {name}")
    return out


def _dataset_press(job: tuple[str, int, int, int]) -> recording.Recording:
    name, object_index, index, seed = job
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xC0, object_index, index]))
    return record_press(name, rng).recording


def dataset_recordings(objects: Sequence[str], presses: int, seed: int, workers: int = 2
                       ) -> dict[str, list[recording.Recording]]:
    jobs = [(name, oi, i, seed) for oi, name in enumerate(objects) for i in range(presses)]
    with ProcessPoolExecutor(workers) as pool:
        recs = list(pool.map(_dataset_press, jobs))
    return {name: recs[oi * presses:(oi + 1) * presses] for oi, name in enumerate(objects)}


def embed(models: str | Path, recs: Sequence[recording.Recording]) -> np.ndarray:
    ref = model_ref(models)
    return np.array([analyse_press(ref, rec).z for rec in recs])


def compare(daemon: dict[str, np.ndarray], dataset: dict[str, np.ndarray],
            stop_latency_ms: dict[str, float]) -> Report:
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
    return Report(rows, len(next(iter(daemon.values()))), len(next(iter(dataset.values()))),
                  float(np.mean(hits)), loo, stop_latency_ms)


def run_consistency(objects: Sequence[str] | None = None, daemon_presses: int = 5,
                    dataset_presses: int = 10, seed: int = 0, models: str | Path = "models",
                    config: str | Path = "configs/sim.toml", out: str | Path | None = None,
                    command: str = "vt-edge sim consistency",
                    progress: Callable[[str], None] = print) -> Report:
    objects = tuple(objects or OBJECTS)
    for name in objects:
        get(name)  # an unknown name fails here, before anything starts
    if len(objects) < 2:
        raise EdgeError("consistency needs at least two objects (re-identification)")
    progress(f"dataset recorder: {dataset_presses} presses of each of {len(objects)} objects")
    dataset = dataset_recordings(objects, dataset_presses, seed)
    progress(f"daemon on the emulated robot: {daemon_presses} presses of each object")
    daemon = daemon_recordings(objects, daemon_presses, config, progress)
    latencies = [r.extra["stop_latency_s"] * 1e3 for recs in daemon.values() for r in recs
                 if r.extra.get("stop_latency_s") is not None]
    stop_ms = {"p50": float(np.percentile(latencies, 50)),
               "p99": float(np.percentile(latencies, 99))}
    report = compare({n: embed(models, r) for n, r in daemon.items()},
                     {n: embed(models, r) for n, r in dataset.items()}, stop_ms)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "consistency.md", report.markdown(command))
        atomic_write_text(out / "consistency.json",
                          json.dumps(report.to_json(), indent=2) + "\n")
    return report
