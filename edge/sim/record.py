"""Record whole simulated datasets in the recordings format.

Each press draws from its own seed ``SeedSequence([seed, class index, press index])``, so a
dataset is identical whatever the number of worker processes or the order they finish in.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np

from edge import __version__
from edge.core import recording
from edge.core.atomic import atomic_write_text
from edge.sim.catalogue import DATASETS
from edge.sim.press import PressParams, simulate_press

log = logging.getLogger(__name__)

DATASET_INDEX = "dataset.json"


def press_path(out: Path, label: str, index: int) -> Path:
    return out / label / f"{label}_{index:03d}{recording.SUFFIX}"


def _record_one(job: tuple[str, int, int, int, PressParams, str]) -> tuple[str, int, bool]:
    label, class_index, index, seed, params, out = job
    rng = np.random.default_rng(np.random.SeedSequence([seed, class_index, index]))
    # Each press starts at its own point of the monotonic clock, as on a robot.
    t0 = 100.0 + 10.0 * (class_index * 1000 + index)
    result = simulate_press(label, rng, params, t0=t0)
    recording.save(result.recording, press_path(Path(out), label, index))
    return label, index, result.contact


def record_dataset(dataset: str, presses: int, out: str | Path, seed: int = 0,
                   params: PressParams | None = None, workers: int | None = None,
                   progress: Callable[[int, int], None] | None = None) -> dict:
    """Record ``presses`` presses of every class of ``dataset`` into ``out``."""
    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset {dataset!r}; choose from {', '.join(DATASETS)}")
    if presses < 1:
        raise ValueError(f"presses must be >= 1, got {presses}")
    params = params or PressParams()
    out = Path(out)
    classes = DATASETS[dataset]
    jobs = [(c.name, ci, i, seed, params, str(out))
            for ci, c in enumerate(classes) for i in range(presses)]
    workers = workers or min(len(jobs), os.cpu_count() or 1)
    started = time.perf_counter()
    no_contact: list[str] = []
    done = 0
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            results = pool.map(_record_one, jobs, chunksize=4)
            for label, index, contact in results:
                done += 1
                if not contact:
                    no_contact.append(f"{label}#{index}")
                if progress:
                    progress(done, len(jobs))
    else:
        for job in jobs:
            label, index, contact = _record_one(job)
            done += 1
            if not contact:
                no_contact.append(f"{label}#{index}")
            if progress:
                progress(done, len(jobs))
    index = {
        "dataset": dataset,
        "seed": seed,
        "presses_per_class": presses,
        "software_version": __version__,
        "press_params": asdict(params),
        "classes": [{"label": c.name, "split": c.split, "description": c.description}
                    for c in classes],
        "no_contact": no_contact,
    }
    atomic_write_text(out / DATASET_INDEX, json.dumps(index, indent=2) + "\n")
    log.info("recorded %d presses of %s in %.1f s", len(jobs), dataset,
             time.perf_counter() - started)
    return index
