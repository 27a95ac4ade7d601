"""Collect mode: the robot side of adapting the system at low cost.

``vt-edge collect --plan plan.toml --out DIR``: walk a collection plan (:mod:`edge.lab.plan`)
object by object: "place OBJECT, Enter", then its presses with "move it slightly, Enter"
between them, each kept press written in the recordings format (the files the simulator
writes and training reads) with its photo beside it where the plan asks, and
``DIR/dataset.json`` (:mod:`edge.lab.dataset`) rewritten after every kept press. Run again,
it continues every class up to its planned count: numbers are never reused. A failed press
(no contact, a stale stream, over the force cap) is shown with its reason and not kept; after
``MAX_FAILED_IN_A_ROW`` in a row the class is skipped. ``--label NAME --presses N`` is a plan
of one class.

Each kept press prints its peak norm (:func:`edge.core.preprocess.peak_norm`, as ``dataset
summary`` and episodes show it) and the stream's rate over its crop window; ``dataset.json``
keeps each class's rate. On the emulated robot, the prompt to place an object says which
object the emulated table holds (its control API, where the configuration's camera is).
"""

from __future__ import annotations

import asyncio
import logging
import math
import socket
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from edge import __version__
from edge.core import recording
from edge.core.atomic import atomic_write_bytes
from edge.core.config import Config
from edge.core.errors import ConfigError, EdgeError, ModelError
from edge.core.layout import PadLayout
from edge.core.model import class_x_th, model_x_th, read_manifest, x_th_mismatch
from edge.core.prompt import NO_PROMPT, Prompt, ask, read_line
from edge.core.tasks import cancel_and_wait
from edge.lab import dataset
from edge.lab.plan import Plan, PlanClass, plan_of_one
from edge.runtime.press import PressController, PressOutcome, outcome_recording
from edge.runtime.ring import FrameRing
from edge.runtime.sensor import SensorTask

log = logging.getLogger(__name__)

# Presses of one class that may fail in a row (no contact, a stale stream, over the force
# cap) before the class is skipped, and the pause after each without a prompt.
MAX_FAILED_IN_A_ROW = 5
FAILED_PRESS_PAUSE_S = 0.5
# The ring keeps the last minute of frames (a press and its margins take a few seconds).
RING_FRAMES = 8000
# How often the start looks for the stream's first frame (which brings the server's sensor
# models), for at most [sensor] connect_timeout_s.
FIRST_FRAME_POLL_S = 0.02
# Thresholds closer than this (relative) are one threshold.
X_TH_RTOL = 1e-9
# The emulated robot's camera is its control API's /camera.jpg (`vt-edge sim serve
# --write-config`); the same API says which object its table holds (GET /object).
SIM_CAMERA_PATH = "/camera.jpg"
SIM_CONTROL_TIMEOUT_S = 5.0


@dataclass
class CollectReport:
    """What a run did (filled as it goes: it says what was kept when Ctrl-C ends it)."""

    kept: list[Path] = field(default_factory=list)
    failed: int = 0
    skipped: list[str] = field(default_factory=list)
    # Per class: presses in the directory now, and planned.
    have: dict[str, int] = field(default_factory=dict)
    planned: dict[str, int] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return all(self.have.get(k, 0) >= n for k, n in self.planned.items())


def _check_existing(out: Path, plan: Plan, cfg: Config) -> dict[str, dict[int, Path]]:
    """The presses already in ``out`` per class; ConfigError naming a file pressed at
    another threshold than the plan's, or with other pads than [sensor]'s."""
    found = {}
    pads = PadLayout.of(cfg.sensor)
    for c in plan.classes:
        x_th = c.threshold(cfg.press.x_th)
        presses = dataset.existing_presses(out, c.label)
        for path in presses.values():
            rec = recording.load(path)
            kept = rec.threshold
            theirs = PadLayout.of_recording(rec.extra, rec.channels)
            if theirs != pads:
                raise ConfigError(
                    f"{path} was pressed with {theirs.text()}, [sensor] gives {pads.text()}: "
                    "one dataset holds one kind of pad; collect into another --out")
            if not math.isclose(kept, x_th, rel_tol=X_TH_RTOL):
                raise ConfigError(
                    f"{path} was pressed at x_th {kept:g}, the plan ({plan.source}) says "
                    f"{x_th:g} for {c.label!r}: set the class's x_th to {kept:g}, or collect "
                    "it into another --out")
        found[c.label] = presses
    return found


def _warn_x_th(cfg: Config, plan: Plan) -> None:
    """A warning (each once) where a class's x_th (the plan's, else [press] x_th) is far from
    the one the model's references were pressed at (that class's own where the model has
    it): its presses would embed elsewhere. Collecting goes on: a lab may be building a model
    at another threshold on purpose."""
    try:
        per_class = class_x_th(read_manifest(cfg.runtime.models_dir))
    except ModelError as exc:
        log.info("x_th not compared with a model's: %s", exc)
        return
    problems = dict.fromkeys(
        x_th_mismatch(c.threshold(cfg.press.x_th), per_class.get(c.label, model_x_th(per_class)),
                      f"{c.label}'s x_th ({plan.source})" if c.x_th is not None
                      else "[press] x_th")
        for c in plan.classes)
    for problem in problems:
        if problem is not None:
            log.warning("%s", problem)


def _origin(cfg: Config, plan: Plan, models: tuple[str, ...] | None) -> dict[str, Any]:
    emulated = cfg.mode == "sim"
    sensor = None
    if models:
        # xela_server sends each sensor's model, not its serial number.
        sensor = {"model": models[0] if len(set(models)) == 1 else ",".join(models),
                  "serials": []}
    return {"kind": "emulated" if emulated else "robot", "recorder": plan.recorder,
            "robot": plan.robot if plan.robot or emulated else socket.gethostname(),
            "sensor": sensor}


def _recorder_sentence(origin: dict[str, Any]) -> str:
    where = ("the emulated robot" if origin["kind"] == "emulated"
             else f"robot {origin['robot']}")
    sensor = origin.get("sensor") or {}
    with_sensor = f" with {sensor['model']} pads" if sensor.get("model") else ""
    return (f"vt-edge collect: {origin['recorder']} placing each object by hand on {where}"
            f"{with_sensor}, the daemon's press controller pressing")


def _merge_class(index: dict[str, Any], c: PlanClass, x_th: float, single: bool = False
                 ) -> dict[str, Any]:
    """The class's entry in ``index``, brought up to the plan; a plan of one class keeps
    the split and description an earlier plan gave it."""
    for entry in index["classes"]:
        if entry.get("label") == c.label:
            break
    else:
        entry = {"label": c.label, "split": c.split, "description": c.description}
        index["classes"].append(entry)
    if not single:
        entry.update(split=c.split, description=c.description)
    entry.update(x_th=x_th, presses=c.presses, photo=c.photo)
    entry.setdefault("failed", [])
    return entry


def _update_index(index: dict[str, Any], plan: Plan, cfg: Config) -> None:
    index.update(plan_sha256=plan.sha256, software_version=__version__)
    if not plan.single:
        index["dataset"] = plan.name
    for c in plan.classes:
        _merge_class(index, c, c.threshold(cfg.press.x_th), plan.single)


async def _first_frame(ring: FrameRing, timeout_s: float) -> None:
    """Until the stream's first frame, for at most ``timeout_s``: the dataset's origin names
    the sensor models that frame brings."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while ring.count == 0:
        if loop.time() >= deadline:
            log.warning("no tactile frame in %.1f s ([sensor] connect_timeout_s): the "
                        "dataset's origin names no sensor", timeout_s)
            return
        await asyncio.sleep(FIRST_FRAME_POLL_S)


async def _photo(camera: Any) -> bytes:
    from edge.vlm.images import prepare_image

    data = await camera.capture()
    # Kept as taken where it is a JPEG; a PNG camera's still becomes one (same size).
    image = await asyncio.to_thread(prepare_image, data, 1 << 16, 1 << 30)
    return image.data if image.source_format == "JPEG" else (
        await asyncio.to_thread(_to_jpeg, data))


def _to_jpeg(data: bytes) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.open(io.BytesIO(data)).convert("RGB").save(buf, "JPEG", quality=92)
    return buf.getvalue()


def _sim_table(cfg: Config) -> str:
    """On the emulated robot, what its table holds and how to change it, for the prompt to
    place an object ("" on a robot, or where the control API does not answer)."""
    from edge.lab.stack import http_json

    camera = cfg.camera
    if cfg.mode != "sim" or camera.kind != "http" or not camera.url.endswith(SIM_CAMERA_PATH):
        return ""
    control = camera.url.removesuffix(SIM_CAMERA_PATH)
    try:
        held = http_json("GET", f"{control}/object", timeout=SIM_CONTROL_TIMEOUT_S)["object"]
    except (OSError, ValueError, KeyError) as exc:
        log.warning("the emulated robot's control API (%s) did not say what its table "
                    "holds: %s", control, exc)
        return ""
    return (f" (the emulated table holds {held}; `vt-edge sim place NAME --url {control}` "
            "puts another there)")


def _failure(outcome: PressOutcome) -> dict[str, Any]:
    return {"result": outcome.result, "message": outcome.message,
            "peak_level": outcome.peak_level,
            "at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


async def collect_plan(cfg: Config, plan: Plan, out: str | Path,
                       prompt: Prompt | None = read_line, devices=None,
                       report: CollectReport | None = None) -> CollectReport:
    """Walk ``plan`` into ``out`` (see the module's docstring); ``prompt`` None presses
    without waiting. ``report`` (filled as it goes) says what was done when it is
    interrupted."""
    from edge.runtime.devices import close_devices, enable_torque, make_camera, open_devices

    out = Path(out)
    report = report if report is not None else CollectReport()
    index = dataset.read_index(out)
    if index is not None and not plan.single and index.get("dataset") != plan.name:
        # dataset.json has one name and one plan hash, which build and table1 report: a
        # second plan would silently take them over.
        raise ConfigError(
            f"{out / recording.DATASET_INDEX} is dataset {index.get('dataset')!r}, the plan "
            f"({plan.source}) is {plan.name!r}: collect each plan into its own --out (a test "
            "set's directory goes to vt-train build --unseen and vt-train table1 --unseen)")
    found = _check_existing(out, plan, cfg)
    _warn_x_th(cfg, plan)
    for c in plan.classes:
        report.have[c.label] = len(found[c.label])
        report.planned[c.label] = c.presses
    todo = [c for c in plan.classes if len(found[c.label]) < c.presses]
    if not todo and index is not None:
        # Nothing to press: the robot is not needed (the daemon may hold it).
        _update_index(index, plan, cfg)
        dataset.write_index(out, index)
        print(f"every class of {plan.source} has its presses in {out}", flush=True)
        return report
    camera = make_camera(cfg) if devices is None else devices.camera
    if any(c.photo for c in todo) and camera is None:
        names = ", ".join(c.label for c in todo if c.photo)
        raise ConfigError(f"the plan asks for photos ({names}) and the configuration has no "
                          "[camera]: set [camera] kind, or photo = false")
    own = devices is None
    if own:
        devices = await open_devices(cfg)
    ring = FrameRing(cfg.sensor.channels, RING_FRAMES)
    # Each press clears Bus Watchdog trips first, as the daemon's do: one host stall longer
    # than the watchdog must not fail every press after it.
    controller = PressController(cfg, devices.gripper, devices.arm, ring,
                                 recover=devices.recover)
    sensor = SensorTask(devices.tactile, ring, controller)
    task = asyncio.create_task(sensor.run(), name="sensor")
    try:
        if own:
            await enable_torque(devices)
        await _first_frame(ring, cfg.sensor.connect_timeout_s)
        origin = _origin(cfg, plan, devices.tactile.server_models)
        if index is None:
            index = dataset.new_index(plan.name, _recorder_sentence(origin), origin,
                                      plan.sha256)
        elif not dataset.same_origin(index.get("origin"), origin):
            raise ConfigError(
                f"{out / recording.DATASET_INDEX}: collected on {index.get('origin')}, this "
                f"run is on {origin}: one dataset, one robot and sensor; use another --out")
        elif index.get("plan_sha256") != plan.sha256:
            log.info("the plan changed since the last run of %s (%s)", out, plan.source)
        _update_index(index, plan, cfg)
        await asyncio.to_thread(dataset.write_index, out, index)
        for c in todo:
            await _collect_class(cfg, c, out, index, found[c.label], sensor, devices, camera,
                                 prompt, report)
    except (asyncio.CancelledError, KeyboardInterrupt):
        have = sum(min(report.have[k], n) for k, n in report.planned.items())
        print(f"\ninterrupted: kept {len(report.kept)} presses in this run, {have} of "
              f"{sum(report.planned.values())} planned are in {out}; run the same command "
              "again to go on from there", flush=True)
        raise
    finally:
        await cancel_and_wait(task)
        if own:
            await close_devices(devices, cfg.runtime.move_timeout_s)
    return report


async def _collect_class(cfg: Config, c: PlanClass, out: Path, index: dict[str, Any],
                         presses: dict[int, Path], sensor: SensorTask, devices: Any,
                         camera: Any, prompt: Prompt | None, report: CollectReport) -> None:
    ccfg = replace(cfg, press=replace(cfg.press, x_th=c.threshold(cfg.press.x_th)))
    # The sensor task's one controller, with this class's threshold from its next press on
    # (as a reload sets the daemon's).
    controller = sensor.controller
    controller.cfg = ccfg
    entry = _merge_class(index, c, ccfg.press.x_th, True)
    next_number = max(presses, default=-1) + 1
    have = len(presses)
    print(f"{c.label}: {have}/{c.presses} pressed; x_th {ccfg.press.x_th:g}", flush=True)
    if prompt is not None:
        table = await asyncio.to_thread(_sim_table, cfg)
        await ask(prompt, f"place the {c.label} ({c.description}) between the fingers"
                          f"{table}, then Enter ", NO_PROMPT)
    failures = 0
    first = True
    while have < c.presses:
        if prompt is not None and not first:
            what = "move" if failures == 0 else "check and move"
            await ask(prompt, f"{c.label} press {have + 1}/{c.presses}: {what} the "
                              f"{c.label} slightly, then Enter ", NO_PROMPT)
        first = False
        outcome = await controller.run()
        reason = None if outcome.contact else f"{outcome.result}: {outcome.message}"
        path = recording.press_path(out, c.label, next_number)
        photo = None
        if reason is None and c.photo:
            try:
                photo = await _photo(camera)
            except EdgeError as exc:
                reason = f"photo: {exc}"
                outcome = replace(outcome, result="photo", message=str(exc))
        if reason is not None:
            failures += 1
            report.failed += 1
            entry["failed"].append(_failure(outcome))
            await asyncio.to_thread(dataset.write_index, out, index)
            print(f"{c.label} press {have + 1}/{c.presses} failed ({failures} in a row): "
                  f"{reason}; not kept", flush=True)
            if failures >= MAX_FAILED_IN_A_ROW:
                print(f"{c.label}: skipped after {failures} failed presses in a row; "
                      f"{have}/{c.presses} kept; run again to go on", flush=True)
                report.skipped.append(c.label)
                return
            if prompt is None:
                # (a stale stream refuses at once: give it time to come back)
                await asyncio.sleep(FAILED_PRESS_PAUSE_S)
            continue
        failures = 0
        if photo is not None:
            # The photo first: a press is kept when its recording exists, and has its photo.
            await asyncio.to_thread(atomic_write_bytes, dataset.photo_path(path), photo)
        await asyncio.to_thread(recording.save, outcome_recording(outcome, ccfg, c.label), path)
        next_number += 1
        have += 1
        report.have[c.label] = have
        report.kept.append(path)
        entry["rate_hz"] = await asyncio.to_thread(dataset.class_rate, out, c.label)
        await asyncio.to_thread(dataset.write_index, out, index)
        press = outcome.summary()
        rate = (f"{press.window_rate_hz:.1f} frames/s" if press.window_rate_hz is not None
                else "no rate")
        print(f"{c.label} press {have}/{c.presses}: peak norm {press.peak_level:.4f}, stop "
              f"latency {(outcome.stop_latency_s or 0) * 1e3:.1f} ms, stream {rate} -> {path}"
              f"{' + photo' if photo is not None else ''}", flush=True)


async def collect(cfg: Config, label: str, presses: int, out: str | Path,
                  prompt: Prompt | None = read_line, devices=None, *,
                  description: str | None = None, x_th: float | None = None,
                  photo: bool = False) -> list[Path]:
    """Press ``label`` up to ``presses`` times in ``out/label/`` (a plan of one class);
    returns the files written."""
    plan = plan_of_one(label, presses, description=description, x_th=x_th, photo=photo,
                       name=Path(out).name or "collected")
    report = await collect_plan(cfg, plan, out, prompt, devices)
    return report.kept
