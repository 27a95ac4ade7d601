"""A small dataset directory in the collect format (the shared contract): dataset.json with
the classes, their split, description and x_th, the data's origin and the plan's hash;
``<label>/<label>_NNN.press.npz`` pressed by the robot's press controller on the virtual
emulated robot, and a photo beside each press of a class that asks for one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from edge.core import recording
from edge.core.recording import press_path
from edge.lab.record import record_press
from edge.sim import catalogue
from edge.sim.camera import render

ORIGIN = {"kind": "robot", "recorder": "a lab member", "robot": "lab-arm-1",
          "sensor": {"model": "XR1944", "serials": ["XR1944-0001"]}}
PLAN_SHA256 = "ab" * 32


def write_lab_dataset(out: Path, classes: dict[str, tuple[str, int, bool]], *, seed: int = 0,
                      origin: dict | None = None, name: str | None = None) -> Path:
    """``classes``: label -> (split, presses, photo). Returns ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for ci, (label, (split, presses, photo)) in enumerate(classes.items()):
        obj = catalogue.get(label)
        x_th = None
        for i in range(presses):
            rng = np.random.default_rng(np.random.SeedSequence([seed, ci, i]))
            rec = record_press(label, rng, t0=1000.0 + 100.0 * (ci * 100 + i)).recording
            x_th = rec.threshold
            path = recording.save(rec, press_path(out, label, i))
            if photo:
                path.with_name(path.name.removesuffix(recording.SUFFIX) + ".jpg").write_bytes(
                    render(label))
        entries.append({"label": label, "split": split, "description": obj.description,
                        "x_th": x_th, "presses": presses, "photo": photo})
    index = {"dataset": name or out.name, "recorder": "vt-edge collect --plan (test)",
             "origin": origin or ORIGIN, "plan_sha256": PLAN_SHA256, "classes": entries}
    (out / "dataset.json").write_text(json.dumps(index, indent=2) + "\n")
    return out
