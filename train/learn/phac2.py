"""PHAC-2 BioTac squeezes (``--format phac2``) as labelled sequences (:mod:`.sequences`).

The Penn Haptic Adjective Corpus 2 distributes each phase of a squeeze as a MATLAB file,
``<object>_<id>_<trial>_<PHASE>.mat``, with per finger (``F0``, ``F1``) the BioTac's
``Electrodes`` (19 x T), ``pdc``, ``pac``, ``tdc``, ``tac`` and the gripper's ``JPos``,
``JVel``, ``JEff``, recorded at 100 Hz. The channels taken (``CHANNELS``, 40 in all):

- both fingers' 19 electrode impedances: where on the fingertip the skin is pressed in;
- both fingers' static pressure ``pdc``: how hard.

Not taken: ``pac`` (vibration, sampled at 2.2 kHz and packed 22 to a frame: not a 100 Hz
channel), ``tdc``/``tac`` (temperature: a property of the object's heat flow, not of the
squeeze the robot's pads measure) and the joint (the gripper, not the skin). Values stay in
the BioTac's raw counts, as floats: the normaliser standardises each channel. The label is
the object's name (the file name less its id, trial and phase). A HOLD file starts when the
gripper has stopped closing, so the stop is its first sample and the window the first second
of the hold (``stop_s`` left at its default: the window's lead, 0.4 s in).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from edge.core.errors import RecordingError
from train.learn import sequences

RATE_HZ = 100.0
# MATLAB variable names, in channel order.
CHANNELS = ("F0Electrodes", "F1Electrodes", "F0pdc", "F1pdc")
NAME = re.compile(r"^(?P<object>.+)_(?P<id>\d+)_(?P<trial>\d+)_(?P<phase>[A-Z_]+)\.mat$")


def find(directory: str | Path) -> list[Path]:
    """The PHAC-2 files under ``directory`` (any depth), sorted by path."""
    directory = Path(directory)
    if not directory.is_dir():
        raise RecordingError(f"{directory}: not a directory of PHAC-2 .mat files")
    found = sorted(p for p in directory.rglob("*.mat") if NAME.match(p.name))
    if not found:
        raise RecordingError(f"{directory}: no PHAC-2 files (<object>_<id>_<trial>_<PHASE>"
                             ".mat)")
    return found


def read(path: str | Path) -> sequences.Sequence:
    """One PHAC-2 file as a sequence of the 40 channels of ``CHANNELS``."""
    from scipy.io import loadmat  # scipy.io: only this converter needs it

    path = Path(path)
    match = NAME.match(path.name)
    if match is None:
        raise RecordingError(f"{path}: not a PHAC-2 file name (<object>_<id>_<trial>_<PHASE>"
                             ".mat)")
    try:
        mat = loadmat(path, variable_names=CHANNELS)
    except Exception as exc:  # scipy raises many types for a bad file
        raise RecordingError(f"{path}: not a readable MATLAB file ({type(exc).__name__}: "
                             f"{exc})") from None
    parts = []
    for key in CHANNELS:
        value = mat.get(key)
        if not isinstance(value, np.ndarray) or value.ndim != 2 or value.dtype.kind not in "iuf":
            raise RecordingError(f"{path}: field {key} missing or not a numeric matrix "
                                 "(channels x samples)")
        parts.append(value.astype(np.float32))
    lengths = {p.shape[1] for p in parts}
    if len(lengths) != 1:
        raise RecordingError(f"{path}: fields {', '.join(CHANNELS)} differ in length "
                             f"({sorted(lengths)} samples)")
    samples = np.concatenate(parts).T
    arrays = {"samples": samples, "rate_hz": np.float64(RATE_HZ),
              "label": np.str_(match["object"])}
    sequences.check(arrays, str(path))
    return sequences.Sequence(samples, RATE_HZ, match["object"], None, str(path))


def convert(directory: str | Path, out: str | Path) -> list[Path]:
    """Write every PHAC-2 file under ``directory`` as ``OUT/<object>/<file>.seq.npz``."""
    written = []
    for path in find(directory):
        seq = read(path)
        target = Path(out) / seq.label / (path.stem + sequences.SUFFIX)
        target.parent.mkdir(parents=True, exist_ok=True)
        written.append(sequences.save(target, seq.samples, seq.rate_hz, seq.label))
    return written
