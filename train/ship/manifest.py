"""``models/manifest.json``: sha256 of every runtime file, plus training config, metrics and
versions. Written last (atomically) by every command that changes a model directory, so
:func:`edge.core.model.load_model` either sees a consistent directory or refuses it by name.

``files`` (verified by the robot at load): the encoder (``encoder.onnx``, or ``encoder.npz``
for ``encoder.kind`` ``mean``), ``database.npz``,
``database.json`` and every ``prompts/*.txt`` present (another component writes those; they
are hashed as found). ``reports`` (evaluation JSON/Markdown/PNG) are hashed for the record but
not required at load.
"""

from __future__ import annotations

import json
import platform
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from edge import __version__
from edge.core.atomic import atomic_write_text
from edge.core.errors import ModelError
from edge.core.model import (
    DEFAULT_ENCODER_KIND,
    MANIFEST,
    MANIFEST_SCHEMA,
    encoder_kind,
    file_entry,
    required_files,
)

PROMPTS_DIR = "prompts"


def runtime_files(directory: Path, kind: str = DEFAULT_ENCODER_KIND) -> list[str]:
    names = list(required_files(kind))
    prompts = directory / PROMPTS_DIR
    if prompts.is_dir():
        names += sorted(p.relative_to(directory).as_posix() for p in prompts.glob("*.txt"))
    return names


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    def installed(name: str) -> str:
        try:
            return version(name)
        except PackageNotFoundError:  # an edge-only install has no torch or onnx
            return "not installed"

    return {"vtzero": __version__, "torch": installed("torch"),
            "onnxruntime": installed("onnxruntime"), "onnx": installed("onnx"),
            "numpy": np.__version__, "python": platform.python_version()}


def read_raw(directory: Path) -> dict[str, Any]:
    path = directory / MANIFEST
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ModelError(f"{path}: unreadable manifest: {exc}") from None
    return data if isinstance(data, dict) else {}


def write_manifest(directory: str | Path, sections: Mapping[str, Any] | None = None,
                   reports: list[str] | None = None) -> dict[str, Any]:
    """Re-hash the runtime files, merge ``sections`` into the existing manifest, write it."""
    directory = Path(directory)
    manifest = read_raw(directory)
    kind = encoder_kind({**manifest, **(sections or {})}, str(directory / MANIFEST))
    missing = [name for name in required_files(kind) if not (directory / name).exists()]
    if missing:
        raise ModelError(f"{directory}: cannot write a manifest without {', '.join(missing)}")
    manifest["schema_version"] = MANIFEST_SCHEMA
    manifest["files"] = {name: file_entry(directory / name)
                         for name in runtime_files(directory, kind)}
    if reports is not None:
        manifest["reports"] = {name: file_entry(directory / name) for name in sorted(reports)}
    if "versions" not in manifest:
        manifest["versions"] = versions()
    for key, value in (sections or {}).items():
        manifest[key] = value
    atomic_write_text(directory / MANIFEST, dumps(manifest))
    return manifest


_NUMBER_LIST = re.compile(r"\[\s*(-?[0-9][^\[\]{}\"]*?)\s*\]")


def dumps(data: Any) -> str:
    """Indented, key-sorted JSON with lists of numbers kept on one line."""
    text = json.dumps(data, indent=2, sort_keys=True)
    return _NUMBER_LIST.sub(lambda m: "[" + ", ".join(
        v.strip() for v in m.group(1).split(",")) + "]", text) + "\n"
