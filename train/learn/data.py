"""Press recordings -> training samples, exactly as docs/method.md, 'Crop and preprocessing',
says.

Every press is cropped and subsampled by :mod:`edge.core.preprocess` (never re-implemented here):
``recording_pairs`` gives the 5 subsampling offsets of the input ``X`` and of the smoothed
target ``X_bar``; another sensor's labelled sequence (:mod:`train.learn.sequences`) goes
through the same ``training_pairs`` at its own rate (4 offsets at 100 Hz). Training and
validation use all 5 offsets per press (1350 + 250 samples on the paper's reference set);
anything that mimics recognition time (the database, the evaluation) uses offset 0 only,
the one input the robot computes.

Class splits come from a file: by default the ``split`` field of the recorder's
``dataset.json`` (27 train + 5 validation classes); a JSON file ``{"train": [...], "val":
[...]}`` overrides it. A directory of sequences without a ``dataset.json`` splits by name
(:func:`sequence_splits`): the last fifth of its classes validate, at least one. Ordering is
deterministic: classes in the order of the split, presses by file path, offsets ascending.

Normalisation: per-channel mean and standard deviation of the training inputs (all samples,
all time steps). Channels a pad barely loads carry little more than sensor noise (~2 counts,
3e-5 units); dividing them by their own tiny spread would blow that noise up to the size of
real signals and make the reconstruction loss mostly about noise, so each channel's std is
floored at a fraction of the RMS of all channels' stds: ``STD_FLOOR_FRACTION`` (0.3) by
default. It is a setting (``--std-floor``, recorded in the model's manifest). At 1.0 (the
earlier default, set for the XELA pads' noise channels) a sensor whose channels all carry
signal at different scales (a BioTac's electrodes) loses the spread of most channels to one
common value; at 0 every channel keeps its own and the pads' noise channels count as much as
loaded ones. 0.3 was chosen by held-out evidence on both kinds of data (docs/method.md,
"What real data showed"): on the emulated robot's sets (3 seeds) it gave the best validation
classes' 1-NN (0.51 against 0.43 at 1.0 and 0.47 at 0) and unseen top-3 consistency (0.28
against 0.26 and 0.17); on PHAC-2's BioTac squeezes (5 seeds) the shipped configuration's
sensible first neighbour was 0.66 against 0.60 at 1.0 and 0.70 at 0 (the trivial feature:
0.65). The statistics go into the checkpoint and into the ONNX graph.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from edge.core import preprocess, recording
from edge.core.errors import RecordingError
from edge.core.recording import DATASET_INDEX
from train.learn import sequences

STD_FLOOR_FRACTION = 0.3


@dataclass(frozen=True)
class Splits:
    """Which classes train the model and which validate it (early stopping)."""

    train: tuple[str, ...]
    val: tuple[str, ...]
    descriptions: dict[str, str]

    def __post_init__(self) -> None:
        both = set(self.train) & set(self.val)
        if both:
            raise ValueError(f"classes in both train and val: {', '.join(sorted(both))}")
        if not self.train:
            raise ValueError("no training classes")

    @property
    def classes(self) -> tuple[str, ...]:
        return self.train + self.val

    @classmethod
    def from_file(cls, path: str | Path, descriptions: dict[str, str] | None = None
                  ) -> Splits:
        """A ``dataset.json`` (its ``split`` fields) or ``{"train": [...], "val": [...]}``."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise RecordingError(f"{path}: cannot read the class splits: {exc}") from None
        if isinstance(data, dict) and "classes" in data:
            train = tuple(c["label"] for c in data["classes"] if c.get("split") == "train")
            val = tuple(c["label"] for c in data["classes"] if c.get("split") == "val")
            desc = {c["label"]: c.get("description", "") for c in data["classes"]}
        elif isinstance(data, dict) and "train" in data:
            train, val = tuple(data["train"]), tuple(data.get("val", ()))
            desc = dict(data.get("descriptions", {}))
        else:
            raise RecordingError(f"{path}: expected a dataset.json or {{'train': [...], "
                                 "'val': [...]}}")
        if descriptions:
            desc.update(descriptions)
        try:
            return cls(train, val, desc)
        except ValueError as exc:
            raise RecordingError(f"{path}: {exc}") from None

    @classmethod
    def of_dataset(cls, directory: str | Path) -> Splits:
        """The splits of a recorded dataset; a directory of sequences without a
        ``dataset.json``: :func:`sequence_splits`."""
        path = Path(directory) / DATASET_INDEX
        if not path.exists() and sequences.find(directory):
            return sequence_splits(directory)
        return cls.from_file(path)


def sequence_splits(directory: str | Path) -> Splits:
    """The classes of the sequences under ``directory`` (which carry no split) in order of
    their labels: the last fifth validate (at least one), the rest train; each label is its
    own description (words on how the object feels are refused by the database: write a
    ``dataset.json`` to split or describe the classes otherwise)."""
    labels = sorted({sequences.load(p).label for p in sequences.find(directory)})
    if len(labels) < 2:
        raise RecordingError(f"{directory}: sequences of {len(labels)} class"
                             f"{'es' * (len(labels) != 1)}: training needs two or more")
    n_val = max(1, len(labels) // 5)
    return Splits(tuple(labels[:-n_val]), tuple(labels[-n_val:]),
                  {label: label.replace("_", " ") for label in labels})


@dataclass(frozen=True, eq=False)
class PressSet:
    """Preprocessed presses: every offset of the input and of the target."""

    x: np.ndarray  # (P, offsets, steps, channels) float32, tactile units
    x_bar: np.ndarray  # (P, offsets, steps, channels) float32, smoothed target
    labels: tuple[str, ...]  # (P,)
    paths: tuple[str, ...]  # (P,)

    def __len__(self) -> int:
        return len(self.labels)

    @property
    def classes(self) -> list[str]:
        """Labels in order of first appearance."""
        return list(dict.fromkeys(self.labels))

    def select(self, labels: Iterable[str]) -> PressSet:
        """The presses of ``labels``, classes in that order, presses by path within one."""
        labels = list(labels)
        idx = [i for label in labels for i in self._indices(label)]
        missing = [label for label in labels if not self._indices(label)]
        if missing:
            raise RecordingError(f"no recordings of {', '.join(missing)}")
        return PressSet(self.x[idx], self.x_bar[idx], tuple(self.labels[i] for i in idx),
                        tuple(self.paths[i] for i in idx))

    def _indices(self, label: str) -> list[int]:
        return [i for i, lab in enumerate(self.labels) if lab == label]

    @classmethod
    def concat(cls, *sets: PressSet) -> PressSet:
        return cls(np.concatenate([s.x for s in sets]), np.concatenate([s.x_bar for s in sets]),
                   tuple(lab for s in sets for lab in s.labels),
                   tuple(p for s in sets for p in s.paths))

    def inputs(self, offset: int = 0) -> np.ndarray:
        """Recognition-time inputs (P, steps, channels): one offset per press."""
        return np.ascontiguousarray(self.x[:, offset])


def load_presses(directory: str | Path, labels: Iterable[str] | None = None,
                 spec: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW) -> PressSet:
    """Every press under ``directory`` (optionally only ``labels``), sorted by path: the
    robot's press recordings (``*.press.npz``) and other sensors' labelled sequences
    (``*.seq.npz``, :mod:`train.learn.sequences`, each at its own rate)."""
    wanted = None if labels is None else set(labels)
    paths = sorted(recording.find(directory) + sequences.find(directory))
    presses = []
    for path in paths:
        press = sequences.load(path) if sequences.is_sequence(path) else recording.load(path)
        if wanted is None or press.label in wanted:
            presses.append((str(path), press))
    if not presses:
        raise RecordingError(f"{directory}: no press recordings or sequences"
                             + ("" if wanted is None else f" of {', '.join(sorted(wanted))}"))
    return press_set(presses, spec)


def press_set(presses: Sequence[tuple[str, recording.Recording | sequences.Sequence]],
              spec: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW) -> PressSet:
    """(path, press) pairs cut by :mod:`edge.core.preprocess`: a recording through
    ``recording_pairs``, a sequence at its own rate through the same ``training_pairs``;
    refused where they differ in steps or channels (one set is one sensor at one step rate)."""
    xs, ts, names = [], [], []
    for name, press in presses:
        if isinstance(press, sequences.Sequence):
            x, t = press.pairs(spec)
        else:
            x, t = preprocess.recording_pairs(press, spec)
        names.append(name)
        if xs and x.shape[1:] != xs[0].shape[1:]:
            raise RecordingError(
                f"{names[-1]} gives {x.shape[1]} steps of {x.shape[2]} channels, {names[0]} "
                f"{xs[0].shape[1]} of {xs[0].shape[2]}: one set holds one sensor's presses at "
                "one step rate")
        xs.append(x)
        ts.append(t)
    # Offsets differ with the rate (5 at 125 Hz, 4 at 100 Hz): a set keeps those all share.
    n_off = min(x.shape[0] for x in xs)
    return PressSet(np.stack([x[:n_off] for x in xs]), np.stack([t[:n_off] for t in ts]),
                    tuple(p.label for _, p in presses), tuple(names))


@dataclass(frozen=True, eq=False)
class Normaliser:
    """Per-channel ``(x - mean) / std`` with the statistics of the training inputs."""

    mean: np.ndarray  # (C,) float32
    std: np.ndarray  # (C,) float32

    @classmethod
    def fit(cls, x: np.ndarray, floor_fraction: float = STD_FLOOR_FRACTION) -> Normaliser:
        if not floor_fraction >= 0:
            raise ValueError(f"the std floor must be >= 0 (a fraction of the RMS of the "
                             f"channels' stds), got {floor_fraction}")
        flat = np.asarray(x, dtype=np.float64).reshape(-1, x.shape[-1])
        mean = flat.mean(axis=0)
        std = flat.std(axis=0)
        rms = float(np.sqrt(np.mean(std**2)))
        if not rms > 0:
            raise ValueError("training inputs have no spread: cannot normalise")
        std = np.maximum(std, floor_fraction * rms)
        std[std <= 0] = rms  # a channel that never moves (floor 0): any scale leaves it 0
        return cls(mean.astype(np.float32), std.astype(np.float32))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return ((np.asarray(x, dtype=np.float32) - self.mean) / self.std).astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        return {"mean": self.mean.tolist(), "std": self.std.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Normaliser:
        return cls(np.asarray(d["mean"], dtype=np.float32), np.asarray(d["std"], dtype=np.float32))


@dataclass(frozen=True, eq=False)
class Samples:
    """Flat training samples (normalised), with where each came from."""

    x: np.ndarray  # (N, steps, channels) float32
    x_bar: np.ndarray  # (N, steps, channels) float32
    label_index: np.ndarray  # (N,) int64 into ``classes``
    press_index: np.ndarray  # (N,) int64 into the PressSet
    offset: np.ndarray  # (N,) int64
    classes: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.x.shape[0])


def samples(presses: PressSet, norm: Normaliser, offsets: Sequence[int] | None = None
            ) -> Samples:
    """All (press, offset) samples, press-major; ``offsets`` None means every offset."""
    n_off = presses.x.shape[1]
    offsets = list(range(n_off)) if offsets is None else list(offsets)
    classes = tuple(presses.classes)
    lookup = {c: i for i, c in enumerate(classes)}
    p = len(presses)
    press = np.repeat(np.arange(p), len(offsets))
    off = np.tile(np.asarray(offsets, dtype=np.int64), p)
    return Samples(
        x=norm(presses.x[press, off]),
        x_bar=norm(presses.x_bar[press, off]),
        label_index=np.asarray([lookup[presses.labels[i]] for i in press], dtype=np.int64),
        press_index=press.astype(np.int64),
        offset=off,
        classes=classes,
    )


@dataclass(frozen=True, eq=False)
class TrainingData:
    train: Samples
    val: Samples
    norm: Normaliser
    splits: Splits
    presses: PressSet  # train classes then val classes


def training_data(directory: str | Path, splits: Splits | None = None,
                  floor_fraction: float = STD_FLOOR_FRACTION) -> TrainingData:
    """The training and validation samples of a recorded reference set."""
    splits = splits or Splits.of_dataset(directory)
    return training_data_of(load_presses(directory, splits.classes), splits, floor_fraction)


def training_data_of(presses: PressSet, splits: Splits,
                     floor_fraction: float = STD_FLOOR_FRACTION) -> TrainingData:
    """The training and validation samples of ``splits``'s classes among ``presses``
    (loaded once, e.g. for many trainings on different class draws)."""
    train_p = presses.select(splits.train)
    norm = Normaliser.fit(train_p.x, floor_fraction)
    train = samples(train_p, norm)
    if splits.val:
        val = samples(presses.select(splits.val), norm)
    else:  # no validation classes: early stopping watches the training loss
        val = train
    return TrainingData(train, val, norm, splits, presses.select(splits.classes))
