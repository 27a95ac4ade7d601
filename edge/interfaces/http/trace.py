"""The press trace the operator page draws: the tactile norm over time around the stop.

Computed from the episode's stored press recording in the compute process (loading and
decompressing the recording and the norm over every frame are CPU work the loop must not
do). Times are seconds relative to ``t_stop``; the model's crop window and ``x_th`` are
given for marking.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from edge.core import preprocess, recording

# At most this many points are sent (a press has a few hundred frames; a long recording is
# decimated, keeping each bin's peak so a spike stays visible).
MAX_POINTS = 1000


def _decimate(t: np.ndarray, y: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    if len(y) <= n:
        return t, y
    bins = np.array_split(np.arange(len(y)), n)
    pick = np.array([b[np.argmax(y[b])] for b in bins])
    return t[pick], y[pick]


def press_trace(path: str) -> dict[str, Any]:
    """The trace of the recording at ``path`` (a ``.press.npz``)."""
    rec = recording.load(path)
    units = preprocess.recording_units(rec)
    norm = np.linalg.norm(units, axis=1).astype(np.float64)
    t = rec.recv_time - rec.t_stop
    td, nd = _decimate(t, norm, MAX_POINTS)
    spec = preprocess.DEFAULT_WINDOW
    t_cross = rec.extra.get("t_cross")
    gt = rec.gripper_time - rec.t_stop
    return {
        "t": np.round(td, 5).tolist(),
        "norm": np.round(nd, 7).tolist(),
        "x_th": rec.threshold,
        "t_stop": 0.0,
        "t_cross": None if not isinstance(t_cross, int | float) else t_cross - rec.t_stop,
        "window": [-spec.before_s, spec.after_s],
        "peak": preprocess.recording_peak(rec),  # the press's peak norm, as episodes show it
        "frames": len(norm),
        "gripper": {"t": np.round(gt, 4).tolist(),
                    "width_mm": np.round(rec.gripper_width_m * 1e3, 4).tolist()},
    }
