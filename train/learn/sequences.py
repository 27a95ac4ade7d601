"""Other sensors' labelled presses: one ``.seq.npz`` file per press, a directory of them a set.

The format (numpy's ``.npz``, no pickled objects), one file per press::

    samples   (T, C) float   the sensor's channels over time, T samples of C channels, in the
                             sensor's own units (nothing is assumed of them: the normaliser
                             standardises each channel over the training presses)
    rate_hz   ()     float   samples per second (the samples are evenly spaced)
    label     ()     str     the object pressed: presses of one object share it
    stop_s    ()     float   optional: seconds from the first sample to the moment the grasp
                             stopped closing (the robot's t_stop); default 0.4 s, the model
                             window's lead, so the window starts at the first sample

Write one with :func:`save` (``np.savez(path, samples=..., rate_hz=..., label=...)`` makes the
same file). A directory of ``*.seq.npz`` files (any depth, sorted by path) is a set; press
recordings of the robot's own kind (``*.press.npz``) may sit beside them, and
:func:`train.learn.data.load_presses` reads both.

A sequence is cut as the robot's presses are (:mod:`edge.core.preprocess`, the same
functions): the window runs 0.4 s before the stop to 0.6 s after it, at the sequence's own
rate (:meth:`~edge.core.preprocess.WindowSpec.at_rate`: 100 samples in 25 steps at 100 Hz),
and the smoothed training target holds the sequence's end samples where it ends within the
filter's reach (``edge="hold"``): a sequence that ends with the grasp needs no stream beyond
the window.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edge.core import preprocess
from edge.core.atomic import atomic_write_bytes
from edge.core.errors import PreprocessError, RecordingError
from edge.core.recording import check_size

SUFFIX = ".seq.npz"
REQUIRED = ("samples", "rate_hz", "label")
OPTIONAL = ("stop_s",)
# A label names a directory and a database class: one line of ordinary length.
MAX_LABEL_CHARS = 200


@dataclass(frozen=True, eq=False)
class Sequence:
    """One labelled press of another sensor."""

    samples: np.ndarray  # (T, C) float32
    rate_hz: float
    label: str
    stop_s: float | None
    path: str

    def window(self, spec: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW
               ) -> tuple[preprocess.WindowSpec, np.ndarray, float]:
        """The window at this sequence's rate, its sample times and its stop."""
        spec = spec.at_rate(self.rate_hz)
        times = np.arange(len(self.samples)) * spec.period_s
        stop = spec.before_s if self.stop_s is None else self.stop_s
        return spec, times, stop

    def pairs(self, spec: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW
              ) -> tuple[np.ndarray, np.ndarray]:
        """Training pairs (X, X_bar) of every offset, as :func:`edge.core.preprocess.
        training_pairs` cuts a press recording, its ends held for the target."""
        spec, times, stop = self.window(spec)
        lead, last = stop - spec.before_s, stop + spec.last_sample_s
        if lead < -1e-9 or last > times[-1] + 1e-9:
            raise RecordingError(
                f"{self.path}: field stop_s: the window [{lead:.3f}, {last:.3f}] s around the "
                f"stop at {stop:.3f} s leaves the {len(times)} samples ([0, {times[-1]:.3f}] "
                f"s): the window needs {spec.before_s:g} s before the stop and "
                f"{spec.after_s:g} s after it")
        try:
            return preprocess.training_pairs(times, self.samples, stop, spec, edge="hold")
        except PreprocessError as exc:
            raise RecordingError(f"{self.path}: {exc}") from None


def find(directory: str | Path) -> list[Path]:
    """The sequence files under ``directory``, sorted by path."""
    directory = Path(directory)
    if not directory.is_dir():
        raise RecordingError(f"{directory}: not a directory of presses")
    return sorted(directory.rglob(f"*{SUFFIX}"))


def is_sequence(path: str | Path) -> bool:
    return str(path).endswith(SUFFIX)


def save(path: str | Path, samples: np.ndarray, rate_hz: float, label: str,
         stop_s: float | None = None) -> Path:
    """Write one sequence atomically (checked as :func:`load` reads it)."""
    path = Path(path)
    if not is_sequence(path):
        raise RecordingError(f"{path}: a sequence file's name ends in {SUFFIX}")
    arrays = {"samples": np.asarray(samples, dtype=np.float32),
              "rate_hz": np.float64(rate_hz), "label": np.str_(label)}
    if stop_s is not None:
        arrays["stop_s"] = np.float64(stop_s)
    check(arrays, str(path))
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())
    return path


def load(path: str | Path) -> Sequence:
    """Read and check one sequence file; any defect raises :class:`RecordingError` naming the
    file and the field."""
    name = str(path)
    try:
        loaded = np.load(io.BytesIO(Path(path).read_bytes()), allow_pickle=False)
    except OSError as exc:
        raise RecordingError(f"{name}: cannot read: {exc.strerror or exc}") from None
    except Exception as exc:  # whatever zipfile and numpy raise on bad bytes
        raise RecordingError(f"{name}: not an .npz archive ({type(exc).__name__}: {exc})"
                             ) from None
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        raise RecordingError(f"{name}: a bare .npy array, not an .npz archive of "
                             f"{', '.join(REQUIRED)}")
    with loaded as npz:
        missing = [key for key in REQUIRED if key not in npz.files]
        if missing:
            raise RecordingError(f"{name}: missing field {', '.join(missing)} (a sequence "
                                 f"holds {', '.join(REQUIRED)} and optionally stop_s)")
        try:
            arrays = {}
            for key in (*REQUIRED, *OPTIONAL):
                if key in npz.files:
                    check_size(npz, key, name)
                    arrays[key] = npz[key]
        except RecordingError:
            raise
        except Exception as exc:  # a member object arrays would need pickle for, a bad zip
            raise RecordingError(f"{name}: unreadable field ({type(exc).__name__}: {exc})"
                                 ) from None
    check(arrays, name)
    stop = arrays.get("stop_s")
    return Sequence(arrays["samples"].astype(np.float32), float(arrays["rate_hz"]),
                    str(arrays["label"]), None if stop is None else float(stop), name)


def _scalar(arrays: dict[str, np.ndarray], key: str, name: str) -> float:
    value = np.asarray(arrays[key])
    if value.shape != () or value.dtype.kind not in "iuf" or not math.isfinite(float(value)):
        raise RecordingError(f"{name}: field {key} must be one finite number, got "
                             f"{value.dtype} of shape {value.shape}")
    return float(value)


def check(arrays: dict[str, np.ndarray], name: str) -> None:
    """Refuse a sequence's fields (``arrays``, as in the file) that break the format, naming
    ``name`` and the field."""
    samples = np.asarray(arrays["samples"])
    if samples.ndim != 2 or samples.shape[0] < 2 or samples.shape[1] < 1 \
            or samples.dtype.kind not in "iuf":
        raise RecordingError(f"{name}: field samples must be numbers of shape (T, C) with "
                             f"T >= 2 samples, got {samples.dtype} of shape {samples.shape}")
    if not np.isfinite(samples).all():
        bad = np.argwhere(~np.isfinite(samples))[0]
        raise RecordingError(f"{name}: field samples holds a non-finite value (sample "
                             f"{bad[0]}, channel {bad[1]})")
    rate = _scalar(arrays, "rate_hz", name)
    if rate <= 0:
        raise RecordingError(f"{name}: field rate_hz must be above 0, got {rate:g}")
    label = np.asarray(arrays["label"])
    text = str(label) if label.dtype.kind == "U" and label.shape == () else None
    if text is None or not text.strip() or len(text) > MAX_LABEL_CHARS \
            or any(c in text for c in "/\\\n\r\0"):
        raise RecordingError(f"{name}: field label must be one line of text naming the object "
                             f"(no path separators, at most {MAX_LABEL_CHARS} characters)")
    if "stop_s" in arrays:
        stop = _scalar(arrays, "stop_s", name)
        if stop < 0:
            raise RecordingError(f"{name}: field stop_s must be at or after the first sample "
                                 f"(>= 0 s), got {stop:g}")
