"""What a press measures that a channel mean does not: a small feature vector per window.

Computed from the model's input window alone (steps x channels, the step geometry of
:data:`edge.core.preprocess.DEFAULT_WINDOW`: 25 steps at 25 Hz, the stop at step 10), so the
robot's recognition input and any other sensor's sequence give it alike. The load at each
step is the window's change since its first step: the robot's window opens 0.4 s before the
stop, before the pads touch (its norm there is the pads' noise), and a sensor in raw counts
with no unloaded sample (PHAC-2's HOLD files) needs no tare for a change. ``n(t)`` is the
load's L2 norm over the channels. ``FEATURES``, in order:

- ``peak``: the largest ``n`` up to the hold's end. The robot stops at one threshold, so
  what the load reaches past it says how fast the object pushes back as the fingers coast
  to a halt (a stiff cube overshoots, a sponge does not).
- ``stiffness``: the steepest rise of ``n`` between two steps up to the hold's end, per
  second. The rise against time stands for the rise against the closing distance because
  the gripper closes at a constant speed until the stop (:mod:`train.eval.physics_eval`
  measures it on the release's reference presses: ``models/eval/physics/physics.md``).
- ``relaxation``: the fall of ``n`` over the hold (``HOLD_S`` after the stop) from its
  highest point in the hold, relative to that point: a viscoelastic object (foam, dough)
  gives way under a constant grip, an elastic one does not.
- ``spread``: the coefficient of variation of the channels' load at that highest point:
  a flat face loads every taxel alike (low), a round or small object a few (high).

Not measured here: Present Current (the robot records it, but the window the runtime
encodes does not hold it) and, on PHAC-2, stiffness at all: its HOLD files start after the
gripper stopped closing (the position moves 0.3 mm over the hold), so ``peak`` and
``stiffness`` there measure how the skin settles in the hold, not a squeeze.
"""

from __future__ import annotations

import numpy as np

from edge.core import preprocess
from edge.core.errors import PreprocessError

FEATURES = ("peak", "stiffness", "relaxation", "spread")
# The press holds the grip this long after the stop before it opens (the press setting
# dt_stopping_s of the release's datasets; their load is flat 5 steps at 25 Hz, then falls).
HOLD_S = 0.2


def steps_of(spec: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW) -> tuple[int, int]:
    """The stop's step and the hold's last step in a window of ``spec``."""
    stop = round(spec.before_s * spec.step_hz)
    return stop, stop + round(HOLD_S * spec.step_hz)


def features(x: np.ndarray, spec: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW
             ) -> np.ndarray:
    """``FEATURES`` of each window of ``x`` (N, steps, channels): (N, 4) float64.

    Refuses (:class:`PreprocessError`) windows too short to hold the stop and the hold,
    non-finite values, and a window that never changes (no press to measure)."""
    x = np.asarray(x, dtype=np.float64)
    stop, hold_end = steps_of(spec)
    if x.ndim != 3 or x.shape[1] <= hold_end or x.shape[2] < 1:
        raise PreprocessError(f"physics features need windows (presses, steps, channels) of "
                              f"more than {hold_end} steps (the stop at step {stop}, the "
                              f"{HOLD_S:g} s hold to step {hold_end}), got shape {x.shape}")
    if not np.isfinite(x).all():
        bad = np.argwhere(~np.isfinite(x))[0]
        raise PreprocessError(f"physics features: window {bad[0]} holds a non-finite value "
                              f"(step {bad[1]}, channel {bad[2]})")
    load = x[:, :hold_end + 1] - x[:, :1]
    n = np.linalg.norm(load, axis=2)
    peak = n.max(axis=1)
    flat = np.flatnonzero(peak <= 0)
    if len(flat):
        raise PreprocessError(f"physics features: window {flat[0]} never changes from its "
                              "first step: no press to measure")
    stiffness = np.diff(n, axis=1).max(axis=1) * spec.step_hz
    held = n[:, stop:]
    top = stop + held.argmax(axis=1)
    rows = np.arange(len(x))
    top_n = n[rows, top]
    # A hold whose load is still zero (no contact by the stop) neither relaxes nor spreads.
    loaded = top_n > 0
    relaxation = np.where(loaded, (top_n - n[:, -1]) / np.where(loaded, top_n, 1.0), 0.0)
    channels = np.abs(load[rows, top])
    mean = channels.mean(axis=1)
    spread = np.where(loaded, channels.std(axis=1) / np.where(loaded, mean, 1.0), 0.0)
    return np.stack([peak, stiffness, relaxation, spread], axis=1)


def standardised(x_reference: np.ndarray,
                 spec: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW):
    """A function of windows giving their ``FEATURES`` standardised with the statistics of
    ``x_reference``'s (the seen presses'); a feature that never varies is left unscaled."""
    ref = features(x_reference, spec)
    mean, std = ref.mean(axis=0), ref.std(axis=0)
    std[std <= 0] = 1.0

    def apply(x: np.ndarray) -> np.ndarray:
        return (features(x, spec) - mean) / std
    return apply
