"""Record presses and whole datasets the way the robot makes them: the daemon's own press
controller (:class:`edge.runtime.press.PressController`, every state and timeout), the real
gripper and arm drivers and the sensor task, on the emulated robot run on a virtual clock
(:mod:`edge.sim.virtual`). What the model is trained and evaluated on is what ``vt-edge run``
presses; only the transport timing is modelled instead of lived.

Each press draws from its own seed ``SeedSequence([seed, class index, press index])`` on a
robot of its own with the pads of the emulated robot of that seed (``[sim] seed``), so a
dataset is byte-identical whatever the number of worker processes or the order they finish in.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from edge import __version__
from edge.core import preprocess, recording
from edge.core.atomic import atomic_write_text
from edge.core.config import Config, load_config
from edge.core.errors import EdgeError
from edge.core.layout import PadLayout
from edge.core.recording import DATASET_INDEX, press_path
from edge.lab.dataset import class_rate
from edge.runtime.press import PressController, PressOutcome, outcome_recording
from edge.runtime.ring import FrameRing
from edge.runtime.sensor import SensorTask
from edge.sim.catalogue import DATASETS, ObjectClass, get
from edge.sim.skin import DRIFT_TAU_S, SkinDraw
from edge.sim.virtual import Transport, VirtualClockLoop, VirtualRobot
from edge.sim.world import robot_pads

log = logging.getLogger(__name__)

# The configuration `vt-edge run` uses on the emulated robot: the recorder presses with it.
SIM_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "sim.toml"
# The stream runs this long before the press starts, as on a robot that is already up.
STREAM_WARMUP_S = 0.3
# A press that does not give a recording (no contact, aborted) is pressed again, up to this
# many times, as a person collecting would.
PRESS_TRIES = 3
# Frames kept: a press with its arm moves takes ~12 s.
RING_FRAMES = 4000
# The daemon's stop as `make bench` measures it (edge.sim.virtual.STOP_LATENCY_P50_S, _P99_S).
DEFAULT_TRANSPORT = Transport()
# Where each press's virtual clock starts, and how far apart presses lie on it.
CLOCK_START_S = 100.0
CLOCK_SPACING_S = 20.0
# How long the pads have been up at a press: drawn so that their drift rate (the start-up
# rate times exp(-age / DRIFT_TAU_S)) is uniform between levelled off and just powered, as
# over a session of the robot (whose emulated pads start drifting when `sim serve` starts).
# Every press on a fresh world at age 0 taught the encoder one robot's start-up drift ramp.
PADS_AGE_MEAN_S = DRIFT_TAU_S


@dataclass(frozen=True)
class PressRecord:
    """One press as recorded: the stored recording and what the world knows about it."""

    recording: recording.Recording
    outcome: PressOutcome
    tries: int
    # What the world knows and the robot does not: first contact, force at the frame that
    # crossed x_th, the largest force of the press.
    t_contact: float | None
    force_at_cross_n: float
    peak_force_n: float

    @property
    def overshoot_n(self) -> float:
        return self.peak_force_n - self.force_at_cross_n


def class_config(cfg: Config, cls: ObjectClass, x_th: float | None = None) -> Config:
    """``cfg`` with the press threshold for ``cls`` (fragile classes are pressed gentler);
    ``x_th`` overrides it for every class."""
    threshold = x_th if x_th is not None else cls.x_th or cfg.press.x_th
    return replace(cfg, press=replace(cfg.press, x_th=threshold))


def sim_config() -> Config:
    """The emulated robot's configuration (``configs/sim.toml``), as the daemon loads it."""
    return load_config(SIM_CONFIG)


async def _press_once(cfg: Config, name: str, rng: np.random.Generator, skin: SkinDraw,
                      transport: Transport, window: preprocess.WindowSpec, pads_age_s: float
                      ) -> tuple[PressOutcome, tuple[float | None, float, float]]:
    loop = asyncio.get_running_loop()
    async with VirtualRobot(cfg, name, rng, skin_draw=skin, transport=transport,
                            pads_age_s=pads_age_s) as robot:
        ring = FrameRing(cfg.sensor.channels, RING_FRAMES)
        controller = PressController(cfg, robot.gripper, robot.arm, ring,
                                     recover=robot.bus.recover_watchdog, window=window,
                                     clock=loop.time)
        sensor = asyncio.create_task(SensorTask(robot.tactile, ring, controller).run(),
                                     name="sensor")
        try:
            await robot.bus.set_torque(True)
            await asyncio.sleep(STREAM_WARMUP_S)
            outcome = await controller.run()
        finally:
            sensor.cancel()
            await asyncio.gather(sensor, return_exceptions=True)
        world = robot.world
        at_cross = robot.tactile.force_at.get(outcome.t_cross, 0.0)
        return outcome, (world.t_contact, at_cross, world.peak_force_n)


def record_press(name: str, rng: np.random.Generator | int = 0, *, cfg: Config | None = None,
                 skin: SkinDraw | None = None, transport: Transport = DEFAULT_TRANSPORT,
                 window: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW,
                 x_th: float | None = None, t0: float = CLOCK_START_S) -> PressRecord:
    """Press ``name`` once on the virtual robot (retried up to ``PRESS_TRIES`` times if the
    press gives no recording); raises :class:`EdgeError` if every try failed."""
    cls = get(name)
    cfg = class_config(cfg or sim_config(), cls, x_th)
    rng = np.random.default_rng(rng)
    skin = skin or robot_pads(0, PadLayout.of(cfg.sensor))
    # The drivers' and the emulated motors' start-up lines (torque on, torque off), once per
    # press, would bury the recorder's own output.
    quiet = [logging.getLogger(n) for n in ("edge.hw", "edge.sim.dxl_emulator")]
    levels = [q.level for q in quiet]
    for q, level in zip(quiet, levels, strict=True):
        q.setLevel(max(level, logging.WARNING))
    try:
        return _press_tries(cfg, cls.name, rng, skin, transport, window, t0)
    finally:
        for q, level in zip(quiet, levels, strict=True):
            q.setLevel(level)


def _press_tries(cfg: Config, name: str, rng: np.random.Generator, skin: SkinDraw,
                 transport: Transport, window: preprocess.WindowSpec, t0: float
                 ) -> PressRecord:
    failures: list[str] = []
    pads_age_s = float(rng.exponential(PADS_AGE_MEAN_S))
    for attempt in range(1, PRESS_TRIES + 1):
        with asyncio.Runner(loop_factory=functools.partial(VirtualClockLoop, t0)) as runner:
            outcome, truth = runner.run(_press_once(cfg, name, rng, skin, transport, window,
                                                    pads_age_s))
        if outcome.contact and outcome.window is not None:
            rec = outcome_recording(outcome, cfg, name)
            rec.extra.update(peak_force_n=truth[2], tries=attempt)
            return PressRecord(rec, outcome, attempt, *truth)
        failures.append(f"{outcome.result}: {outcome.message}")
        t0 += CLOCK_SPACING_S
    raise EdgeError(f"{name}: {PRESS_TRIES} presses gave no recording ({'; '.join(failures)})")


def _record_one(job: tuple[str, int, int, int, str, Config, float | None, Transport]
                ) -> tuple[str, int, int]:
    label, class_index, index, seed, out, cfg, x_th, transport = job
    rng = np.random.default_rng(np.random.SeedSequence([seed, class_index, index]))
    t0 = CLOCK_START_S + CLOCK_SPACING_S * PRESS_TRIES * (class_index * 1000 + index)
    pressed = record_press(label, rng, cfg=cfg, skin=robot_pads(seed, PadLayout.of(cfg.sensor)),
                           transport=transport,
                           x_th=x_th, t0=t0)
    recording.save(pressed.recording, press_path(Path(out), label, index))
    return label, index, pressed.tries


def record_dataset(dataset: str, presses: int, out: str | Path, seed: int = 0, *,
                   cfg: Config | None = None, x_th: float | None = None,
                   transport: Transport = DEFAULT_TRANSPORT,
                   workers: int | None = None,
                   progress: Callable[[int, int], None] | None = None) -> dict:
    """Record ``presses`` presses of every class of ``dataset`` into ``out``."""
    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset {dataset!r}; choose from {', '.join(DATASETS)}")
    if presses < 1:
        raise ValueError(f"presses must be >= 1, got {presses}")
    out = Path(out)
    cfg = cfg or sim_config()
    classes = DATASETS[dataset]
    jobs = [(c.name, ci, i, seed, str(out), cfg, x_th, transport)
            for ci, c in enumerate(classes) for i in range(presses)]
    workers = workers or min(len(jobs), os.cpu_count() or 1)
    started = time.perf_counter()
    retried: list[str] = []

    def done(results) -> None:
        for n, (label, index, tries) in enumerate(results, 1):
            if tries > 1:
                retried.append(f"{label}#{index}")
            if progress:
                progress(n, len(jobs))

    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            done(pool.map(_record_one, jobs, chunksize=4))
    else:
        done(map(_record_one, jobs))
    index = {
        "dataset": dataset,
        "seed": seed,
        "presses_per_class": presses,
        "software_version": __version__,
        "recorder": "the daemon's press controller on the virtual-clock emulated robot",
        "press": asdict(cfg.press),
        "transport": asdict(transport),
        "pads_age_mean_s": PADS_AGE_MEAN_S,
        "classes": [{"label": c.name, "split": c.split, "description": c.description,
                     "x_th": class_config(cfg, c, x_th).press.x_th,
                     "rate_hz": class_rate(out, c.name)} for c in classes],
        "retried": retried,
    }
    atomic_write_text(out / DATASET_INDEX, json.dumps(index, indent=2) + "\n")
    log.info("recorded %d presses of %s in %.1f s", len(jobs), dataset,
             time.perf_counter() - started)
    return index
