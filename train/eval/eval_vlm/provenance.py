"""Where a report's numbers come from: who pressed a set (the robot and sensor, or the
emulated robot), what tactile model answered, and how to train a missing variant."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from edge.core.errors import RecordingError
from edge.core.model import Origin, manifest_origin
from edge.core.recording import DATASET_INDEX


def describe_origin(origin: Mapping[str, Any] | None) -> str:
    """Who pressed: the emulated robot, or which robot and sensor (the contract's origin)."""
    if origin is None:
        return "presses of unrecorded origin"
    if origin.get("kind") != "robot":
        return "simulated presses by the emulated robot"
    sensor = origin.get("sensor") or {}
    serials = ", ".join(sensor.get("serials") or [])
    parts = ["real presses by the robot" + (f" `{origin['robot']}`" if origin.get("robot")
                                            else "")]
    if sensor.get("model"):
        parts.append(f"with a XELA {sensor['model']}" + (f" ({serials})" if serials else ""))
    if origin.get("recorder"):
        parts.append(f"pressed by {origin['recorder']}")
    return " ".join(parts)


def reference_origin(directory: Path) -> dict[str, Any] | None:
    """Who pressed a dataset directory's presses (its ``dataset.json`` origin); None when
    it has no ``dataset.json``."""
    index = Path(directory) / DATASET_INDEX
    try:
        meta = json.loads(index.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise RecordingError(f"{index}: unreadable: {exc}") from None
    return Origin.of_dataset(meta, str(index)).to_json()


def model_facts(manifest: Mapping[str, Any]) -> dict[str, Any]:
    """What a report says about a tactile model: its decoder, its data's origin, and whether
    it was built from a lab's data (``vt-train build``) or is the simulated release."""
    decoder = manifest.get("training", {}).get("vq", {}).get("config", {}).get(
        "model", {}).get("decoder")
    origin = manifest_origin(manifest)
    built = str(manifest.get("created_by", "")).startswith("vt-train build")
    # Where a built model's presses came from: the advice names them, not a placeholder.
    data = manifest.get("training", {}).get("dataset", {}).get("directory")
    unseen = [u for u in manifest.get("evaluation", {}).get("unseen", []) if u != data]
    return {"decoder": decoder, "origin": origin.to_json(),
            "built": built or not origin.emulated, "data": data, "unseen": unseen}


def decoder_title(decoder: str | None) -> str:
    return {"teacher": "the paper's (z_q and X, teacher-forced)",
            "zeros": "zero-input (z_q alone)"}.get(
        decoder or "", "not recorded in the manifest")


def variant_advice(facts: Mapping[str, Any], model_dir: Path, variant: str) -> str:
    """How to train a missing comparison variant (``beta`` or ``zeros``) from the data the
    model came from: ``vt-train build`` for a lab's data, ``vt-train release`` only for the
    simulated set."""
    if facts["built"]:
        unseen = "".join(f" --unseen {u}" for u in facts.get("unseen") or ())
        return (f"`vt-train build --data {facts.get('data') or 'DATASET'}{unseen} --out "
                f"{model_dir} --variant {variant}` (the data the model was built from; the "
                "steps already done are kept)")
    return "`vt-train release` (the simulated reference set)"
