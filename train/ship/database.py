"""Build the tactile-to-text reference database, and add classes to it without retraining.

Every reference press (training and validation classes) is encoded with the *exported* ONNX
encoder, exactly as the robot will encode a press: :func:`edge.core.preprocess.recording_pairs`
in tactile units, through onnxruntime. As in the paper's TactileReference, every press gives
one reference per subsampling offset (5: the same press seen on five 25 Hz grids 8 ms apart),
so a class of 10 presses has 50 references (the offsets follow the window's subsampling:
:func:`offsets_of`); the robot computes offset 0 of its press and finds the nearest of them.
Stored per reference: z, z_q (= codebook[code]), code, label, source file, offset, and its
feature (each channel's mean over that model input, in tactile units: the space the daemon's
familiarity ranks in, :class:`edge.core.model.Familiarity`); per label:
its description (from the recorder's ``dataset.json`` or given), which must name the object,
never say how it feels (:mod:`edge.core.descriptions`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from edge.core import preprocess, recording
from edge.core.descriptions import check_description
from edge.core.errors import ModelError, RecordingError
from edge.core.layout import XR1944, PadLayout
from edge.core.model import (
    CLASS_X_TH,
    DEFAULT_K,
    ENCODER_FILES,
    ClassInfo,
    MeanEncoder,
    OnnxEncoder,
    ReferenceDatabase,
    Space,
    encoder_kind,
    load_model,
    nearest_code,
)
from edge.core.progress import Progress as Bar
from train.learn.data import PressSet, Splits, load_presses
from train.ship.manifest import read_raw, write_manifest

log = logging.getLogger(__name__)

# The manifest's record of the stream's rate each class's presses were made at (the median
# of their crop windows' rates), beside its class_x_th.
CLASS_RATE_HZ = "class_rate_hz"
# The presses the database holds, by content (recording.frames_sha256 -> "label/file name"):
# a press copied under another name is still the same press.
PRESS_SHA256 = "press_sha256"
# Presses `db add --allow-test` took from a test split (Table I says so).
TEST_PRESSES_ADDED = "test_presses_added"
# Thresholds are compared to this many decimals (a setting written twice is one value).
X_TH_DIGITS = 9


def summary(db: ReferenceDatabase) -> dict:
    return {"references": len(db), "classes": len(db.classes), "space": db.space, "k": db.k,
            "offsets": db.offsets,
            "added": [c.label for c in db.classes if c.split == "added"]}


def offsets_of(presses: PressSet) -> tuple[int, ...]:
    """Every subsampling offset the presses were cut at: the database holds one reference per
    press and offset (the paper's 5 at the robot's 125 Hz; 4 for a sequence at 100 Hz)."""
    return tuple(range(presses.x.shape[1]))


def reference_inputs(presses: PressSet, offsets: Sequence[int] | None = None) -> np.ndarray:
    """The inputs of every (press, offset), press-major: (P * len(offsets), steps, channels);
    ``offsets`` None: every offset of the presses."""
    x = presses.x[:, list(offsets_of(presses) if offsets is None else offsets)]
    return np.ascontiguousarray(x.reshape(-1, *x.shape[2:]))


def reference_features(presses: PressSet, offsets: Sequence[int] | None = None
                       ) -> np.ndarray:
    """Each (press, offset)'s per-channel mean over its model input, press-major:
    (P * len(offsets), channels) float32."""
    return reference_inputs(presses, offsets).mean(axis=1, dtype=np.float64).astype(np.float32)


def encode_presses(encoder: OnnxEncoder, presses: PressSet,
                   offsets: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
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
                    offsets: Sequence[int] | None = None, *, tactile_words_ok: bool = False
                    ) -> ReferenceDatabase:
    """The database of ``presses`` (ordered as ``splits.classes``) with embeddings ``z`` of
    every (press, offset), press-major (:func:`reference_inputs`; ``offsets`` None: every
    offset of the presses).

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
    offsets = offsets_of(presses) if offsets is None else offsets
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
        offset=np.tile(np.asarray(offsets, dtype=np.int8), len(presses)),
        feature=reference_features(presses, offsets))


def build_database(encoder_file: bytes, presses: PressSet, splits: Splits,
                   space: Space = "z", k: int = DEFAULT_K, kind: str = "onnx"
                   ) -> ReferenceDatabase:
    """The database of ``presses`` (classes of ``splits``) encoded by ``encoder_file``, an
    encoder of ``kind`` (``edge.core.model.ENCODER_FILES``)."""
    presses = presses.select(splits.classes)
    if kind == "mean":  # the trivial feature: no codebook
        z, code = encode_presses(MeanEncoder(encoder_file, presses.x.shape[2]), presses)
        return from_embeddings(presses, splits, z, None, code, space, k)
    from train.ship.export import codebook_of  # onnx: not needed to add to a database

    z, code = encode_presses(OnnxEncoder(encoder_file), presses)
    return from_embeddings(presses, splits, z, codebook_of(encoder_file), code, space, k)


def build_into(model_dir: str | Path, recordings: str | Path, splits: Splits | None = None,
               space: Space = "z", k: int = DEFAULT_K) -> ReferenceDatabase:
    """``vt-train db build``: encode ``recordings`` with ``model_dir/encoder.onnx``, write
    the database files and re-hash the manifest."""
    model_dir = Path(model_dir)
    kind = encoder_kind(read_raw(model_dir))
    path = model_dir / ENCODER_FILES[kind]
    try:
        encoder_file = path.read_bytes()
    except OSError as exc:
        raise ModelError(f"{path}: {exc.strerror or exc}") from None
    splits = splits or Splits.of_dataset(recordings)
    presses = load_presses(recordings, splits.classes)
    db = build_database(encoder_file, presses, splits, space, k, kind)
    thresholds = {}
    for label, values in grouped(press_index(recordings), "x_th").items():
        problem = mixed(label, "thresholds x_th", values)
        if problem:
            raise RecordingError(f"{recordings}: {problem}")
        if label in splits.classes:
            thresholds[label] = next(iter(values))
    db.save(model_dir)
    write_manifest(model_dir, {"database": summary(db), CLASS_X_TH: thresholds,
                               PRESS_SHA256: press_digests(
                                   m for m in press_index(recordings)
                                   if m.label in splits.classes)})
    log.info("database: %d references of %d classes in %s", len(db), len(db.classes),
             model_dir)
    return db


@dataclass(frozen=True)
class PressMeta:
    """What a press's metadata says about how it was made."""

    path: Path
    label: str
    x_th: float  # rounded to X_TH_DIGITS: one setting written twice is one value
    origin: str  # recording source and sensor model
    layout: PadLayout = XR1944  # the pads behind its channels
    rate_hz: float | None = None  # the stream's rate over the crop window (frames/s)
    sha256: str = ""  # its frames' (recording.frames_sha256)

    @property
    def name(self) -> str:
        return f"{self.label}/{self.path.name}"


def press_index(directory: str | Path, progress: bool = False) -> list[PressMeta]:
    """The metadata of every press under ``directory``, sorted by path."""
    files = recording.find(directory)
    out = []
    with Bar(f"check {Path(directory).name}", len(files), "presses", enabled=progress) as bar:
        for path in files:
            rec = recording.load(path)
            out.append(PressMeta(path, rec.label, round(rec.threshold, X_TH_DIGITS),
                                 f"source {rec.source}, sensor {rec.sensor_model}",
                                 PadLayout.of_recording(rec.extra, rec.channels),
                                 preprocess.recording_rate(rec).window_hz,
                                 recording.frames_sha256(rec)))
            bar.update()
    return out


def class_rates(presses: Sequence[PressMeta]) -> dict[str, float | None]:
    """Per label: the median of its presses' rates (None: none measured), to 0.1 Hz."""
    rates: dict[str, list[float]] = {}
    for p in presses:
        rates.setdefault(p.label, [])
        if p.rate_hz is not None:
            rates[p.label].append(p.rate_hz)
    return {label: round(float(np.median(r)), 1) if r else None for label, r in rates.items()}


def rate_mix(rates: dict[str, float | None]) -> str | None:
    """One line naming the classes at each rate where ``rates`` holds rates more than
    ``preprocess.RATE_TOLERANCE`` apart; else None."""
    groups: list[tuple[float, list[str]]] = []
    for label, rate in sorted(((lab, r) for lab, r in rates.items() if r is not None),
                              key=lambda item: item[1]):
        if groups and preprocess.rate_problem(rate, groups[-1][0]) is None:
            groups[-1][1].append(label)
        else:
            groups.append((rate, [label]))
    if len(groups) < 2:
        return None
    def span(labels: list[str]) -> str:
        low, high = (f(rates[lab] for lab in labels) for f in (min, max))  # type: ignore[type-var]
        return f"{low:.1f} Hz" if low == high else f"{low:.1f}-{high:.1f} Hz"

    return (f"classes pressed at stream rates more than {preprocess.RATE_TOLERANCE * 100:.0f} "
            "% apart: " + "; ".join(f"{span(labels)}: {_names(labels, 6)}"
                                    for _, labels in groups))


def press_digests(presses: Iterable[PressMeta]) -> dict[str, str]:
    """The manifest's ``press_sha256``: each press's content digest -> label/file name."""
    return {p.sha256: p.name for p in presses}


def grouped(presses: Sequence[PressMeta], field: str) -> dict[str, dict[Any, list[str]]]:
    """Per label: each value of ``field`` among its presses, with the presses' names."""
    out: dict[str, dict[Any, list[str]]] = {}
    for p in presses:
        out.setdefault(p.label, {}).setdefault(getattr(p, field), []).append(
            p.path.name.removesuffix(recording.SUFFIX))
    return out


def mixed(label: str, what: str, values: dict[Any, list[str]]) -> str | None:
    """One line naming the values and presses where a class mixes ``what``; else None."""
    if len(values) < 2:
        return None
    return f"class {label!r} mixes {what}: " + "; ".join(
        f"{v} ({_names(names)})" for v, names in values.items())


def _names(names: Sequence[str], most: int = 4) -> str:
    return ", ".join(names[:most]) + (f" and {len(names) - most} more"
                                       if len(names) > most else "")


def _check_threshold(label: str, x_th: float, known: dict[str, float]) -> None:
    if label in known:
        if round(known[label], X_TH_DIGITS) != x_th:
            raise ModelError(f"the presses of {label!r} were made at x_th {x_th:g}; the "
                             f"database's {label!r} at {known[label]:g}: press at that "
                             "threshold, or say --force")
        return
    if known and x_th not in {round(t, X_TH_DIGITS) for t in known.values()}:
        levels = ", ".join(f"{t:g}" for t in sorted(set(known.values())))
        raise ModelError(f"the presses of {label!r} were made at x_th {x_th:g}; the "
                         f"database's classes at {levels}: press at one of those "
                         "(vt-edge collect --x-th), or say --force")


def _test_split(recordings: Path, metas: Sequence[PressMeta]) -> tuple[Path, list[PressMeta]]:
    """The ``dataset.json`` over ``recordings`` (a dataset directory or one class's folder in
    it) and those of ``metas`` whose class it splits ``test``; no index: none."""
    for directory in (recordings, recordings.parent):
        path = directory / recording.DATASET_INDEX
        try:
            index = json.loads(path.read_text())
        except FileNotFoundError:
            continue
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{path}: cannot read: {exc}") from None
        classes = index.get("classes") if isinstance(index, dict) else None
        test = {c.get("label") for c in classes or () if isinstance(c, dict)
                and c.get("split") == "test"}
        return path, [m for m in metas if m.label in test]
    return recordings / recording.DATASET_INDEX, []


def _check_new(metas: Sequence[PressMeta], known: dict[str, str]) -> None:
    """Refuse presses the database holds already, or given twice, by content (a press
    copied under another name is the same press)."""
    seen: dict[str, str] = {}
    held = []
    for m in metas:
        if m.sha256 in known:
            held.append(f"{m.path.name} is {known[m.sha256]}")
        elif m.sha256 in seen:
            held.append(f"{m.path.name} is {seen[m.sha256]} (given twice)")
        seen.setdefault(m.sha256, m.path.name)
    if held:
        raise ModelError(f"{len(held)} of these presses are in the database already (the same "
                         f"frames, whatever the file name): {_names(held, 6)}. Nothing added")


def add_class(model_dir: str | Path, recordings: str | Path, label: str,
              description: str, *, relabel: bool = False, force: bool = False,
              allow_test: bool = False) -> ReferenceDatabase:
    """``vt-train db add``: encode the presses of a new (or existing) class with the shipped
    encoder (onnxruntime only: no torch or onnx on this path) and add them under ``label``; no
    retraining. Refused: presses labelled otherwise in their metadata (unless ``relabel``),
    presses the database already holds (by content: the same frames under any file name), a
    threshold unlike the database's classes' (unless ``force``), presses whose dataset splits
    them ``test`` (unless ``allow_test``: the manifest records it, and Table I says so).
    Database files and manifest are rewritten atomically, the manifest last."""
    if not label.strip() or not description.strip():
        raise ModelError("db add needs a non-empty --label and --description")
    check_description(description, label)
    model = load_model(model_dir)  # verifies hashes: never extend a damaged directory
    metas = press_index(recordings)
    if not metas:
        raise RecordingError(f"{recordings}: no press recordings")
    others: dict[str, int] = {}
    for m in metas:
        if m.label != label:
            others[m.label] = others.get(m.label, 0) + 1
    if others and not relabel:
        raise RecordingError(
            f"{recordings}: " + ", ".join(f"{n} presses labelled {lab!r}"
                                          for lab, n in others.items())
            + f" in their metadata, not {label!r}: add them under their own --label, or say "
            f"--relabel to file them as {label!r}")
    index_path, test = _test_split(Path(recordings), metas)
    if test and not allow_test:
        raise RecordingError(
            f"{recordings}: {len(test)} presses of {', '.join(sorted({m.label for m in test}))} "
            f"are split test in {index_path}: a database that holds its test presses scores "
            "Table I on what it learned. Add other presses, or say --allow-test (the manifest "
            "records it, and Table I says so)")
    thresholds = grouped([replace(m, label=label) for m in metas], "x_th")[label]
    problem = mixed(label, "thresholds x_th", thresholds)
    if problem:
        raise RecordingError(f"{recordings}: {problem}")
    x_th = next(iter(thresholds))
    manifest = read_raw(Path(model_dir))
    known = {str(k): float(v) for k, v in manifest.get(CLASS_X_TH, {}).items()}
    if not known:
        log.warning("%s records no class thresholds (built before vt-train build): the "
                    "threshold %g is not checked", Path(model_dir) / "manifest.json", x_th)
    if force:
        try:
            _check_threshold(label, x_th, known)
        except ModelError as exc:
            log.warning("--force: %s", exc)
    else:
        _check_threshold(label, x_th, known)
    digests = manifest.get(PRESS_SHA256)
    if digests is None:
        log.warning("%s records no press digests (built before presses were identified by "
                    "content): only presses added from now on are checked for copies",
                    Path(model_dir) / "manifest.json")
    _check_new(metas, digests or {})
    presses = load_presses(recordings)
    old = model.database
    sources = [Path(p).name for p in presses.paths for _ in offsets_of(presses)]
    offsets = np.tile(np.asarray(offsets_of(presses), dtype=np.int8), len(presses))
    z, code = encode_presses(model.encoder, presses)
    db = old.with_class(ClassInfo(label, description.strip(), "added"), z, code, sources,
                        offsets, reference_features(presses))
    if old.feature is None:
        log.warning("%s has no reference features (built before they were stored): the "
                    "daemon's familiarity stays in the embedding until vt-train db build",
                    Path(model_dir) / "database.npz")
    db.save(model_dir)
    sections: dict = {"database": summary(db),
                      PRESS_SHA256: (digests or {}) | press_digests(
                          replace(m, label=label) for m in metas)}
    if known:
        sections[CLASS_X_TH] = known | {label: known.get(label, x_th)}
    if test:
        log.warning("--allow-test: %d presses of the test split of %s added; Table I will say "
                    "so", len(test), index_path)
        sections[TEST_PRESSES_ADDED] = [*manifest.get(TEST_PRESSES_ADDED, []), {
            "label": label, "presses": len(test), "dataset": str(index_path)}]
    write_manifest(model_dir, sections)
    log.info("added %d presses (%d references) of %s (%s) at x_th %g; database now %d "
             "references of %d classes", len(presses), len(z), label,
             "existing class" if label in old.labels else "new class", x_th, len(db),
             len(db.classes))
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
