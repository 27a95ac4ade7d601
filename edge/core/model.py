"""The tactile encoder and the tactile-to-text reference database, as the robot uses them.

numpy + onnxruntime only (never torch). A model directory holds an encoder of the kind its
manifest names (``encoder.kind``; absent: ``onnx``, every model built before the kind was a
setting):

- ``encoder.onnx``: input ``x`` (batch, 25, channels) float32 (96 for two 4 x 4 pads; the
  manifest's ``encoder.input_shape`` says how many, ``sensor_layout`` of which pads) in *tactile
  units* (``(raw - tare) / 65536``, exactly what :func:`edge.core.preprocess.model_input`
  returns). The per-channel normalisation computed on the training data is the first operation
  *inside* the graph, so the robot never applies it by hand and can never apply the wrong one.
  Outputs ``z`` (batch, D) float32 (D = 16 as shipped), the continuous embedding, and
  ``code`` (batch,) int64, the index of the nearest codebook vector.
- or, of kind ``mean``, ``encoder.npz`` (``mean`` and ``std``, (channels,) float32, the
  normaliser fitted on the training classes as for a network): the trivial feature, each
  channel's mean over the window of the normalised input (:class:`MeanEncoder`, pure numpy).
  D = channels; ``code`` is 0 throughout (no codebook).
- ``database.npz`` (numpy arrays, loaded with ``allow_pickle=False``) and ``database.json``
  (labels, their descriptions, the retrieval settings): the embeddings of every reference
  sample, grouped by class: every subsampling offset of every reference press (the paper's
  50 per class: 10 presses x 5 offsets).
- ``manifest.json``: the sha256 and size of every runtime file (the prompt templates
  included), the training configuration, metrics and versions. :func:`load_model` checks
  every listed file before using any of it and refuses a missing or altered one.

Retrieval (docs/method.md, 'Reference database and retrieval'): L2 distance from the query
embedding to every reference embedding; the first ``k`` *distinct* classes, nearest first.
Classes are stored in contiguous blocks, so the nearest reference of every class is one
``np.minimum.reduceat`` over the squared distances ``||r||^2 - 2 r.z`` (norms precomputed,
float32); no retry loop is needed to find k distinct classes however many references one class
has. The distances returned are recomputed exactly (float64) for the winners.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import logging
import math
import zipfile
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from edge.core.atomic import atomic_write_bytes, atomic_write_text
from edge.core.errors import ModelError
from edge.core.preprocess import DEFAULT_WINDOW, WindowSpec

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
ENCODER_FILE = "encoder.onnx"
DATABASE_ARRAYS = "database.npz"
DATABASE_INDEX = "database.json"
REQUIRED_FILES = (ENCODER_FILE, DATABASE_ARRAYS, DATABASE_INDEX)
MEAN_ENCODER_FILE = "encoder.npz"
# The manifest's encoder.kind -> the encoder's file; a manifest without a kind is "onnx".
ENCODER_FILES = {"onnx": ENCODER_FILE, "mean": MEAN_ENCODER_FILE}
DEFAULT_ENCODER_KIND = "onnx"
MANIFEST_SCHEMA = 1
DATABASE_SCHEMA = 1
DEFAULT_K = 3
# Rows of the leave-one-out distance matrix computed at once (N x LOO_BLOCK float64: 13 MB
# for a database of 1600 references).
LOO_BLOCK = 1024
# Familiarity compares the nearest class's distance with this-many-th nearest class's: the
# best of 2..32 on FoodReplica against half the known classes' fresh presses (docs/method.md,
# 'Familiarity').
FAMILIARITY_CLASSES = 8
# ONNX input/output names: the contract between train/ship/export.py and this module.
INPUT_NAME = "x"
OUTPUT_NAMES = ("z", "code")

Space = Literal["z", "z_q"]
# What pressed a database's references: the emulated robot, or a real one (its lab's own).
OriginKind = Literal["emulated", "robot"]


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def file_entry(path: str | Path) -> dict[str, Any]:
    """The manifest entry of one file: its sha256 and size."""
    data = Path(path).read_bytes()
    return {"sha256": sha256_bytes(data), "bytes": len(data)}


# --------------------------------------------------------------------------------------
# Encoder


class OnnxEncoder:
    """The ONNX encoder in an onnxruntime session.

    Single-threaded by default (a small robot computer runs the sensor path and the bus on
    its other cores); ``InferenceSession.run`` is thread-safe, so this may be called from a
    worker thread off the event loop.
    """

    def __init__(self, model: bytes | str | Path, *, threads: int = 1,
                 name: str = ENCODER_FILE) -> None:
        import onnxruntime as ort  # here: the daemon's loop process only needs a ModelRef

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        source = model if isinstance(model, bytes) else str(model)
        try:
            self._session = ort.InferenceSession(source, opts,
                                                 providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise ModelError(f"{name}: not a loadable ONNX encoder: {exc}") from None
        inputs = self._session.get_inputs()
        outputs = [o.name for o in self._session.get_outputs()]
        if len(inputs) != 1 or inputs[0].name != INPUT_NAME or tuple(outputs[:2]) != OUTPUT_NAMES:
            raise ModelError(
                f"{name}: expected input {INPUT_NAME!r} and outputs {OUTPUT_NAMES}, got "
                f"{[i.name for i in inputs]} -> {outputs}")
        shape = inputs[0].shape
        if len(shape) != 3 or not all(isinstance(d, int) for d in shape[1:]):
            raise ModelError(f"{name}: input shape {shape} is not (batch, steps, channels)")
        self.steps, self.channels = int(shape[1]), int(shape[2])
        z_shape = self._session.get_outputs()[0].shape
        self.dim = int(z_shape[1]) if len(z_shape) == 2 and isinstance(z_shape[1], int) else None
        self.name = name

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``x`` (B, steps, channels) in tactile units -> z (B, D) float32, code (B,) int64."""
        x = np.ascontiguousarray(x, dtype=np.float32)
        if x.ndim != 3 or x.shape[1:] != (self.steps, self.channels):
            raise ModelError(
                f"encoder input must be ({self.steps}, {self.channels}) or "
                f"(batch, {self.steps}, {self.channels}), got {x.shape}")
        if x.shape[0] == 0:
            raise ModelError("encoder input has an empty batch")
        if not np.all(np.isfinite(x)):
            raise ModelError("encoder input contains NaN or infinity")
        z, code = self._session.run(list(OUTPUT_NAMES), {INPUT_NAME: x})
        return np.asarray(z, dtype=np.float32), np.asarray(code, dtype=np.int64)


class MeanEncoder:
    """The trivial feature as an encoder: each channel's mean over the window of the input
    normalised as a network's is (``(x - mean) / std`` with the training classes'
    statistics). Pure numpy; the same call as :class:`OnnxEncoder`."""

    def __init__(self, data: bytes, steps: int, *, name: str = MEAN_ENCODER_FILE) -> None:
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                mean, std = npz["mean"], npz["std"]
        except KeyError as exc:
            raise ModelError(f"{name}: missing array {exc}") from None
        except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, OSError) as exc:
            raise ModelError(f"{name}: truncated or corrupt ({exc})") from None
        if (mean.ndim != 1 or mean.shape != std.shape or not mean.size
                or not np.all(np.isfinite(mean)) or not np.all(std > 0)):
            raise ModelError(f"{name}: mean and std must be one finite value per channel, "
                             f"std > 0; got shapes {mean.shape} and {std.shape}")
        self._mean = mean.astype(np.float32)
        self._std = std.astype(np.float32)
        self.steps, self.channels = int(steps), int(mean.shape[0])
        self.dim: int | None = self.channels
        self.name = name

    @staticmethod
    def to_bytes(mean: np.ndarray, std: np.ndarray) -> bytes:
        """The ``encoder.npz`` of a normaliser's per-channel ``mean`` and ``std``."""
        buf = io.BytesIO()
        np.savez(buf, mean=np.asarray(mean, np.float32), std=np.asarray(std, np.float32))
        return buf.getvalue()

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``x`` (B, steps, channels) in tactile units -> z (B, channels) float32, code (B,)
        int64 zeros."""
        x = np.asarray(x, dtype=np.float32)
        if x.ndim != 3 or x.shape[1:] != (self.steps, self.channels):
            raise ModelError(
                f"encoder input must be (batch, {self.steps}, {self.channels}), got {x.shape}")
        if x.shape[0] == 0:
            raise ModelError("encoder input has an empty batch")
        if not np.all(np.isfinite(x)):
            raise ModelError("encoder input contains NaN or infinity")
        z = ((x - self._mean) / self._std).mean(axis=1, dtype=np.float64)
        return z.astype(np.float32), np.zeros(x.shape[0], dtype=np.int64)


def encoder_kind(manifest: Mapping[str, Any], name: str = MANIFEST) -> str:
    """The manifest's ``encoder.kind`` (``onnx`` where it names none); refuses another."""
    kind = manifest.get("encoder", {}).get("kind", DEFAULT_ENCODER_KIND)
    if kind not in ENCODER_FILES:
        raise ModelError(f"{name}: encoder.kind must be one of {', '.join(ENCODER_FILES)}, "
                         f"got {kind!r:.40}")
    return kind


def required_files(kind: str = DEFAULT_ENCODER_KIND) -> tuple[str, ...]:
    """The files a model directory with an encoder of ``kind`` cannot do without."""
    return (ENCODER_FILES[kind], DATABASE_ARRAYS, DATABASE_INDEX)


# --------------------------------------------------------------------------------------
# Reference database


def nearest_code(z: np.ndarray, codebook: np.ndarray) -> np.ndarray:
    """Index of the L2-nearest codebook vector of each row of ``z`` (int64)."""
    z = np.asarray(z, dtype=np.float32)
    d2 = ((z[..., None, :] - codebook) ** 2).sum(-1)
    return np.argmin(d2, axis=-1).astype(np.int64)


@dataclass(frozen=True)
class ClassInfo:
    label: str
    description: str
    split: str  # train / val (from training) or added (db add)


class ReferenceDatabase:
    """Reference embeddings grouped by class, their labels and descriptions.

    Arrays (N references, D dims, K codes): ``z`` (N, D) and ``z_q`` (N, D) float32, ``code``
    (N,) int64, ``label_index`` (N,) int32 into ``classes``, ``source`` (N,) the press file
    names, ``offset`` (N,) int8 the subsampling offset each reference was cut at (one press
    gives one reference per offset; a database written before offsets were stored reads as
    offset 0 throughout), ``codebook`` (K, D) float32. ``space`` says which embedding
    retrieval compares: ``z`` (continuous, the default) or ``z_q`` (the query is quantised
    to its nearest code first). ``feature`` (N, channels) float32, or None (a database
    written before it was stored): each reference's per-channel mean over its model input
    window (tactile units, at its own offset), the space :class:`Familiarity` ranks in.
    """

    def __init__(self, classes: Sequence[ClassInfo], z: np.ndarray, z_q: np.ndarray,
                 code: np.ndarray, label_index: np.ndarray, source: Sequence[str],
                 codebook: np.ndarray, space: Space = "z", k: int = DEFAULT_K,
                 name: str = DATABASE_ARRAYS, offset: np.ndarray | None = None,
                 feature: np.ndarray | None = None) -> None:
        classes = tuple(classes)
        z = np.asarray(z, dtype=np.float32)
        n = z.shape[0] if z.ndim == 2 else -1
        if offset is None:
            offset = np.zeros(max(n, 0), dtype=np.int8)
        problems = []
        if z.ndim != 2 or n < 1:
            problems.append(f"z must be (N, D) with N >= 1, got {z.shape}")
        else:
            if np.shape(z_q) != z.shape:
                problems.append(f"z_q shape {np.shape(z_q)} differs from z {z.shape}")
            for key, arr in (("code", code), ("label_index", label_index), ("source", source),
                             ("offset", offset)):
                if np.shape(arr) != (n,):
                    problems.append(f"{key} has shape {np.shape(arr)}, expected ({n},)")
            if np.ndim(codebook) != 2 or np.shape(codebook)[1] != z.shape[1]:
                problems.append(f"codebook shape {np.shape(codebook)} does not match D")
            if feature is not None and (np.ndim(feature) != 2 or len(feature) != n
                                        or not np.all(np.isfinite(feature))):
                problems.append(f"feature must be (N={n}, channels) finite values, got "
                                f"shape {np.shape(feature)}")
        if space not in ("z", "z_q"):
            problems.append(f"space must be 'z' or 'z_q', got {space!r}")
        if not isinstance(k, int) or k < 1:
            problems.append(f"k must be a positive integer, got {k!r}")
        labels = [c.label for c in classes]
        if len(set(labels)) != len(labels):
            problems.append("duplicate class labels")
        for c in classes:
            if not c.label or not c.description.strip():
                problems.append(f"class {c.label!r} needs a label and a non-empty description")
        if problems:
            raise ModelError(f"{name}: " + "; ".join(problems))
        label_index = np.asarray(label_index, dtype=np.int32)
        if label_index.min() < 0 or label_index.max() >= len(classes):
            raise ModelError(f"{name}: label_index outside 0..{len(classes) - 1}")
        counts = np.bincount(label_index, minlength=len(classes))
        if np.any(counts == 0):
            empty = [labels[i] for i in np.flatnonzero(counts == 0)]
            raise ModelError(f"{name}: classes without references: {', '.join(empty)}")
        z_q = np.asarray(z_q, dtype=np.float32)
        codebook = np.asarray(codebook, dtype=np.float32)
        code = np.asarray(code, dtype=np.int64)
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(z_q))
                and np.all(np.isfinite(codebook))):
            raise ModelError(f"{name}: embeddings contain NaN or infinity")
        if code.min() < 0 or code.max() >= codebook.shape[0]:
            raise ModelError(f"{name}: code outside 0..{codebook.shape[0] - 1}")
        # Group references by class (stable), so each class is one contiguous block.
        order = np.argsort(label_index, kind="stable")
        self.classes = classes
        self.z = np.ascontiguousarray(z[order])
        self.z_q = np.ascontiguousarray(z_q[order])
        self.code = code[order]
        self.label_index = label_index[order]
        self.source = np.asarray(source, dtype=str)[order]
        self.offset = np.asarray(offset, dtype=np.int8)[order]
        self.feature = (None if feature is None
                        else np.ascontiguousarray(np.asarray(feature, np.float32)[order]))
        self.codebook = codebook
        self.space: Space = space
        self.k = k
        self._descriptions = {c.label: c.description for c in classes}
        self._labels = labels
        refs = self.z if space == "z" else self.z_q
        self._refs = np.ascontiguousarray(refs, dtype=np.float32)
        self._norms = np.einsum("ij,ij->i", self._refs, self._refs).astype(np.float32)
        self._starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.intp)
        self._ends = np.cumsum(counts).astype(np.intp)

    # ----- queries

    def __len__(self) -> int:
        return int(self.z.shape[0])

    @property
    def dim(self) -> int:
        return int(self.z.shape[1])

    @property
    def labels(self) -> list[str]:
        return list(self._labels)

    def description(self, label: str) -> str:
        try:
            return self._descriptions[label]
        except KeyError:
            raise ModelError(f"label {label!r} is not in the reference database") from None

    def describe(self, labels: Iterable[str]) -> str:
        return ", ".join(self.description(label) for label in labels)

    def quantise(self, z: np.ndarray) -> np.ndarray:
        """The nearest codebook vector of each row of ``z``."""
        return self.codebook[nearest_code(z, self.codebook)]

    def topk(self, z: np.ndarray, k: int | None = None) -> list[tuple[str, float]]:
        """The first ``k`` distinct classes by L2 distance to ``z``, nearest first."""
        k = self.k if k is None else k
        if not isinstance(k, int | np.integer) or k < 1:
            raise ModelError(f"k must be a positive integer, got {k!r}")
        q = np.asarray(z, dtype=np.float32).reshape(-1)
        if q.shape[0] != self.dim or not np.all(np.isfinite(q)):
            raise ModelError(f"query embedding must be {self.dim} finite values, got {q.shape}")
        if self.space == "z_q":
            q = self.quantise(q)
        # Squared distance up to the constant ||q||^2: enough to rank.
        d2 = self._norms - 2.0 * (self._refs @ q)
        per_class = np.minimum.reduceat(d2, self._starts)
        k = min(int(k), per_class.shape[0])
        if k < per_class.shape[0]:
            cand = np.argpartition(per_class, k - 1)[:k]
        else:
            cand = np.arange(per_class.shape[0])
        q64 = q.astype(np.float64)
        exact = []
        for c in cand:
            start = self._starts[c]
            best = start + int(np.argmin(d2[start:self._ends[c]]))
            diff = self._refs[best].astype(np.float64) - q64
            exact.append(math.sqrt(float(diff @ diff)))
        # Nearest first; equal distances (z_q space) in class order, deterministically.
        ranked = sorted(zip(exact, cand.tolist(), strict=True))
        return [(self._labels[c], d) for d, c in ranked]

    def nearest_other_press(self, block: int = LOO_BLOCK, points: np.ndarray | None = None
                            ) -> np.ndarray:
        """Each reference's distance to each class's nearest reference from another press,
        (N, classes) float64 in the retrieval space, or between ``points`` (N, d) given one
        row per reference (inf where a class holds only the reference's own press): the
        leave-one-out figures :class:`Familiarity` ranks a query among.

        A press is a ``source`` within a class: its offsets are one touch seen on shifted
        grids, so they are left out together. ``block`` rows at a time bound the memory
        (N x block float64); squared distances are expanded as ``|a|^2 + |b|^2 - 2 a.b`` in
        float64, exact to about 1e-12 for embeddings of unit scale."""
        n = len(self)
        press = np.unique(np.char.add(self.label_index.astype(str),
                                      np.char.add("/", self.source)), return_inverse=True)[1]
        refs = np.asarray(self._refs if points is None else points, dtype=np.float64)
        norms = np.einsum("ij,ij->i", refs, refs)
        out = np.empty((n, len(self.classes)), dtype=np.float64)
        for start in range(0, n, block):
            stop = min(start + block, n)
            d2 = norms[start:stop, None] + norms[None, :] - 2.0 * (refs[start:stop] @ refs.T)
            d2[press[start:stop, None] == press[None, :]] = np.inf
            out[start:stop] = np.minimum.reduceat(d2, self._starts, axis=1)
        return np.sqrt(np.maximum(out, 0.0))

    # ----- building and storage

    def with_class(self, info: ClassInfo, z: np.ndarray, code: np.ndarray,
                   source: Sequence[str], offset: np.ndarray | None = None,
                   feature: np.ndarray | None = None) -> ReferenceDatabase:
        """A new database with ``z`` (and their codes, sources, offsets and features) added
        under ``info.label``.

        An existing label keeps its references, gains these, and takes the new description.
        The new database has features only where this one and the added references both do.
        """
        z = np.asarray(z, dtype=np.float32)
        code = np.asarray(code, dtype=np.int64)
        if offset is None:
            offset = np.zeros(len(z), dtype=np.int8)
        classes = list(self.classes)
        if info.label in self._labels:
            idx = self._labels.index(info.label)
            classes[idx] = ClassInfo(info.label, info.description, classes[idx].split)
        else:
            idx = len(classes)
            classes.append(info)
        return ReferenceDatabase(
            classes,
            np.concatenate([self.z, z]),
            np.concatenate([self.z_q, self.codebook[code]]),
            np.concatenate([self.code, code]),
            np.concatenate([self.label_index, np.full(len(z), idx, dtype=np.int32)]),
            [*self.source.tolist(), *source],
            self.codebook, self.space, self.k,
            offset=np.concatenate([self.offset, np.asarray(offset, dtype=np.int8)]),
            feature=(None if self.feature is None or feature is None
                     else np.concatenate([self.feature, np.asarray(feature, np.float32)])))

    @property
    def offsets(self) -> list[int]:
        """The subsampling offsets the references were cut at."""
        return sorted(int(o) for o in np.unique(self.offset))

    def index_json(self, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
        counts = np.bincount(self.label_index, minlength=len(self.classes))
        presses = [len(set(self.source[self.label_index == i].tolist()))
                   for i in range(len(self.classes))]
        return {
            "schema_version": DATABASE_SCHEMA,
            "space": self.space,
            "k": self.k,
            "embedding_dim": self.dim,
            "codebook_size": int(self.codebook.shape[0]),
            "references": len(self),
            "offsets": self.offsets,
            "classes": [{"label": c.label, "description": c.description, "split": c.split,
                         "presses": p, "references": int(n)}
                        for c, n, p in zip(self.classes, counts, presses, strict=True)],
            **(extra or {}),
        }

    def save(self, directory: str | Path, extra: Mapping[str, Any] | None = None) -> None:
        """Write ``database.npz`` and ``database.json`` atomically (each file)."""
        directory = Path(directory)
        buf = io.BytesIO()
        feature = {} if self.feature is None else {"feature": self.feature}
        np.savez_compressed(
            buf, z=self.z, z_q=self.z_q, code=self.code, label_index=self.label_index,
            classes=np.array(self._labels, dtype=str), source=self.source,
            offset=self.offset, codebook=self.codebook, **feature)
        atomic_write_bytes(directory / DATABASE_ARRAYS, buf.getvalue())
        atomic_write_text(directory / DATABASE_INDEX,
                          json.dumps(self.index_json(extra), indent=2) + "\n")

    @classmethod
    def from_bytes(cls, arrays: bytes, index: bytes,
                   names: tuple[str, str] = (DATABASE_ARRAYS, DATABASE_INDEX)
                   ) -> ReferenceDatabase:
        npz_name, json_name = names
        try:
            meta = json.loads(index.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ModelError(f"{json_name}: not valid JSON: {exc}") from None
        if not isinstance(meta, dict) or meta.get("schema_version") != DATABASE_SCHEMA:
            raise ModelError(f"{json_name}: not a version {DATABASE_SCHEMA} database index")
        try:
            entries = meta["classes"]
            classes = [ClassInfo(str(c["label"]), str(c["description"]), str(c["split"]))
                       for c in entries]
            space, k = meta["space"], meta["k"]
        except (KeyError, TypeError) as exc:
            raise ModelError(f"{json_name}: malformed database index ({exc!r})") from None
        keys = ("z", "z_q", "code", "label_index", "classes", "source", "codebook")
        try:
            with np.load(io.BytesIO(arrays), allow_pickle=False) as npz:
                missing = [key for key in keys if key not in npz.files]
                if missing:
                    raise ModelError(f"{npz_name}: missing arrays {', '.join(missing)}")
                a = {key: npz[key] for key in keys}
                offset = npz["offset"] if "offset" in npz.files else None
                feature = npz["feature"] if "feature" in npz.files else None
        except ModelError:
            raise
        except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, OSError) as exc:
            raise ModelError(f"{npz_name}: truncated or corrupt ({exc})") from None
        if a["classes"].tolist() != [c.label for c in classes]:
            raise ModelError(f"{npz_name} and {json_name} list different classes")
        return cls(classes, a["z"], a["z_q"], a["code"], a["label_index"],
                   a["source"].tolist(), a["codebook"], space, k, name=npz_name,
                   offset=offset, feature=feature)

    @classmethod
    def load(cls, directory: str | Path) -> ReferenceDatabase:
        """Read a database without manifest checks (building tools); the robot uses
        :func:`load_model`."""
        directory = Path(directory)
        return cls.from_bytes(_read(directory / DATABASE_ARRAYS),
                              _read(directory / DATABASE_INDEX))


class Familiarity:
    """How familiar a query is, as a percentile among the database's own references (each
    against the rest, its whole press left out: :meth:`ReferenceDatabase.nearest_other_press`),
    computed when the database loads.

    Where the database has features (:attr:`ReferenceDatabase.feature`), in the *channel-mean
    space*: the query's per-channel mean over its model input window, standardised with the
    references' feature mean and std (a channel that never moves left unscaled); its distance
    to the nearest reference, ranked among every reference's nearest distance to another
    press. Why there and not in the embedding: the encoder's metric term draws its training
    presses (the references) tight, so fresh presses of known objects land as far from them
    as touches of new ones; a space the encoder did not learn has no such bias (docs/method.md,
    'Familiarity', has the measurement).

    Where it has none (a model directory older than the features), or with ``embedding``
    (for comparison), in the embedding: how much nearer the nearest class is than the
    :data:`FAMILIARITY_CLASSES`-th nearest (the *ratio* of their distances), ranked among the
    references' same ratio.

    :meth:`percentile` is the share of references whose figure is strictly below the
    query's, in percent: 0 = the query is nearer the references than every reference is to
    the others; 100 = farther than all (a touch like nothing the database holds).
    """

    def __init__(self, database: ReferenceDatabase, embedding: bool = False) -> None:
        self.database = database
        self.uses_feature = database.feature is not None and not embedding
        if self.uses_feature:
            feature = database.feature.astype(np.float64)
            self._mean = feature.mean(axis=0)
            std = feature.std(axis=0)
            self._std = np.where(std > 0, std, 1.0)
            self._refs = (feature - self._mean) / self._std
            figures = database.nearest_other_press(points=self._refs).min(axis=1)
        else:
            figures = _class_ratios(database.nearest_other_press())
        self.loo = np.sort(figures[np.isfinite(figures)])

    def ratio(self, z: np.ndarray) -> float | None:
        """The query's ratio (its nearest class's distance over its
        :data:`FAMILIARITY_CLASSES`-th nearest's); None where the database has one class."""
        ranked = self.database.topk(z, FAMILIARITY_CLASSES)
        if len(ranked) < 2:
            return None
        return float(_class_ratios(np.array([[d for _, d in ranked]]))[0])

    def distance(self, feature: np.ndarray) -> float:
        """The standardised query ``feature``'s (channels,) distance to its nearest
        reference."""
        q = np.asarray(feature, dtype=np.float64).reshape(-1)
        if q.shape[0] != self._refs.shape[1] or not np.all(np.isfinite(q)):
            raise ModelError(f"query feature must be {self._refs.shape[1]} finite values, "
                             f"got {q.shape}")
        diff = self._refs - (q - self._mean) / self._std
        return math.sqrt(float(np.einsum("ij,ij->i", diff, diff).min()))

    def percentile(self, z: np.ndarray, feature: np.ndarray | None = None) -> float | None:
        """The percentile of the query among the references: its ``feature`` (the model
        input's per-channel mean, required where the database has features) or its embedding
        ``z``'s ratio; None where the database has one class (the ratio) or no two presses
        to compare."""
        if self.uses_feature:
            if feature is None:
                raise ModelError("the database ranks familiarity on features: the query's "
                                 "feature (its model input's per-channel mean) is needed")
            figure: float | None = self.distance(feature)
        else:
            figure = self.ratio(z)
        if figure is None or self.loo.size == 0:
            return None
        return float(rank_percentile(self.loo, figure))


def rank_percentile(loo: np.ndarray, figures: np.ndarray | float) -> np.ndarray:
    """The percentile of each of ``figures`` among the sorted leave-one-out figures ``loo``
    (non-empty): the share strictly below it, in percent (the one ranking of every
    familiarity figure, the daemon's and the evaluation's comparisons)."""
    return 100.0 * np.searchsorted(loo, figures, side="left") / loo.size


def _class_ratios(per_class: np.ndarray) -> np.ndarray:
    """Each row's nearest class distance over its :data:`FAMILIARITY_CLASSES`-th nearest
    (the farthest where fewer classes are finite); NaN where fewer than two are. Where both
    are 0 (quantised embeddings of one code) the query is as ambiguous as can be: 1."""
    d = np.sort(per_class, axis=1)
    finite = np.isfinite(d).sum(axis=1)
    k = np.minimum(finite, FAMILIARITY_CLASSES) - 1
    far = d[np.arange(len(d)), np.maximum(k, 0)]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(far > 0, d[:, 0] / np.where(far > 0, far, 1.0), 1.0)
    return np.where(k >= 1, ratio, np.nan)


def synthetic_database(n_refs: int, n_classes: int, dim: int = 4,
                       seed: int = 0) -> ReferenceDatabase:
    """A random database of ``n_refs`` references in ``n_classes`` classes (for timing and
    testing retrieval)."""
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n_refs, dim)).astype(np.float32)
    label_index = np.sort(rng.integers(0, n_classes, n_refs)).astype(np.int32)
    label_index[:n_classes] = np.arange(n_classes)  # every class has a reference
    label_index.sort()
    classes = [ClassInfo(f"class_{i:05d}", f"description {i}", "train")
               for i in range(n_classes)]
    codebook = rng.standard_normal((32, dim)).astype(np.float32)
    return ReferenceDatabase(classes, z, z, np.zeros(n_refs, dtype=np.int64), label_index,
                             np.full(n_refs, "synthetic"), codebook)


def synthetic_inputs(manifest: Mapping[str, Any], n: int = 64, steps: int = 25,
                     seed: int = 0) -> np.ndarray:
    """``n`` encoder inputs of ``steps`` samples drawn around the model's input
    normalisation (mean + std x N(0, 1), per channel), float32 (for timing the encoder)."""
    mean = np.asarray(manifest["encoder"]["mean"], dtype=np.float32)
    std = np.asarray(manifest["encoder"]["std"], dtype=np.float32)
    rng = np.random.default_rng(seed)
    return (mean + std * rng.standard_normal((n, steps, mean.shape[-1]))).astype(np.float32)


# --------------------------------------------------------------------------------------
# The model directory


@dataclass(frozen=True)
class Origin:
    """Who pressed a model's reference database (the manifest's ``origin``).

    A manifest without one is older than the key, and every such release was pressed by the
    emulated robot: it reads as :data:`EMULATED_ORIGIN`.
    """

    kind: OriginKind
    recorder: str
    robot: str | None = None  # the robot's [robot]/host name
    sensor_model: str | None = None
    sensor_serials: tuple[str, ...] = ()

    @property
    def emulated(self) -> bool:
        return self.kind == "emulated"

    def to_json(self) -> dict[str, Any]:
        sensor = None if self.sensor_model is None else {
            "model": self.sensor_model, "serials": list(self.sensor_serials)}
        return {"kind": self.kind, "recorder": self.recorder, "robot": self.robot,
                "sensor": sensor}

    @classmethod
    def from_json(cls, raw: Any, where: str = MANIFEST) -> Origin:
        """The ``origin`` object; :class:`ModelError` naming ``where`` if malformed."""
        def bad(why: str) -> ModelError:
            return ModelError(f"{where}: origin {why}")

        if not isinstance(raw, dict):
            raise bad(f"must be an object, got {type(raw).__name__}")
        kind = raw.get("kind")
        if kind not in ("emulated", "robot"):
            raise bad(f"kind must be 'emulated' or 'robot', got {kind!r:.40}")
        recorder = raw.get("recorder", "")
        robot = raw.get("robot")
        if not isinstance(recorder, str) or not (robot is None or isinstance(robot, str)):
            raise bad("recorder must be a string and robot a string or null")
        sensor = raw.get("sensor")
        if sensor is None:
            return cls(kind, recorder, robot)
        serials = sensor.get("serials", []) if isinstance(sensor, dict) else None
        if (not isinstance(sensor, dict) or not isinstance(sensor.get("model"), str)
                or not isinstance(serials, list)
                or not all(isinstance(s, str) for s in serials)):
            raise bad('sensor must be null or {"model": str, "serials": [str, ...]}')
        return cls(kind, recorder, robot, sensor["model"], tuple(serials))

    @classmethod
    def of_dataset(cls, index: Mapping[str, Any], where: str) -> Origin:
        """A collected dataset's ``dataset.json`` ``origin``. One without it (or with null)
        was written by the simulated recorder, which says who pressed in its ``recorder``."""
        raw = index.get("origin")
        if raw is not None:
            return cls.from_json(raw, where)
        recorder = index.get("recorder")
        return cls("emulated", recorder if isinstance(recorder, str) else "the emulated robot")


EMULATED_ORIGIN = Origin("emulated", "the emulated robot (a release older than the manifest's "
                         "origin)")


def manifest_origin(manifest: Mapping[str, Any]) -> Origin:
    """The manifest's ``origin``; :data:`EMULATED_ORIGIN` when it has none."""
    raw = manifest.get("origin")
    return EMULATED_ORIGIN if raw is None else Origin.from_json(raw)


@dataclass(frozen=True, eq=False)
class Model:
    """A verified model directory: the encoder plus the reference database."""

    directory: Path
    manifest: dict[str, Any]
    encoder: OnnxEncoder | MeanEncoder
    database: ReferenceDatabase
    window: WindowSpec

    def encode(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | int]:
        """``x`` in tactile units, (25, C) or (B, 25, C) -> (z, code).

        One sequence gives z (D,) float32 and an ``int`` code; a batch gives z (B, D) and
        code (B,) int64. Blocking (about a millisecond): call it off the event loop.
        """
        x = np.asarray(x, dtype=np.float32)
        if x.ndim == 2:
            z, code = self.encoder(x[None])
            return z[0], int(code[0])
        return self.encoder(x)

    def topk(self, z: np.ndarray, k: int = DEFAULT_K) -> list[tuple[str, float]]:
        """The first ``k`` distinct reference classes nearest to ``z``: (label, distance)."""
        return self.database.topk(z, k)

    def describe(self, labels: Iterable[str]) -> str:
        """The labels' descriptions joined with ", " (the ``${topk_refs}`` sentence)."""
        return self.database.describe(labels)

    @property
    def labels(self) -> list[str]:
        return self.database.labels

    @property
    def origin(self) -> Origin:
        """Who pressed the reference database (checked when the manifest was read)."""
        return manifest_origin(self.manifest)

    @functools.cached_property
    def digest(self) -> str:
        return manifest_digest(self.manifest)


@dataclass(frozen=True)
class ModelRef:
    """Which model: its directory and digest. What the daemon's event-loop process holds;
    the model itself is loaded where it runs (:mod:`edge.runtime.compute`)."""

    directory: Path
    digest: str
    # Where the model's input is cut around the stop (the manifest's encoder.window): the
    # press records around it and the analysis crops it.
    window: WindowSpec = DEFAULT_WINDOW
    # Who pressed the reference database (the manifest's origin).
    origin: Origin = EMULATED_ORIGIN
    # The encoder's input channels and the pads they came from (the manifest's).
    layout: ModelLayout = field(default_factory=lambda: LEGACY_LAYOUT)
    # The threshold the references were pressed at (model_x_th); None where not recorded.
    x_th: float | None = None
    # The directory of references taught beside the model (edge/runtime/references.py):
    # the compute process merges them into the database it looks presses up in, and loads
    # them again whenever they change. None: the model's database alone.
    references: Path | None = None


@dataclass(frozen=True)
class ModelLayout:
    """The tactile channels a model takes: ``encoder.input_shape[2]`` of its manifest, and
    the pads and taxels per pad behind them (``sensor_layout``) where the manifest says."""

    channels: int
    pads: int | None = None
    taxels_per_pad: int | None = None

    def text(self) -> str:
        """``96 channels (2 pads x 16 taxels x 3)``, for messages."""
        if self.pads is None or self.taxels_per_pad is None:
            return f"{self.channels} channels"
        return (f"{self.channels} channels ({self.pads} pad{'s' * (self.pads != 1)} x "
                f"{self.taxels_per_pad} taxels x 3)")


# A manifest that does not name its pads predates other layouts: every such model was built
# from presses of two XR1944 pads (4 x 4 taxels).
LEGACY_LAYOUT = ModelLayout(96, 2, 16)


def manifest_layout(manifest: Mapping[str, Any], name: str = MANIFEST) -> ModelLayout:
    """What the manifest's encoder takes (:class:`ModelLayout`); refuses a malformed one."""
    shape = manifest.get("encoder", {}).get("input_shape")
    raw = manifest.get("sensor_layout")
    if shape is None and raw is None:
        return LEGACY_LAYOUT
    if not (isinstance(shape, list) and len(shape) == 3 and type(shape[2]) is int
            and shape[2] > 0):
        raise ModelError(f"{name}: encoder.input_shape must be [batch, steps, channels], "
                         f"got {shape!r}")
    channels = shape[2]
    if raw is None:
        return LEGACY_LAYOUT if channels == LEGACY_LAYOUT.channels else ModelLayout(channels)
    pads, taxels = (raw.get("pads"), raw.get("taxels_per_pad")) if isinstance(raw, dict) \
        else (None, None)
    if not (type(pads) is int and type(taxels) is int and pads * taxels * 3 == channels):
        raise ModelError(f"{name}: sensor_layout {raw!r} does not give the encoder's "
                         f"{channels} channels (pads x taxels_per_pad x 3)")
    return ModelLayout(channels, pads, taxels)


def manifest_digest(manifest: Mapping[str, Any]) -> str:
    """A model's identity: its manifest holds the sha256 of every file it loads."""
    return sha256_bytes(json.dumps(manifest, sort_keys=True).encode("utf-8"))


def model_ref(models_dir: str | Path, references: str | Path | None = None) -> ModelRef:
    """The model in ``models_dir`` by its manifest (checked; the files are verified when
    the model is loaded), with the references taught beside it in ``references``."""
    directory = Path(models_dir).resolve()  # absolute: errors and logs say where
    manifest = read_manifest(directory)
    return ModelRef(directory, manifest_digest(manifest), _window(manifest),
                    manifest_origin(manifest), manifest_layout(manifest, str(directory / MANIFEST)),
                    model_x_th(class_x_th(manifest)),
                    None if references is None else Path(references).resolve())


# The manifest's record of the stop threshold each class's references were pressed at.
CLASS_X_TH = "class_x_th"
# How far (a factor, either way) a press's x_th may be from the one the references were
# pressed at before it is said: a press stops where the norm crosses x_th, and the window
# around that stop is what the model embeds, so presses at another threshold embed
# elsewhere. A calibrated value rounded (0.00445 -> 0.004, 1.11x) passes; the fragile
# threshold for every class (0.003 against 0.004, 1.33x) or a typo (0.02) does not.
X_TH_TOLERANCE = 1.25


def class_x_th(manifest: Mapping[str, Any]) -> dict[str, float]:
    """The manifest's ``class_x_th`` (label -> x_th); empty where the model records none."""
    raw = manifest.get(CLASS_X_TH)
    if not isinstance(raw, dict):
        return {}
    return {str(k): float(v) for k, v in raw.items() if isinstance(v, int | float)}


# The manifest's record of the stream's rate (frames/s) each class's presses were made at.
CLASS_RATE_HZ = "class_rate_hz"


def class_rate_hz(manifest: Mapping[str, Any]) -> dict[str, float]:
    """The manifest's ``class_rate_hz`` (label -> frames/s); empty where the model records
    none, and without the classes whose rate was not measured."""
    raw = manifest.get(CLASS_RATE_HZ)
    if not isinstance(raw, dict):
        return {}
    return {str(k): float(v) for k, v in raw.items() if isinstance(v, int | float)}


def model_x_th(thresholds: Mapping[str, float]) -> float | None:
    """The model's threshold: the one most of its classes were pressed at (the larger on a
    tie: fragile classes are pressed lower); None without any."""
    if not thresholds:
        return None
    counts: dict[float, int] = {}
    for value in thresholds.values():
        counts[value] = counts.get(value, 0) + 1
    return max(counts, key=lambda v: (counts[v], v))


def x_th_mismatch(x_th: float, reference: float | None, what: str = "[press] x_th"
                  ) -> str | None:
    """Why ``x_th`` (named ``what``) is too far from ``reference``, the threshold the model's
    references were pressed at (:func:`model_x_th`, or a class's own in
    :func:`class_x_th`), past ``X_TH_TOLERANCE``; None when it is close enough or there is
    nothing to compare with. For the daemon's start, doctor and collect alike."""
    if reference is None or reference <= 0 or x_th <= 0:
        return None
    if max(x_th / reference, reference / x_th) <= X_TH_TOLERANCE:
        return None
    return (f"{what} = {x_th:g} is {x_th / reference:.3g} times the x_th = {reference:g} the "
            f"model's references were pressed at (more than {X_TH_TOLERANCE:g}x either way): "
            "presses at another threshold embed elsewhere. Use the model's value, or this "
            "robot's calibrated one (`vt-edge calibrate threshold`) with a model built from "
            "presses at it")


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ModelError(f"{path}: missing") from None
    except OSError as exc:
        raise ModelError(f"{path}: cannot read: {exc.strerror or exc}") from None


def _safe_name(directory: Path, name: str) -> Path:
    rel = Path(name)
    if rel.is_absolute() or ".." in rel.parts or not rel.parts:
        raise ModelError(f"{directory / MANIFEST}: file name {name!r} leaves the directory")
    return directory / rel


def read_manifest(directory: str | Path) -> dict[str, Any]:
    directory = Path(directory)
    path = directory / MANIFEST
    if not path.exists():
        raise ModelError(f"{path}: missing; a model directory needs a manifest "
                         "(regenerate it with `vt-train release`)")
    try:
        manifest = json.loads(_read(path).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("schema_version") != MANIFEST_SCHEMA:
        raise ModelError(f"{path}: not a version {MANIFEST_SCHEMA} manifest")
    files = manifest.get("files")
    if not isinstance(files, dict) or not all(
            isinstance(v, dict) and isinstance(v.get("sha256"), str) for v in files.values()):
        raise ModelError(f"{path}: 'files' must map names to {{'sha256': ...}}")
    missing = [name for name in required_files(encoder_kind(manifest, str(path)))
               if name not in files]
    if missing:
        raise ModelError(f"{path}: does not list {', '.join(missing)}")
    if manifest.get("origin") is not None:
        Origin.from_json(manifest["origin"], str(path))
    return manifest


def verified_files(directory: str | Path, manifest: dict[str, Any]) -> dict[str, bytes]:
    """Every file the manifest lists, read once and checked against its sha256."""
    directory = Path(directory)
    out: dict[str, bytes] = {}
    for name, entry in sorted(manifest["files"].items()):
        path = _safe_name(directory, name)
        data = _read(path)
        actual = sha256_bytes(data)
        if actual != entry["sha256"]:
            raise ModelError(
                f"{path}: sha256 {actual[:16]}... does not match the manifest "
                f"({entry['sha256'][:16]}...); the file was changed or damaged after release. "
                "Restore it, or regenerate the directory with `vt-train release` (after a "
                "deliberate edit: `vt-train rehash --model DIR`)")
        out[name] = data
    return out


def _window(manifest: dict[str, Any]) -> WindowSpec:
    spec = manifest.get("encoder", {}).get("window")
    if spec is None:
        return DEFAULT_WINDOW
    try:
        return WindowSpec(**spec)
    except TypeError as exc:
        raise ModelError(f"{MANIFEST}: encoder.window is malformed: {exc}") from None


# The manifest's record of another sensor's sequences a model was built from (their rate and
# channels): the robot's runtime refuses such a model, `vt-train eval` reads it.
SEQUENCES = "sequences"


def load_model(models_dir: str | Path, *, threads: int = 1, any_sensor: bool = False
               ) -> Model:
    """Verify ``models_dir/manifest.json`` and load the encoder and database.

    Every file the manifest lists (encoder, database, prompt templates) must exist and match
    its sha256; otherwise :class:`ModelError` names the file. Reads each file once, so what
    is checked is what is loaded. A model built from another sensor's sequences is refused
    unless ``any_sensor`` (an evaluation, not the robot).
    """
    directory = Path(models_dir)
    manifest = read_manifest(directory)
    data = verified_files(directory, manifest)
    window = _window(manifest)
    if manifest.get(SEQUENCES) is not None and not any_sensor:
        raise ModelError(
            f"{directory}: built from another sensor's sequences, {window.rate_hz:g} Hz x "
            f"{manifest_layout(manifest).channels} channels; the robot crops its pads' stream "
            f"at {DEFAULT_WINDOW.rate_hz:g} Hz into {LEGACY_LAYOUT.text()} by default. Build "
            "the robot's model from its own presses (vt-train build on a vt-edge collect "
            "dataset); `vt-train eval` reads this one")
    kind = encoder_kind(manifest)
    encoder_path = directory / ENCODER_FILES[kind]
    encoder: OnnxEncoder | MeanEncoder
    if kind == "mean":
        encoder = MeanEncoder(data[MEAN_ENCODER_FILE], window.n_steps, name=str(encoder_path))
    else:
        encoder = OnnxEncoder(data[ENCODER_FILE], threads=threads, name=str(encoder_path))
    database = ReferenceDatabase.from_bytes(
        data[DATABASE_ARRAYS], data[DATABASE_INDEX],
        (str(directory / DATABASE_ARRAYS), str(directory / DATABASE_INDEX)))
    layout = manifest_layout(manifest, str(directory / MANIFEST))
    if encoder.channels != layout.channels:
        raise ModelError(f"{encoder_path}: takes {encoder.channels} channels but "
                         f"the manifest says {layout.text()}")
    if encoder.steps != window.n_steps:
        raise ModelError(f"{encoder_path}: takes {encoder.steps} steps but the "
                         f"manifest window gives {window.n_steps}")
    if encoder.dim is not None and encoder.dim != database.dim:
        raise ModelError(f"{directory / DATABASE_ARRAYS}: embeddings have {database.dim} "
                         f"dims, the encoder gives {encoder.dim}")
    if database.feature is not None and database.feature.shape[1] != encoder.channels:
        raise ModelError(f"{directory / DATABASE_ARRAYS}: features have "
                         f"{database.feature.shape[1]} channels, the encoder takes "
                         f"{encoder.channels}")
    log.info("model %s: %s encoder, %d reference presses of %d classes, retrieval in %s "
             "space", directory, kind, len(database), len(database.classes), database.space)
    return Model(directory, manifest, encoder, database, window)
