"""Build the tactile-to-text reference database, and add classes to it without retraining.

Every reference press (training and validation classes) is encoded with the *exported* ONNX
encoder, exactly as the robot will encode a press: :func:`edge.core.preprocess.recording_pairs`
in tactile units, through onnxruntime. As in the paper's TactileReference, every press gives
one reference per subsampling offset (5: the same press seen on five 25 Hz grids 8 ms apart),
so a class of 10 presses has 50 references; the robot computes offset 0 of its press and
finds the nearest of them. Stored per reference: z, z_q (= codebook[code]), code, label,
source file, offset; per label: its description (from the recorder's ``dataset.json`` or
given), which must name the object, never say how it feels (:mod:`edge.core.descriptions`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edge.core.descriptions import check_description
from edge.core.errors import ModelError, RecordingError
from edge.core.model import (
    DEFAULT_K,
    ENCODER_FILE,
    ClassInfo,
    OnnxEncoder,
    ReferenceDatabase,
    Space,
    load_model,
    nearest_code,
)
from train.data import PressSet, Splits, load_presses
from train.export import codebook_of
from train.manifest import write_manifest

log = logging.getLogger(__name__)

# Every subsampling offset of every press (the paper's 5 per press).
DB_OFFSETS = (0, 1, 2, 3, 4)


def summary(db: ReferenceDatabase) -> dict:
    return {"references": len(db), "classes": len(db.classes), "space": db.space, "k": db.k,
            "offsets": db.offsets,
            "added": [c.label for c in db.classes if c.split == "added"]}


def reference_inputs(presses: PressSet, offsets: Sequence[int] = DB_OFFSETS) -> np.ndarray:
    """The inputs of every (press, offset), press-major: (P * len(offsets), steps, channels)."""
    x = presses.x[:, list(offsets)]
    return np.ascontiguousarray(x.reshape(-1, *x.shape[2:]))


def encode_presses(encoder: OnnxEncoder, presses: PressSet,
                   offsets: Sequence[int] = DB_OFFSETS) -> tuple[np.ndarray, np.ndarray]:
    """z (P * len(offsets), D) and codes, press-major."""
    return encoder(reference_inputs(presses, offsets))


def check_descriptions(descriptions: dict[str, str], labels: Sequence[str]) -> None:
    """Every reference class has a description that names it without tactile words."""
    missing = [c for c in labels if not descriptions.get(c, "").strip()]
    if missing:
        raise ModelError(f"no description for {', '.join(missing)}: every reference class "
                         "needs one (dataset.json or the splits file)")
    for label in labels:
        check_description(descriptions[label], label)


def from_embeddings(presses: PressSet, splits: Splits, z: np.ndarray,
                    codebook: np.ndarray | None, code: np.ndarray | None = None,
                    space: Space = "z", k: int = DEFAULT_K,
                    offsets: Sequence[int] = DB_OFFSETS, *, tactile_words_ok: bool = False
                    ) -> ReferenceDatabase:
    """The database of ``presses`` (ordered as ``splits.classes``) with embeddings ``z`` of
    every (press, offset), press-major (:func:`reference_inputs`).

    ``code`` (default: nearest in ``codebook``) gives z_q = codebook[code]; without a
    codebook (the beta-VAE) a one-vector stand-in keeps the format. ``tactile_words_ok``
    is for the named ablation only (descriptions in tactile adjectives).
    """
    if tactile_words_ok:
        missing = [c for c in splits.classes if not splits.descriptions.get(c, "").strip()]
        if missing:
            raise ModelError(f"no description for {', '.join(missing)}")
    else:
        check_descriptions(splits.descriptions, splits.classes)
    per_press = len(offsets)
    if len(z) != len(presses) * per_press:
        raise ModelError(f"{len(z)} embeddings for {len(presses)} presses x {per_press} "
                         "offsets")
    split_of = {c: "train" for c in splits.train} | {c: "val" for c in splits.val}
    classes = [ClassInfo(c, splits.descriptions[c], split_of[c]) for c in splits.classes]
    index = {c: i for i, c in enumerate(splits.classes)}
    if codebook is None:
        codebook = np.zeros((1, z.shape[1]), dtype=np.float32)
    if code is None:
        code = nearest_code(z, codebook)
    return ReferenceDatabase(
        classes, z, codebook[code], code,
        np.repeat(np.asarray([index[label] for label in presses.labels], dtype=np.int32),
                  per_press),
        [Path(p).name for p in presses.paths for _ in offsets], codebook, space, k,
        offset=np.tile(np.asarray(offsets, dtype=np.int8), len(presses)))


def build_database(encoder_onnx: bytes, presses: PressSet, splits: Splits,
                   space: Space = "z", k: int = DEFAULT_K) -> ReferenceDatabase:
    """The database of ``presses`` (classes of ``splits``) encoded by ``encoder_onnx``."""
    encoder = OnnxEncoder(encoder_onnx)
    presses = presses.select(splits.classes)
    z, code = encode_presses(encoder, presses)
    return from_embeddings(presses, splits, z, codebook_of(encoder_onnx), code, space, k)


def build_into(model_dir: str | Path, recordings: str | Path, splits: Splits | None = None,
               space: Space = "z", k: int = DEFAULT_K) -> ReferenceDatabase:
    """``vt-train db build``: encode ``recordings`` with ``model_dir/encoder.onnx``, write
    the database files and re-hash the manifest."""
    model_dir = Path(model_dir)
    try:
        onnx_bytes = (model_dir / ENCODER_FILE).read_bytes()
    except OSError as exc:
        raise ModelError(f"{model_dir / ENCODER_FILE}: {exc.strerror or exc}") from None
    splits = splits or Splits.of_dataset(recordings)
    presses = load_presses(recordings, splits.classes)
    db = build_database(onnx_bytes, presses, splits, space, k)
    db.save(model_dir)
    write_manifest(model_dir, {"database": summary(db)})
    log.info("database: %d references of %d classes in %s", len(db), len(db.classes),
             model_dir)
    return db


def add_class(model_dir: str | Path, recordings: str | Path, label: str,
              description: str) -> ReferenceDatabase:
    """``vt-train db add``: encode the presses of a new (or existing) class with the shipped
    encoder and add them under ``label``; no retraining. Database files and manifest are
    rewritten atomically, the manifest last."""
    if not label.strip() or not description.strip():
        raise ModelError("db add needs a non-empty --label and --description")
    check_description(description, label)
    model = load_model(model_dir)  # verifies hashes: never extend a damaged directory
    presses = load_presses(recordings)
    found = sorted(set(presses.labels))
    if label in found:
        presses = presses.select([label])
    elif len(found) == 1:
        log.info("recordings are labelled %r; adding them as %r", found[0], label)
    else:
        raise RecordingError(f"{recordings}: recordings of {', '.join(found)}; none is labelled "
                             f"{label!r} (point --recordings at one class's presses)")
    z, code = encode_presses(model.encoder, presses)
    old = model.database
    db = old.with_class(ClassInfo(label, description.strip(), "added"), z, code,
                        [Path(p).name for p in presses.paths for _ in DB_OFFSETS],
                        np.tile(np.asarray(DB_OFFSETS, dtype=np.int8), len(presses)))
    db.save(model_dir)
    write_manifest(model_dir, {"database": summary(db)})
    log.info("added %d presses (%d references) of %s (%s); database now %d references of "
             "%d classes", len(presses), len(z), label,
             "existing class" if label in old.labels else "new class", len(db), len(db.classes))
    return db


def topk_timing(db: ReferenceDatabase, queries: int = 50, k: int = DEFAULT_K,
                seed: int = 1) -> dict[str, float]:
    """Median and 90th percentile wall time of one ``topk`` call, milliseconds."""
    import time

    rng = np.random.default_rng(seed)
    qs = rng.standard_normal((queries, db.dim)).astype(np.float32)
    db.topk(qs[0], k)
    times = []
    for q in qs:
        t0 = time.perf_counter()
        db.topk(q, k)
        times.append(time.perf_counter() - t0)
    return {"topk_ms_median": 1e3 * float(np.median(times)),
            "topk_ms_p90": 1e3 * float(np.percentile(times, 90)), "references": len(db)}
