"""References taught to the running robot: an overlay beside the verified model, never in it.

A taught press (a new object, or "this was..." on an episode) is kept in the state directory,
``<state_dir>/references/``: ``references.json`` (one entry per taught press: its id, label,
description, the episode it came from, when and through what it was taught, the ``x_th``
and stream rate it was pressed at, the digest of the model it was embedded with, and its
embedding) and ``presses/<id>.press.npz`` (the press itself, labelled as taught, so that
retention of the episode store cannot lose it and :meth:`ReferenceStore.export` can hand it
to the next full build). Every write is atomic (the press first, the index after it), and
the read-modify-write of an add or a removal holds a file lock, so two writers (the daemon
and a CLI run) never lose one another's change.

One entry per press, holding the embedding at every subsampling offset the model's
database was cut at (z and code per offset) and its feature there (each channel's mean over
the model input, the space :class:`Familiarity` ranks in), as ``vt-train db add`` adds a
press: a taught press then weighs in retrieval as a built one does, and the query (offset 0)
finds its nearest offset as it would for a built class. An entry written before features
were kept gets them from its press copy when merged.

Loading checks every field and refuses a malformed file, naming it and the field. Entries
embedded by another model (another manifest digest) are set aside: kept on disk and listed
as stale, never merged (embeddings of another encoder are points of another space); the
press is kept, so an export still folds them into a build. :meth:`Overlay.lookup` merges the
current entries into the model's database (:meth:`ReferenceDatabase.with_class`) and ranks
the merged database's own leave-one-out distances for :class:`Familiarity`: what recognition
looks a press up in (:func:`edge.runtime.compute.lookup_for`).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import re
import secrets
import socket
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from edge import __version__
from edge.core import preprocess, recording
from edge.core.atomic import atomic_dir, atomic_write_bytes, atomic_write_text
from edge.core.descriptions import check_description
from edge.core.errors import BadRequest, DescriptionError, EdgeError, ModelError, NotFoundError
from edge.core.model import (
    ClassInfo,
    Familiarity,
    Model,
    ReferenceDatabase,
    class_rate_hz,
    class_x_th,
    model_x_th,
    x_th_mismatch,
)

log = logging.getLogger(__name__)

REFERENCES_DIR = "references"
INDEX = "references.json"
PRESSES = "presses"
LOCK = ".lock"
SCHEMA = 1
# Who taught a reference.
Source = Literal["api", "mqtt", "cli", "page"]
SOURCES: tuple[str, ...] = get_args(Source)
# A label names a directory and its presses' files when exported: a word of letters,
# digits, "_", "-" and ".", as the catalogue's labels are.
LABEL = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
# The split a taught class gets in an export (the collect format's split): a class the
# encoder is trained on in the next build, as the lab's own reference objects are.
EXPORT_SPLIT = "train"
# The database's ``source`` of a taught reference: its press, by id.
SOURCE_PREFIX = "taught:"
# A taught class that is new to the model gets this split in the merged database.
TAUGHT_SPLIT = "taught"
# What a refusal calls the threshold and the stream: a press's, or the robot's before it
# presses (its setting, and the stream as it runs).
PRESS_NAMES = ("this press's x_th", "this press's stream")
ROBOT_NAMES = ("[press] x_th", "the tactile stream")


def references_dir(state_dir: str | Path) -> Path:
    """Where the references taught to a daemon with this state directory are kept."""
    return Path(state_dir) / REFERENCES_DIR


@dataclass(frozen=True)
class TaughtReference:
    """One taught press and its embedding by one model."""

    id: str
    label: str
    description: str
    episode: str | None  # the episode the press came from (None: not from an episode)
    taught_at: str  # ISO 8601, UTC
    source: str  # who taught it: one of SOURCES
    x_th: float  # the threshold the press stopped at
    rate_hz: float | None  # the stream's rate over its crop window (None: not measured)
    model: str  # the digest of the model that embedded it
    offsets: tuple[int, ...]  # the subsampling offsets embedded, one row of z each
    z: tuple[tuple[float, ...], ...]
    code: tuple[int, ...]
    press_sha256: str  # its frames' (recording.frames_sha256): one press is taught once
    # Per offset, each channel's mean over the model input (None: taught before it was kept).
    feature: tuple[tuple[float, ...], ...] | None = None

    @property
    def press_file(self) -> str:
        return f"{PRESSES}/{self.id}{recording.SUFFIX}"

    def to_json(self) -> dict[str, Any]:
        return {"id": self.id, "label": self.label, "description": self.description,
                "episode": self.episode, "taught_at": self.taught_at, "source": self.source,
                "x_th": self.x_th, "rate_hz": self.rate_hz, "model": self.model,
                "offsets": list(self.offsets), "z": [list(row) for row in self.z],
                "code": list(self.code), "press_sha256": self.press_sha256,
                **({} if self.feature is None
                   else {"feature": [list(row) for row in self.feature]})}

    @classmethod
    def from_json(cls, raw: Any, where: str) -> TaughtReference:
        """One entry; :class:`ModelError` naming ``where`` and the field if malformed."""
        if not isinstance(raw, dict):
            raise ModelError(f"{where}: must be an object, got {type(raw).__name__}")

        def field(name: str, ok: Any, want: str) -> Any:
            value = raw.get(name)
            if not ok(value):
                raise ModelError(f"{where}.{name}: must be {want}, got {value!r:.60}")
            return value

        def text(v: Any) -> bool:
            return isinstance(v, str) and bool(v)

        def number(v: Any) -> bool:
            return type(v) in (int, float) and np.isfinite(v) and v > 0

        offsets = field("offsets", lambda v: isinstance(v, list) and bool(v) and all(
            type(o) is int and 0 <= o < 128 for o in v), "a non-empty list of offsets")
        n = len(offsets)
        def rows(v: Any) -> bool:
            return isinstance(v, list) and len(v) == n and all(
                isinstance(row, list) and row and len(row) == len(v[0])
                and all(type(x) in (int, float) and np.isfinite(x) for x in row) for row in v)

        want = f"{n} rows (one per offset) of equally many finite numbers"
        z = field("z", rows, want)
        feature = (None if raw.get("feature") is None
                   else field("feature", rows, f"null or {want}"))
        return cls(
            id=field("id", lambda v: text(v) and LABEL.fullmatch(v), "a reference id"),
            label=field("label", lambda v: text(v) and LABEL.fullmatch(v), "a label"),
            description=field("description", text, "a non-empty string"),
            episode=field("episode", lambda v: v is None or text(v), "an episode id or null"),
            taught_at=field("taught_at", text, "an ISO 8601 time"),
            source=field("source", lambda v: v in SOURCES, f"one of {', '.join(SOURCES)}"),
            x_th=float(field("x_th", number, "a threshold > 0")),
            rate_hz=(None if raw.get("rate_hz") is None
                     else float(field("rate_hz", number, "a rate > 0 or null"))),
            model=field("model", text, "a model digest"),
            offsets=tuple(offsets),
            z=tuple(tuple(float(x) for x in row) for row in z),
            code=tuple(field("code", lambda v: isinstance(v, list) and len(v) == n and all(
                type(c) is int and c >= 0 for c in v), f"{n} codes >= 0")),
            press_sha256=field("press_sha256", text, "a sha256"),
            feature=(None if feature is None
                     else tuple(tuple(float(x) for x in row) for row in feature)))


@dataclass(frozen=True)
class Lookup:
    """What recognition looks a press up in: the model's database with the taught references
    merged in, its :class:`Familiarity`, and the overlay that was merged."""

    database: ReferenceDatabase
    familiarity: Familiarity
    overlay: Overlay


@dataclass(frozen=True)
class Overlay:
    """The taught references as read, for one model: those it embedded (``current``), and
    those another model did (``stale``: kept, listed, never used)."""

    path: Path | None  # the index file (None: no references are kept for this model)
    digest: str  # sha256 of the index file ("" where there is none)
    current: tuple[TaughtReference, ...] = ()
    stale: tuple[TaughtReference, ...] = ()

    @classmethod
    def of(cls, path: Path, digest: str, refs: Sequence[TaughtReference],
           model_digest: str) -> Overlay:
        return cls(path, digest, tuple(r for r in refs if r.model == model_digest),
                   tuple(r for r in refs if r.model != model_digest))

    def to_json(self) -> list[dict[str, Any]]:
        """Every reference as listed (``stale``: embedded by another model, not used),
        without its embedding."""
        return [{**{k: v for k, v in ref.to_json().items()
                    if k not in ("z", "code", "feature")},
                 "stale": stale}
                for refs, stale in ((self.current, False), (self.stale, True))
                for ref in refs]

    def labels(self) -> dict[str, list[TaughtReference]]:
        """The current references by label, in the order they were taught."""
        out: dict[str, list[TaughtReference]] = {}
        for ref in self.current:
            out.setdefault(ref.label, []).append(ref)
        return out

    def merged(self, model: Model) -> ReferenceDatabase:
        """The model's database with every current reference added under its label (the
        latest description of a label wins, as ``db add`` gives a class its new one)."""
        database = model.database
        size = database.codebook.shape[0]
        for ref in self.current:
            where = f"{self.path}: reference {ref.id}"
            if len(ref.z[0]) != database.dim:
                raise ModelError(f"{where}: z has {len(ref.z[0])} dims, the model embeds in "
                                 f"{database.dim}")
            if max(ref.code) >= size:
                raise ModelError(f"{where}: code outside the model's codebook 0..{size - 1}")
            if (ref.feature is not None and database.feature is not None
                    and len(ref.feature[0]) != database.feature.shape[1]):
                raise ModelError(f"{where}: feature has {len(ref.feature[0])} channels, the "
                                 f"model's references {database.feature.shape[1]}")
        # A model database without features ranks in the embedding: none are needed.
        features = ({} if database.feature is None
                    else {ref.id: self._feature(ref, model) for ref in self.current})
        missing = [ref_id for ref_id, f in features.items() if f is None]
        if missing:
            log.warning("%s: %d taught references have no feature and no readable press "
                        "(%s): familiarity falls back to the embedding ratio; teach them "
                        "again to restore it", self.path, len(missing), ", ".join(missing))
        for label, refs in self.labels().items():
            database = database.with_class(
                ClassInfo(label, refs[-1].description, TAUGHT_SPLIT),
                np.asarray([row for ref in refs for row in ref.z], dtype=np.float32),
                np.asarray([c for ref in refs for c in ref.code], dtype=np.int64),
                [SOURCE_PREFIX + ref.id for ref in refs for _ in ref.offsets],
                np.asarray([o for ref in refs for o in ref.offsets], dtype=np.int8),
                None if missing or not features
                else np.concatenate([features[ref.id] for ref in refs]))
        return database

    def _feature(self, ref: TaughtReference, model: Model) -> np.ndarray | None:
        """The reference's feature at each of its offsets: as kept, or (an entry taught
        before features were kept) from the press copy beside the index; None where that is
        missing or unreadable."""
        if ref.feature is not None:
            return np.asarray(ref.feature, dtype=np.float32)
        if self.path is None:
            return None
        try:
            rec = recording.load(self.path.parent / ref.press_file)
        except (OSError, EdgeError) as exc:
            log.warning("%s: reference %s: %s", self.path, ref.id, exc)
            return None
        return model_inputs(model, rec, ref.offsets).mean(axis=1)

    def lookup(self, model: Model) -> Lookup:
        """The merged database of ``model`` and its familiarity (the leave-one-out
        distances over all of it: a few tens of milliseconds for the shipped 1600)."""
        database = self.merged(model)
        return Lookup(database, Familiarity(database), self)


def signature(directory: Path | None) -> tuple[int, int, int] | None:
    """What tells that the index in ``directory`` changed (inode, mtime, size: every atomic
    write is a new inode); None where there is none. One ``stat``: cheap for every press."""
    if directory is None:
        return None
    try:
        st = os.stat(directory / INDEX)
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


def model_inputs(model: Model, rec: recording.Recording, offsets: Sequence[int]
                 ) -> np.ndarray:
    """The press's model input at each of ``offsets``: (offsets, steps, channels)."""
    spec = model.window
    window = preprocess.crop(rec.recv_time, preprocess.recording_units(rec), rec.t_stop, spec)
    return np.stack([preprocess.subsample(window, o, spec) for o in offsets])


def embed_press(model: Model, rec: recording.Recording
                ) -> tuple[np.ndarray, np.ndarray, list[int], np.ndarray]:
    """The press's model input at every offset the model's database holds, embedded:
    z (offsets, D), code (offsets,), the offsets and the features (offsets, channels: each
    channel's mean over the input). Blocking (milliseconds)."""
    offsets = model.database.offsets
    x = model_inputs(model, rec, offsets)
    z, code = model.encoder(x)
    return z, code, offsets, x.mean(axis=1)


class ReferenceStore:
    """The taught references of one state directory (``references_dir(state_dir)``).

    Every method blocks (file I/O, and :meth:`add` the encoder): the daemon calls
    :meth:`add` in its compute process (:func:`edge.runtime.compute.teach_press`) and the
    others through ``asyncio.to_thread``.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.index = self.root / INDEX

    # ----- reading

    def read(self) -> tuple[str, list[TaughtReference]]:
        """The index's digest and every entry (none where there is no index yet);
        :class:`ModelError` naming the file and the field where it is malformed."""
        try:
            data = self.index.read_bytes()
        except FileNotFoundError:
            return "", []
        except OSError as exc:
            raise ModelError(f"{self.index}: cannot read: {exc.strerror or exc}") from None
        try:
            raw = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ModelError(f"{self.index}: not valid JSON ({exc}); restore it, or move it "
                             "aside to start without taught references") from None
        if not isinstance(raw, dict) or raw.get("schema_version") != SCHEMA:
            raise ModelError(f"{self.index}: schema_version: not a version {SCHEMA} index of "
                             "taught references")
        entries = raw.get("references")
        if not isinstance(entries, list):
            raise ModelError(f"{self.index}: references: must be a list")
        refs = [TaughtReference.from_json(e, f"{self.index}: references[{i}]")
                for i, e in enumerate(entries)]
        seen: set[str] = set()
        for i, ref in enumerate(refs):
            if ref.id in seen:
                raise ModelError(f"{self.index}: references[{i}].id: {ref.id!r} twice")
            seen.add(ref.id)
        return hashlib.sha256(data).hexdigest(), refs

    def load(self, model_digest: str) -> Overlay:
        """The references for the model of ``model_digest``; those of another model are set
        aside (logged once a load)."""
        overlay = Overlay.of(self.index, *self.read(), model_digest)
        if overlay.stale:
            log.warning("%s: %d taught references were embedded by another model and are not "
                        "used (%s); teach those objects again, or fold them into a build "
                        "(vt-edge references export)", self.index, len(overlay.stale),
                        ", ".join(sorted({r.label for r in overlay.stale})))
        return overlay

    # ----- changing

    def add(self, model: Model, rec: recording.Recording, label: str,
            description: str | None = None, *, source: Source, episode: str | None = None,
            append: bool = False, now: float | None = None) -> TaughtReference:
        """Teach the press ``rec`` as ``label``: embed it with ``model``, keep the press and
        the entry. :class:`BadRequest` saying why where it is refused: a label unlike a name;
        a new label without a description, or one that says how the object feels; a label
        the model's database or the overlay has, unless ``append``; a press stopped at
        another ``x_th``, or streamed at another rate, than the class's (or, for a new
        class, the model's); the same press taught already."""
        rate_hz = preprocess.recording_rate(rec, model.window).window_hz
        with self._locked():
            digest, everything = self.read()
            overlay = Overlay.of(self.index, digest, everything, model.digest)
            known = label in model.database.labels or label in overlay.labels()
            description = self._admitted(model, overlay, label, description, source, append,
                                         float(rec.threshold), rate_hz, PRESS_NAMES)
            sha = recording.frames_sha256(rec)
            same = [r for r in everything if r.press_sha256 == sha]
            if same:
                raise BadRequest(f"this press is taught already, as {same[0].label!r} "
                                 f"(reference {same[0].id})")
            z, code, offsets, feature = embed_press(model, rec)
            ref = TaughtReference(
                id=secrets.token_hex(6), label=label, description=description,
                episode=episode, taught_at=_iso(now), source=source,
                x_th=float(rec.threshold), rate_hz=rate_hz,
                model=model.digest, offsets=tuple(offsets),
                z=tuple(tuple(float(v) for v in row) for row in z),
                code=tuple(int(c) for c in code), press_sha256=sha,
                feature=tuple(tuple(float(v) for v in row) for row in feature))
            # The press first: an index never names a press that is not on disk.
            recording.save(replace(rec, label=label), self.root / ref.press_file)
            self._write([*everything, ref])
        log.info("taught %s (%s, %s): reference %s from %s, %d offsets", label,
                 "more presses" if known else "new class", source, ref.id,
                 f"episode {episode}" if episode else "a press", len(offsets))
        return ref

    def remove(self, ref_id: str) -> TaughtReference:
        """Remove the reference ``ref_id`` (and its press); :class:`NotFoundError` if none."""
        with self._locked():
            _, refs = self.read()
            gone = [r for r in refs if r.id == ref_id]
            if not gone:
                raise NotFoundError(f"no taught reference {ref_id!r}")
            self._write([r for r in refs if r.id != ref_id])
        log.info("removed taught reference %s (%s)", ref_id, gone[0].label)
        return gone[0]

    def remove_label(self, label: str) -> list[TaughtReference]:
        """Remove every reference taught as ``label``; :class:`NotFoundError` if none."""
        with self._locked():
            _, refs = self.read()
            gone = [r for r in refs if r.label == label]
            if not gone:
                raise NotFoundError(f"no taught references of {label!r}")
            self._write([r for r in refs if r.label != label])
        log.info("removed %d taught references of %s", len(gone), label)
        return gone

    def check(self, model: Model, label: str, description: str | None, *, source: Source,
              append: bool, x_th: float, rate_hz: float | None) -> str:
        """What :meth:`add` would refuse before there is a press: the label, description
        and append rules, and presses stopped at ``x_th`` (``[press] x_th``) from a stream
        at ``rate_hz`` (None: not measured) against the class's; :class:`BadRequest` saying
        why. The description the presses would be taught with."""
        digest, everything = self.read()
        return self._admitted(model, Overlay.of(self.index, digest, everything, model.digest),
                              label, description, source, append, x_th, rate_hz)

    def _admitted(self, model: Model, overlay: Overlay, label: str, description: str | None,
                  source: str, append: bool, x_th: float, rate_hz: float | None,
                  names: tuple[str, str] = ROBOT_NAMES) -> str:
        """The description ``label`` is taught with, or :class:`BadRequest` saying why a
        press of it at ``x_th`` and ``rate_hz`` (``names``: what to call them) is refused."""
        if not isinstance(label, str) or not LABEL.fullmatch(label):
            raise BadRequest(f"label {label!r:.80}: must be 1-64 letters, digits, '_', '-' or "
                             "'.', starting with a letter or digit")
        if source not in SOURCES:
            raise BadRequest(f"source {source!r}: must be one of {', '.join(SOURCES)}")
        taught = overlay.labels()
        known = label in model.database.labels or label in taught
        if known and not append:
            where = ("the model's database" if label in model.database.labels
                     else "the taught references")
            raise BadRequest(f"{label!r} is in {where} already: say append to add "
                             "presses to it, or teach another label")
        if description is not None and description.strip():
            try:
                description = check_description(description, label)
            except DescriptionError as exc:
                raise BadRequest(str(exc)) from None
        elif known:
            description = (taught[label][-1].description if label in taught
                           else model.database.description(label))
        else:
            raise BadRequest(f"{label!r} is a new class: it needs a description that "
                             "names the object (e.g. 'wood cube')")
        self._check_stream(model, overlay, label, x_th, rate_hz, names)
        return description

    def _check_stream(self, model: Model, overlay: Overlay, label: str, x_th: float,
                      rate_hz: float | None, names: tuple[str, str]) -> None:
        """Presses at ``x_th`` and ``rate_hz`` against the class's (a new class: the
        model's), in one line naming both."""
        taught = overlay.labels().get(label, [])
        thresholds = class_x_th(model.manifest)
        expected_x_th = (taught[0].x_th if taught
                         else thresholds.get(label, model_x_th(thresholds)))
        problem = x_th_mismatch(x_th, expected_x_th, names[0])
        if problem is not None:
            raise BadRequest(f"{label!r}: {problem}")
        rates = class_rate_hz(model.manifest)
        if taught and taught[0].rate_hz is not None:
            expected = taught[0].rate_hz
        elif label in rates:
            expected = rates[label]
        else:  # a new class: the model's classes' (the grid's where it records none)
            expected = float(np.median(list(rates.values()))) if rates \
                else model.window.rate_hz
        problem = preprocess.rate_problem(rate_hz, expected)
        if problem is not None:
            raise BadRequest(f"{label!r}: {names[1]} at {problem}, the rate the class's "
                             "references were pressed at: a press at another rate embeds "
                             "elsewhere")

    def _write(self, refs: Sequence[TaughtReference]) -> None:
        """The index, atomically; then the presses no entry names are removed (a press
        written before a crash that lost its entry, or one removed)."""
        atomic_write_text(self.index, json.dumps(
            {"schema_version": SCHEMA, "software_version": __version__,
             "references": [r.to_json() for r in refs]}, indent=1) + "\n")
        named = {Path(r.press_file).name for r in refs}
        for path in (self.root / PRESSES).glob(f"*{recording.SUFFIX}"):
            if path.name not in named:
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / LOCK, "a") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    # ----- export

    def export(self, dest: str | Path, name: str | None = None) -> Path:
        """Write every taught press (stale ones included: a build embeds the press anew) as
        a collection in the ``collect`` format: ``DEST/dataset.json`` and
        ``DEST/<label>/<label>_NNN.press.npz``, each class split ``train`` with its
        description, ``x_th`` and rate, so that ``vt-train build`` folds them into the next
        model. ``DEST`` must not exist; it appears whole or not at all."""
        dest = Path(dest)
        if dest.exists():
            raise BadRequest(f"{dest} exists: export into a new directory")
        _, refs = self.read()
        if not refs:
            raise NotFoundError(f"{self.root}: no taught references to export")
        by_label: dict[str, list[TaughtReference]] = {}
        for ref in sorted(refs, key=lambda r: r.taught_at):
            by_label.setdefault(ref.label, []).append(ref)
        first: recording.Recording | None = None
        classes = []
        with atomic_dir(dest) as out:
            for label, group in by_label.items():
                for i, ref in enumerate(group):
                    press = self.root / ref.press_file
                    try:
                        data = press.read_bytes()
                    except FileNotFoundError:
                        raise ModelError(f"{press}: the press of reference {ref.id} "
                                         f"({label}) is missing") from None
                    first = first or recording.from_bytes(data)
                    atomic_write_bytes(recording.press_path(out, label, i), data)
                rates = [r.rate_hz for r in group if r.rate_hz is not None]
                classes.append({
                    "label": label, "split": EXPORT_SPLIT,
                    "description": group[-1].description, "x_th": group[0].x_th,
                    "rate_hz": round(float(np.median(rates)), 1) if rates else None,
                    "presses": len(group), "references": [r.id for r in group]})
            assert first is not None
            atomic_write_text(out / recording.DATASET_INDEX, json.dumps(
                _dataset_index(name or dest.name, first, classes), indent=2) + "\n")
        log.info("exported %d taught presses of %d classes to %s", len(refs), len(classes),
                 dest)
        return dest


def _dataset_index(name: str, rec: recording.Recording, classes: list[dict[str, Any]]
                   ) -> dict[str, Any]:
    """The collection's ``dataset.json`` (the keys ``collect`` writes)."""
    emulated = rec.source == "sim"
    origin = {"kind": "emulated" if emulated else "robot",
              "recorder": "taught to the running daemon",
              "robot": None if emulated else socket.gethostname(),
              "sensor": {"model": rec.sensor_model, "serials": []}}
    where = "the emulated robot" if emulated else f"robot {origin['robot']}"
    return {"dataset": name,
            "recorder": f"vt-edge references export: presses taught to the daemon on {where}",
            "origin": origin, "software_version": __version__, "classes": classes}


def _iso(now: float | None) -> str:
    when = datetime.now(UTC) if now is None else datetime.fromtimestamp(now, UTC)
    return when.isoformat(timespec="milliseconds").replace("+00:00", "Z")


__all__ = ["INDEX", "LOCK", "PRESSES", "REFERENCES_DIR", "SOURCES", "Lookup", "Overlay",
           "ReferenceStore", "Source", "TaughtReference", "embed_press", "model_inputs",
           "references_dir",
           "signature"]
