"""The on-disk format of one press, shared by the robot's collect mode, the simulator and
training.

A recording is a ``.npz`` archive (numpy only, no pickle) holding the raw frames at the
sensor's own rate with their monotonic receive times, the server's times and sequence
numbers, the gripper trace, the tare, and a JSON metadata block (label, ``t_stop``,
threshold, sensor model, software and schema versions). Writes are atomic; the loader checks
every array's dtype, shape and consistency and refuses anything else with a message that
names the file and the problem. Zip member CRCs catch corruption; a truncated file fails to
open as a zip.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from edge import __version__
from edge.core.atomic import atomic_write_bytes
from edge.core.errors import RecordingError

SCHEMA_VERSION = 1
SUFFIX = ".press.npz"
# A dataset directory's index (classes, splits, descriptions, thresholds, origin), beside
# DIR/<label>/<label>_NNN.press.npz: written by the recorder and by collect, read by training.
DATASET_INDEX = "dataset.json"


def press_path(out: Path, label: str, index: int) -> Path:
    """Where press ``index`` of ``label`` lies in the dataset directory ``out``."""
    return out / label / f"{label}_{index:03d}{SUFFIX}"
# A recording of a press lasts seconds; anything this large is not one.
MAX_FRAMES = 1_000_000
MAX_META_BYTES = 1_000_000
# No member of a recording is larger (1e6 frames x 96 channels x uint16 is 192 MB); a header
# that says otherwise is corrupt or hostile, and is refused before anything is allocated.
MAX_ARRAY_BYTES = 512 * 1024 * 1024

_ARRAYS: dict[str, tuple[np.dtype, int]] = {
    # name: (dtype, ndim)
    "frames": (np.dtype(np.uint16), 2),
    "recv_time": (np.dtype(np.float64), 1),
    "sensor_time": (np.dtype(np.float64), 1),
    "seq": (np.dtype(np.int64), 1),
    "tare": (np.dtype(np.float64), 1),
    "gripper_time": (np.dtype(np.float64), 1),
    "gripper_width_m": (np.dtype(np.float64), 1),
    "gripper_current_ma": (np.dtype(np.float64), 1),
}


@dataclass(frozen=True, eq=False)
class Recording:
    """One press. Times are seconds on the recording host's monotonic clock."""

    # (N, C) uint16 raw counts, channel = (pad * taxels + taxel) * 3 + axis (edge/core/layout.py)
    frames: np.ndarray
    recv_time: np.ndarray  # (N,) float64
    sensor_time: np.ndarray  # (N,) float64, the sensor server's clock
    seq: np.ndarray  # (N,) int64 server sequence numbers
    tare: np.ndarray  # (C,) float64 mean of unloaded raw samples before the press
    t_stop: float  # when the stop was sent to the gripper
    label: str
    threshold: float  # x_th in tactile units
    sensor_model: str
    gripper_time: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gripper_width_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gripper_current_ma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    source: str = "sim"
    software_version: str = __version__
    schema_version: int = SCHEMA_VERSION
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def channels(self) -> int:
        return int(self.frames.shape[1])

    def meta(self) -> dict[str, Any]:
        return {
            "schema_version": self.schema_version,
            "software_version": self.software_version,
            "label": self.label,
            "t_stop": self.t_stop,
            "threshold": self.threshold,
            "sensor_model": self.sensor_model,
            "source": self.source,
            "extra": self.extra,
        }


def to_bytes(rec: Recording) -> bytes:
    _check(rec, "<recording>")
    buf = io.BytesIO()
    arrays = {name: np.ascontiguousarray(getattr(rec, name), dtype=dt)
              for name, (dt, _) in _ARRAYS.items()}
    meta = json.dumps(rec.meta(), sort_keys=True, allow_nan=False)
    np.savez_compressed(buf, meta=np.array(meta), **arrays)
    return buf.getvalue()


def save(rec: Recording, path: str | Path) -> Path:
    """Write ``rec`` atomically; returns the path written."""
    path = Path(path)
    atomic_write_bytes(path, to_bytes(rec))
    return path


def load(path: str | Path) -> Recording:
    """Read and validate a recording; any defect raises :class:`RecordingError`."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read recording: {exc.strerror or exc}") from None
    return from_bytes(data, str(path))


def check_size(npz: np.lib.npyio.NpzFile, key: str, name: str) -> None:
    """Refuse a member whose header claims more than MAX_ARRAY_BYTES, before reading it."""
    with npz.zip.open(f"{key}.npy") as fh:
        version = np.lib.format.read_magic(fh)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, _, dtype = read_header(fh)
    size = math.prod(shape) * dtype.itemsize
    if size > MAX_ARRAY_BYTES:
        raise RecordingError(f"{name}: array {key} claims {size} bytes (shape {shape}); "
                             "no recording is that large: the file is corrupt")


def from_bytes(data: bytes, name: str = "<recording>") -> Recording:
    try:
        loaded = np.load(io.BytesIO(data), allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise RecordingError(f"{name}: not a press recording (a bare .npy array, not an "
                                 ".npz archive)")
        with loaded as npz:
            members = set(npz.files)
            missing = sorted(({"meta"} | set(_ARRAYS)) - members)
            if missing:
                raise RecordingError(
                    f"{name}: not a press recording, missing {', '.join(missing)}")
            for key in ("meta", *_ARRAYS):
                check_size(npz, key, name)
            meta_arr = npz["meta"]
            arrays = {key: npz[key] for key in _ARRAYS}
    except RecordingError:
        raise
    except Exception as exc:
        # Parsing bytes only: whatever zipfile, zlib or numpy raise on them (BadZipFile,
        # zlib.error, EOFError, ValueError, KeyError, NotImplementedError for an unknown
        # zip version, SyntaxError/TokenError from a garbled array header...) means the same.
        raise RecordingError(
            f"{name}: truncated or corrupt recording ({type(exc).__name__}: {exc}); "
            "re-record or restore it from a backup") from None
    if meta_arr.dtype.kind != "U" or meta_arr.shape != () or meta_arr.nbytes > MAX_META_BYTES:
        raise RecordingError(f"{name}: metadata block is not a JSON string")
    try:
        meta = json.loads(str(meta_arr))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise RecordingError(f"{name}: metadata is not valid JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise RecordingError(f"{name}: metadata must be a JSON object")
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION:
        raise RecordingError(
            f"{name}: schema version {version!r} is not supported (this software reads "
            f"{SCHEMA_VERSION}); convert it with the software version that wrote it")
    for key, dt in _ARRAYS.items():
        if arrays[key].dtype != dt[0]:
            raise RecordingError(
                f"{name}: array {key} has dtype {arrays[key].dtype}, expected {dt[0]}")
    try:
        rec = Recording(
            **arrays,
            t_stop=_num(meta, "t_stop", name),
            label=_str(meta, "label", name),
            threshold=_num(meta, "threshold", name),
            sensor_model=_str(meta, "sensor_model", name),
            source=_str(meta, "source", name),
            software_version=_str(meta, "software_version", name),
            schema_version=version,
            extra=meta.get("extra") if isinstance(meta.get("extra"), dict) else {},
        )
    except TypeError as exc:
        raise RecordingError(f"{name}: malformed metadata: {exc}") from None
    _check(rec, name)
    return rec


def _num(meta: dict, key: str, name: str) -> float:
    value = meta.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise RecordingError(f"{name}: metadata {key} must be a finite number, got {value!r}")
    return float(value)


def _str(meta: dict, key: str, name: str) -> str:
    value = meta.get(key)
    if not isinstance(value, str) or not value:
        raise RecordingError(f"{name}: metadata {key} must be a non-empty string, got {value!r}")
    return value


def _check(rec: Recording, name: str) -> None:
    for key, (_, ndim) in _ARRAYS.items():
        arr = getattr(rec, key)
        if not isinstance(arr, np.ndarray) or arr.ndim != ndim:
            raise RecordingError(f"{name}: {key} must be a {ndim}-D array")
    n, c = rec.frames.shape
    if not 2 <= n <= MAX_FRAMES:
        raise RecordingError(f"{name}: {n} frames; a press has 2..{MAX_FRAMES}")
    if c < 1 or c % 3:
        raise RecordingError(f"{name}: {c} channels; expected a multiple of 3 (x, y, z)")
    for key in ("recv_time", "sensor_time", "seq"):
        if getattr(rec, key).shape != (n,):
            raise RecordingError(
                f"{name}: {key} has {getattr(rec, key).shape[0]} entries for {n} frames")
    if rec.tare.shape != (c,):
        raise RecordingError(f"{name}: tare has {rec.tare.shape[0]} values for {c} channels")
    m = rec.gripper_time.shape[0]
    for key in ("gripper_width_m", "gripper_current_ma"):
        if getattr(rec, key).shape != (m,):
            raise RecordingError(f"{name}: {key} length differs from gripper_time ({m})")
    for key in ("recv_time", "sensor_time", "tare", "gripper_time", "gripper_width_m",
                "gripper_current_ma"):
        if not np.all(np.isfinite(getattr(rec, key))):
            raise RecordingError(f"{name}: {key} contains NaN or infinity")
    if np.any(np.diff(rec.recv_time) < 0):
        raise RecordingError(f"{name}: recv_time goes backwards; frames must be in order")
    if not rec.recv_time[0] <= rec.t_stop <= rec.recv_time[-1]:
        raise RecordingError(
            f"{name}: t_stop {rec.t_stop:.3f} lies outside the frames "
            f"[{rec.recv_time[0]:.3f}, {rec.recv_time[-1]:.3f}]")
    if not 0 < rec.threshold < 1:
        raise RecordingError(f"{name}: threshold {rec.threshold} must be in (0, 1)")


def frames_sha256(rec: Recording) -> str:
    """A press's identity by its content: the sha256 of its raw frames (their shape, then the
    counts as little-endian uint16), whatever its file is called."""
    digest = hashlib.sha256(np.asarray(rec.frames.shape, dtype="<i8").tobytes())
    digest.update(np.ascontiguousarray(rec.frames, dtype="<u2").tobytes())
    return digest.hexdigest()


def find(directory: str | Path) -> list[Path]:
    """Recordings under ``directory``, sorted by path for deterministic datasets."""
    directory = Path(directory)
    if not directory.is_dir():
        raise RecordingError(f"{directory}: not a directory of recordings")
    return sorted(directory.rglob(f"*{SUFFIX}"))
