"""A collected dataset directory: ``DIR/dataset.json`` and ``DIR/<label>/<label>_NNN.press.npz``
(a press's photo beside it: ``<label>_NNN.jpg``).

``dataset.json`` keeps the recorder's keys (``dataset``; ``classes`` with ``label``,
``split``, ``description``, ``x_th``) plus ``recorder`` (a sentence), ``origin`` (as in a
model's manifest), ``plan_sha256`` and, per class, ``presses`` (planned), ``photo`` and
``failed`` (the presses collect did not keep, with their reasons).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from edge import __version__
from edge.core import recording
from edge.core.atomic import atomic_write_text
from edge.core.errors import ConfigError

DATASET_INDEX = "dataset.json"
PHOTO_SUFFIX = ".jpg"


def press_path(out: Path, label: str, index: int) -> Path:
    return out / label / f"{label}_{index:03d}{recording.SUFFIX}"


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
