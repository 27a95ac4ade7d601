"""``vt-train eval-vlm``: the paper's Table I protocol against any OpenAI-compatible VLM.

For every press of each unseen test set (FoodReplica: 22 classes, Cube: 4) the VLM is asked
once per condition to name the object among that set's labels, exactly as the robot asks it:
the offset-0 input through the shipped encoder and reference database
(:func:`edge.core.model.load_model`), the description of the nearest distinct classes, the
shipped prompt templates (:mod:`edge.vlm.prompt`, ``models/prompts``) and the robot's own client
(:class:`edge.vlm.client.OpenAIVLM`: data-URL image, temperature 0, seed, ``[vlm]
structured_output`` with the robot's fallback when a server refuses it, answer checked
against the candidates with one corrective retry, transport retries with backoff). The
picture is :func:`edge.sim.camera.render` of the press's label (a real food and its replica
look the same), or a photo from a user's directory for real data.

Conditions (``CONDITIONS``): ``vision_only`` (the vision_only template: no tactile
sentence), ``vq_top3`` (the proposed method), ``vq_top1`` (only the nearest class's
description), ``beta_top3`` (the beta-VAE's embeddings and its own reference database, built
from the reference recordings: every offset of every press, like the shipped one), and, not
in the default set, ``vq_zeros_top3`` (the VQ-VAE with the zero-input decoder, from its
checkpoint, the same way), ``vq_top3_adjectives`` (the method with the references described
in hand-written tactile adjectives, :mod:`train.eval.ablation`) and ``tactile_only``.

Every answer is appended to ``answers.jsonl`` in the output directory as soon as it arrives
(one ``write`` of one line, ``O_APPEND``, fsync), keyed by condition, dataset, press, VLM
model and the sha256 of the rendered prompt and of the image: a run that is interrupted (or
stopped by an unreachable server) continues where it stopped and never asks a cached
question again; a changed template, description or picture is a new question. Jobs run in a
fixed order (round-robin over classes, so ``--limit`` keeps every class in play), at most
``concurrency`` requests in flight.

Outputs: ``eval_vlm.json`` (accuracy, invalid answers and confusion matrix per dataset and
condition, every press's answers), ``eval_vlm.md`` (a table like the paper's Table I),
``confusion_<dataset>.png``. An ``invalid_answer`` (not a candidate, even after the
corrective retry) counts as wrong and has its own column: it is never mapped to a label.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import hashlib
import io
import json
import logging
import os
import re
import textwrap
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import aiohttp
import numpy as np

from edge.core.atomic import atomic_write_text
from edge.core.config import VLMConfig
from edge.core.errors import EdgeError, EvalVLMError, ImageError, ModelError, RecordingError
from edge.core.model import Origin, ReferenceDatabase, load_model, manifest_origin
from edge.core.progress import PLAIN_EVERY_S
from edge.core.progress import Progress as Bar
from edge.core.recording import DATASET_INDEX
from edge.vlm.client import OpenAIVLM, VLMAnswer, VLMClient
from edge.vlm.images import prepare_image
from edge.vlm.prompt import PromptTemplate, load_template
from train.learn.data import PressSet, load_presses

log = logging.getLogger(__name__)

ANSWERS_FILE = "answers.jsonl"
REPORT_JSON = "eval_vlm.json"
REPORT_MD = "eval_vlm.md"
CACHE_SCHEMA = 1
INVALID = "invalid_answer"
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
DEFAULT_CONCURRENCY = 4
DPI = 80




@dataclass(frozen=True)
class Condition:
    name: str
    title: str
    mode: str  # the prompt template: vision_only / vision_tactile / tactile_only
    variant: str | None  # the tactile encoder: vq / beta / vq_zeros, None: no tactile sentence
    k: int  # distinct reference classes in the description (0: none)
    # Where the descriptions come from: the database (object names, the method) or the
    # ablation's hand-written tactile adjectives.
    descriptions: str = "names"


CONDITIONS: dict[str, Condition] = {c.name: c for c in (
    Condition("vision_only", "Vision only", "vision_only", None, 0),
    Condition("vq_top3", "Vision + tactile (VQ-VAE, top-3)", "vision_tactile", "vq", 3),
    Condition("vq_top1", "Vision + tactile (VQ-VAE, top-1)", "vision_tactile", "vq", 1),
    Condition("beta_top3", "Vision + tactile (beta-VAE, top-3)", "vision_tactile", "beta", 3),
    Condition("vq_zeros_top3", "Vision + tactile (VQ-VAE with the zero-input decoder, top-3)",
              "vision_tactile", "vq_zeros", 3),
    Condition("vq_top3_adjectives", "Vision + tactile (VQ-VAE, top-3), descriptions in "
              "tactile adjectives (ablation)", "vision_tactile", "vq", 3, "adjectives"),
    Condition("tactile_only", "Tactile only (VQ-VAE, top-3, no image)", "tactile_only", "vq",
              3),
)}
DEFAULT_CONDITIONS = ("vision_only", "vq_top3", "vq_top1", "beta_top3")
# Conditions whose encoder comes from a training checkpoint, not the shipped model.
CHECKPOINT_VARIANTS = ("beta", "vq_zeros")

# The paper's Table I (GPT-4V), percent, for the side-by-side table.
PAPER = {"vision_only": {"foodreplica": 53.6, "cube": 50.0},
         "vq_top3": {"foodreplica": 58.9, "cube": 65.0},
         "vq_top1": {"foodreplica": 58.4, "cube": 52.5},
         "beta_top3": {"foodreplica": 52.5, "cube": 50.0}}
DATASET_TITLES = {"foodreplica": "FoodReplica", "cube": "Cube"}
PAPER_SETS = tuple(DATASET_TITLES)
PHOTO_BESIDE = "photos beside the presses"
SIM_CAMERA = "simulated camera (edge.sim.camera.render)"


def parse_paper_sets(items: Iterable[str]) -> dict[str, str]:
    """``--paper-set NAME=foodreplica`` (or ``=cube``): which of our sets stands beside which
    of the paper's; a set named like the paper's stands beside it unasked."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, paper = item.partition("=")
        if not sep or not name.strip() or paper.strip().lower() not in PAPER_SETS:
            raise EvalVLMError(f"--paper-set {item!r}: expected NAME=foodreplica or NAME=cube")
        out[name.strip()] = paper.strip().lower()
    return out


def paper_set(name: str, mapping: Mapping[str, str]) -> str | None:
    """The paper's set ``name`` stands beside, if any."""
    return mapping.get(name) or (name if name in PAPER_SETS else None)


def set_title(name: str, mapping: Mapping[str, str]) -> str:
    paper = paper_set(name, mapping)
    if paper is None or paper == name:
        return DATASET_TITLES.get(name, name)
    return f"{name} (as {DATASET_TITLES[paper]})"


def describe_origin(origin: Mapping[str, Any] | None) -> str:
    """Who pressed: the emulated robot, or which robot and sensor (the contract's origin)."""
    if origin is None:
        return "presses of unrecorded origin"
    if origin.get("kind") != "robot":
        return "simulated presses by the emulated robot"
    sensor = origin.get("sensor") or {}
    serials = ", ".join(sensor.get("serials") or [])
    parts = ["real presses by the robot" + (f" `{origin['robot']}`" if origin.get("robot")
                                            else "")]
    if sensor.get("model"):
        parts.append(f"with a XELA {sensor['model']}" + (f" ({serials})" if serials else ""))
    if origin.get("recorder"):
        parts.append(f"pressed by {origin['recorder']}")
    return " ".join(parts)


def reference_origin(directory: Path) -> dict[str, Any] | None:
    """Who pressed a dataset directory's presses (its ``dataset.json`` origin); None when
    it has no ``dataset.json``."""
    index = Path(directory) / DATASET_INDEX
    try:
        meta = json.loads(index.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise RecordingError(f"{index}: unreadable: {exc}") from None
    return Origin.of_dataset(meta, str(index)).to_json()


def model_facts(manifest: Mapping[str, Any]) -> dict[str, Any]:
    """What a report says about a tactile model: its decoder, its data's origin, and whether
    it was built from a lab's data (``vt-train build``) or is the simulated release."""
    decoder = manifest.get("training", {}).get("vq", {}).get("config", {}).get(
        "model", {}).get("decoder")
    origin = manifest_origin(manifest)
    built = str(manifest.get("created_by", "")).startswith("vt-train build")
    # Where a built model's presses came from: the advice names them, not a placeholder.
    data = manifest.get("training", {}).get("dataset", {}).get("directory")
    unseen = [u for u in manifest.get("evaluation", {}).get("unseen", []) if u != data]
    return {"decoder": decoder, "origin": origin.to_json(),
            "built": built or not origin.emulated, "data": data, "unseen": unseen}


def decoder_title(decoder: str | None) -> str:
    return {"teacher": "the paper's (z_q and X, teacher-forced)",
            "zeros": "zero-input (z_q alone)"}.get(
        decoder or "", "not recorded in the manifest")


def variant_advice(facts: Mapping[str, Any], model_dir: Path, variant: str) -> str:
    """How to train a missing comparison variant (``beta`` or ``zeros``) from the data the
    model came from: ``vt-train build`` for a lab's data, ``vt-train release`` only for the
    simulated set."""
    if facts["built"]:
        unseen = "".join(f" --unseen {u}" for u in facts.get("unseen") or ())
        return (f"`vt-train build --data {facts.get('data') or 'DATASET'}{unseen} --out "
                f"{model_dir} --variant {variant}` (the data the model was built from; the "
                "steps already done are kept)")
    return "`vt-train release` (the simulated reference set)"


@dataclass(frozen=True)
class EvalVLMConfig:
    vlm: VLMConfig  # base_url, model, key, timeouts; ``mode`` is set per condition
    out: Path
    unseen: tuple[Path, ...]
    model_dir: Path = Path("models")
    conditions: tuple[str, ...] = DEFAULT_CONDITIONS
    reference: Path | None = None  # reference recordings (the checkpoint variants' database)
    beta: Path | None = None  # beta-VAE checkpoint
    zeros: Path | None = None  # the zero-input decoder's VQ-VAE checkpoint
    images: Path | None = None  # photos; None = beside the presses, else the simulated camera
    limit: int | None = None  # presses per dataset
    concurrency: int = DEFAULT_CONCURRENCY
    paper_sets: Mapping[str, str] = dataclasses.field(default_factory=dict)  # ours -> paper's

    def validate(self, endpoint: bool = True) -> None:
        """Refuse a configuration that cannot run; ``endpoint=False`` (a dry run) lets the
        VLM endpoint be missing."""
        self.vlm.validate("vlm")
        if endpoint and not self.vlm.configured:
            raise EvalVLMError("no VLM endpoint: give --url (and --model)")
        unknown = [c for c in self.conditions if c not in CONDITIONS]
        if unknown or not self.conditions:
            raise EvalVLMError(f"unknown condition(s) {', '.join(unknown) or '(none given)'}; "
                               f"known: {', '.join(CONDITIONS)}")
        if len(set(self.conditions)) != len(self.conditions):
            raise EvalVLMError("a condition is listed twice")
        if "beta_top3" in self.conditions and (self.beta is None or self.reference is None):
            raise EvalVLMError("beta_top3 needs --beta CHECKPOINT and --reference RECORDINGS")
        if "vq_zeros_top3" in self.conditions and (self.zeros is None
                                                   or self.reference is None):
            raise EvalVLMError("vq_zeros_top3 needs --zeros CHECKPOINT and --reference "
                               "RECORDINGS")
        if not self.unseen:
            raise EvalVLMError("no unseen recordings given")
        if self.limit is not None and self.limit < 1:
            raise EvalVLMError(f"--limit must be >= 1, got {self.limit}")
        if not 1 <= self.concurrency <= 64:
            raise EvalVLMError(f"--concurrency must be in 1..64, got {self.concurrency}")


# --------------------------------------------------------------------------------------
# Test sets, retrieval and the questions


@dataclass(frozen=True, eq=False)
class UnseenSet:
    """One unseen dataset, its presses in evaluation order and its candidate labels."""

    name: str
    directory: Path
    candidates: tuple[str, ...]
    presses: PressSet
    press_ids: tuple[str, ...]  # recording paths relative to ``directory``
    origin: dict[str, Any] | None = None  # who pressed (dataset.json); None: not recorded


def round_robin(labels: Sequence[str], classes: Sequence[str]) -> list[int]:
    """Indices ordered press 0 of every class (in ``classes`` order), press 1, ...

    ``labels`` must be ordered by path within a class (as :func:`load_presses` gives).
    """
    rank = {c: i for i, c in enumerate(classes)}
    seen: dict[str, int] = {}
    keys = []
    for i, label in enumerate(labels):
        n = seen.get(label, 0)
        seen[label] = n + 1
        keys.append((n, rank[label], i))
    return [i for _, _, i in sorted(keys)]


def load_test_set(directory: str | Path, limit: int | None = None,
                  spec: Any = None) -> UnseenSet:
    """The presses of ``directory``; candidates are its ``dataset.json`` classes (all of
    them, whatever ``limit`` keeps), else the labels found."""
    directory = Path(directory)
    kwargs = {} if spec is None else {"spec": spec}
    presses = load_presses(directory, **kwargs)
    index = directory / DATASET_INDEX
    name = directory.name
    candidates = list(dict.fromkeys(sorted(presses.labels)))
    origin = None
    if index.exists():
        try:
            meta = json.loads(index.read_text(encoding="utf-8"))
            classes = meta["classes"]
            # A collected dataset holds its reference classes too: its test classes are
            # the questions.
            if any(c.get("split") == "test" for c in classes):
                classes = [c for c in classes if c.get("split") == "test"]
                presses = presses.select([str(c["label"]) for c in classes])
            candidates = [str(c["label"]) for c in classes]
            name = str(meta.get("dataset") or name)
            origin = Origin.of_dataset(meta, str(index)).to_json()
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise RecordingError(f"{index}: cannot read the class list: {exc!r}") from None
    stray = sorted(set(presses.labels) - set(candidates))
    if stray:
        raise RecordingError(f"{directory}: presses of {', '.join(stray)}, which "
                             f"{DATASET_INDEX} does not list as classes")
    order = round_robin(presses.labels, candidates)
    if limit is not None:
        order = order[:limit]
    presses = PressSet(presses.x[order], presses.x_bar[order],
                       tuple(presses.labels[i] for i in order),
                       tuple(presses.paths[i] for i in order))
    ids = tuple(Path(p).relative_to(directory).as_posix() for p in presses.paths)
    return UnseenSet(name, directory, tuple(candidates), presses, ids, origin)


@dataclass(frozen=True, eq=False)
class Tactile:
    """One tactile encoder and its reference database, used exactly as the robot uses them."""

    variant: str
    embed: Callable[[np.ndarray], np.ndarray]  # x (N, steps, channels) units -> z (N, D)
    database: ReferenceDatabase

    def topk(self, x: np.ndarray, k: int) -> list[list[tuple[str, float]]]:
        z = self.embed(x)
        return [self.database.topk(q, k) for q in z]


def vq_tactile(model: Any) -> Tactile:
    """The shipped model: ONNX encoder, shipped database (what the robot runs)."""
    return Tactile("vq", lambda x: np.asarray(model.encode(x)[0]), model.database)


def checkpoint_tactile(variant: str, checkpoint: Path, reference: Path, spec: Any,
                       k: int = 3) -> Tactile:
    """A model from its training checkpoint (the beta-VAE, or the VQ-VAE with the zero-input
    decoder): torch embeddings (z; the beta-VAE's posterior mean) and a database of every
    offset of every reference press embedded by it (same classes and descriptions as the
    shipped one)."""
    from train.learn.trainer import load_checkpoint

    model, norm, _ = load_checkpoint(checkpoint)
    got = model.cfg.variant if model.cfg.variant == "beta" else f"vq_{model.cfg.decoder}"
    if got != variant:
        raise ModelError(f"{checkpoint}: a {got} checkpoint, not {variant}")
    return torch_tactile(variant, model, norm, load_reference(reference, spec), k)


def load_reference(reference: Path, spec: Any = None):
    """The reference presses of a recordings directory (its ``dataset.json`` splits), with
    their splits."""
    from train.learn.data import Splits

    splits = Splits.of_dataset(reference)
    kwargs = {} if spec is None else {"spec": spec}
    presses = load_presses(reference, splits.classes, **kwargs).select(splits.classes)
    return presses, splits


def torch_tactile(variant: str, model: Any, norm: Any, reference: tuple[PressSet, Any],
                  k: int = 3) -> Tactile:
    """A torch model and a database of ``reference`` (presses, splits) embedded by it."""
    from train.learn.trainer import embed
    from train.ship import database

    presses, splits = reference

    def embed_z(x: np.ndarray) -> np.ndarray:
        return embed(model, norm, x)[0]

    codebook = None
    if model.quantiser is not None:
        codebook = model.quantiser.codebook.detach().numpy().copy()
    db = database.from_embeddings(presses, splits, embed_z(database.reference_inputs(presses)),
                                  codebook, k=k)
    return Tactile(variant, embed_z, db)


def describe(condition: Condition, db: ReferenceDatabase, labels: Sequence[str]) -> str:
    """The touch sentence of ``labels`` under ``condition``: the database's descriptions
    (object names), or for the ablation the hand-written tactile adjectives."""
    if condition.descriptions == "adjectives":
        from train.eval.ablation import TACTILE_ADJECTIVES

        return ", ".join(TACTILE_ADJECTIVES.get(label) or db.description(label)
                         for label in labels)
    return db.describe(labels)


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._") or "model"


@dataclass(frozen=True, eq=False)
class Job:
    """One question: a press under a condition."""

    condition: Condition
    dataset: str
    press: str
    label: str
    candidates: tuple[str, ...]
    topk: tuple[tuple[str, float], ...]
    description: str
    prompt: str
    image: bytes | None
    image_sha256: str | None
    model: str

    @functools.cached_property
    def prompt_sha256(self) -> str:
        return sha256_hex(self.prompt.encode("utf-8"))

    @functools.cached_property
    def key(self) -> str:
        image = (self.image_sha256 or "none")[:16]
        return (f"{self.condition.name}|{self.dataset}|{self.press}|{self.model}|"
                f"prompt:{self.prompt_sha256[:16]}|image:{image}")

    def record(self, answer: VLMAnswer) -> dict[str, Any]:
        return {
            "schema": CACHE_SCHEMA, "key": self.key, "condition": self.condition.name,
            "dataset": self.dataset, "press": self.press, "label": self.label,
            "model": self.model, "mode": self.condition.mode,
            "prompt_sha256": self.prompt_sha256, "image_sha256": self.image_sha256,
            "topk": [[lab, round(d, 6)] for lab, d in self.topk],
            "description": self.description,
            "answer": answer.to_dict(),
        }


class ImageSource:
    """The picture of a press: a user's photo in ``--images`` (per press, else per class);
    without it the photo ``vt-edge collect`` took beside the press (same stem), else the
    simulated camera's picture of its label."""

    def __init__(self, directory: Path | None = None, vlm: VLMConfig | None = None) -> None:
        self.directory = directory
        self.vlm = vlm or VLMConfig()
        if directory is not None and not directory.is_dir():
            raise EvalVLMError(f"--images {directory}: not a directory")
        self.used: dict[str, dict[str, int]] = {}  # per set: source -> pictures

    @property
    def name(self) -> str:
        if self.directory is not None:
            return str(self.directory)
        if not self.used:
            return SIM_CAMERA
        return "; ".join(f"{dataset}: " + ", ".join(
            f"{source} ({n})" if len(counts) > 1 else source for source, n in counts.items())
            for dataset, counts in self.used.items())

    def _count(self, dataset: str, source: str) -> None:
        counts = self.used.setdefault(dataset, {})
        counts[source] = counts.get(source, 0) + 1

    @staticmethod
    def beside(press_path: Path) -> Path | None:
        """The photo collect saved beside a press: ``<label>_NNN.jpg`` (.jpeg, .png)."""
        stem = press_path.name.split(".")[0]
        for suffix in IMAGE_SUFFIXES:
            path = press_path.with_name(stem + suffix)
            if path.is_file():
                return path
        return None

    def path_for(self, dataset: str, press: str, label: str) -> Path | None:
        assert self.directory is not None
        stem = Path(press).name.split(".")[0]
        for folder in (self.directory / dataset, self.directory):
            for name in (stem, label):
                for suffix in IMAGE_SUFFIXES:
                    path = folder / f"{name}{suffix}"
                    if path.is_file():
                        return path
        return None

    def get(self, dataset: str, press: str, label: str, press_path: Path | None = None
            ) -> bytes:
        if self.directory is None:
            photo = self.beside(press_path) if press_path is not None else None
            self._count(dataset, PHOTO_BESIDE if photo else SIM_CAMERA)
            if photo is not None:
                return _read_image(photo, self.vlm.max_image_side_px, self.vlm.max_image_bytes)
            return _rendered(label)
        path = self.path_for(dataset, press, label)
        if path is None:
            raise EvalVLMError(
                f"no photo of {dataset}/{press} in {self.directory}: expected "
                f"{Path(press).name.split('.')[0]}.jpg or {label}.jpg (or .jpeg/.png) in "
                f"{self.directory / dataset} or {self.directory}")
        return _read_image(path, self.vlm.max_image_side_px, self.vlm.max_image_bytes)


@functools.lru_cache(maxsize=256)
def _rendered(label: str) -> bytes:
    from edge.sim.camera import render

    try:
        return render(label)
    except KeyError:
        raise EvalVLMError(f"the simulated camera has no picture of {label!r}: give --images "
                           "DIR with photos for real data") from None


@functools.lru_cache(maxsize=256)
def _read_image(path: Path, max_side_px: int, max_bytes: int) -> bytes:
    """A photo's bytes, checked now (as the client will prepare it) so that a bad file
    stops the run before the first question, not in the middle."""
    try:
        data = path.read_bytes()
        prepare_image(data, max_side_px, max_bytes)
    except (OSError, ImageError) as exc:
        raise EvalVLMError(f"{path}: not a usable photo: {exc}") from None
    return data


@dataclass(frozen=True, eq=False)
class Plan:
    """Everything decided before the first question: the sets, templates and jobs."""

    config: EvalVLMConfig
    sets: tuple[UnseenSet, ...]
    conditions: tuple[Condition, ...]
    templates: dict[str, PromptTemplate]
    jobs: tuple[Job, ...]
    images: str


def prepare(cfg: EvalVLMConfig, endpoint: bool = True) -> Plan:
    """Load the model and test sets, retrieve, render every prompt: no network yet."""
    cfg.validate(endpoint)
    conditions = tuple(CONDITIONS[name] for name in cfg.conditions)
    model = load_model(cfg.model_dir)
    sets = load_sets(cfg.unseen, cfg.limit, model.window)
    tactile: dict[str, Tactile] = {}
    if any(c.variant == "vq" for c in conditions):
        tactile["vq"] = vq_tactile(model)
    checkpoints = {"beta": cfg.beta, "vq_zeros": cfg.zeros}
    for variant in CHECKPOINT_VARIANTS:
        if any(c.variant == variant for c in conditions):
            path = checkpoints[variant]
            assert path is not None and cfg.reference is not None
            tactile[variant] = checkpoint_tactile(variant, path, cfg.reference, model.window)
            _check_same_references(model.database, tactile[variant].database)
    templates = {c.mode: load_template(c.mode, cfg.vlm.prompt_dir) for c in conditions}
    images = ImageSource(cfg.images, cfg.vlm)
    jobs = build_jobs(sets, [(c, tactile.get(c.variant or "")) for c in conditions],
                      templates, images, cfg.vlm.model)
    return Plan(cfg, sets, conditions, templates, tuple(jobs), images.name)


def load_sets(unseen: Sequence[Path], limit: int | None, spec: Any) -> tuple[UnseenSet, ...]:
    sets = tuple(load_test_set(d, limit, spec) for d in unseen)
    names = [s.name for s in sets]
    if len(set(names)) != len(names):
        raise EvalVLMError(f"two unseen sets share a name: {', '.join(names)}")
    return sets


def build_jobs(sets: Sequence[UnseenSet],
               conditions: Sequence[tuple[Condition, Tactile | None]],
               templates: Mapping[str, PromptTemplate], images: ImageSource,
               model: str) -> list[Job]:
    """One question per press of every set and (condition, tactile source), in plan order
    (set, press, condition)."""
    with_image = any(templates[c.mode].uses_image for c, _ in conditions)
    jobs: list[Job] = []
    for ts in sets:
        x = ts.presses.inputs(0)  # the one input the robot computes
        retrieved: dict[int, list[list[tuple[str, float]]]] = {}
        for cond, source in conditions:
            if cond.variant is not None:
                if source is None:
                    raise EvalVLMError(f"{cond.name}: no tactile model given")
                if id(source) not in retrieved:
                    k = max(c.k for c, s in conditions if s is source)
                    retrieved[id(source)] = source.topk(x, k)
        for i, (press, label) in enumerate(zip(ts.press_ids, ts.presses.labels, strict=True)):
            image = images.get(ts.name, press, label, ts.directory / press) \
                if with_image else None
            for cond, source in conditions:
                template = templates[cond.mode]
                topk: tuple[tuple[str, float], ...] = ()
                description = ""
                if cond.variant is not None:
                    assert source is not None
                    topk = tuple(retrieved[id(source)][i][:cond.k])
                    description = describe(cond, source.database, [lab for lab, _ in topk])
                sent = image if template.uses_image else None
                assert not template.uses_image or sent is not None
                jobs.append(Job(
                    condition=cond, dataset=ts.name, press=press, label=label,
                    candidates=ts.candidates, topk=topk, description=description,
                    prompt=template.render(description, ts.candidates), image=sent,
                    image_sha256=sha256_hex(sent) if sent is not None else None,
                    model=model))
    return jobs


def _check_same_references(vq: ReferenceDatabase, other: ReferenceDatabase) -> None:
    if sorted(vq.source.tolist()) != sorted(other.source.tolist()) or vq.labels != other.labels:
        log.warning("the database built from --reference holds other presses or classes "
                    "than the shipped VQ database: the comparison with the shipped model is "
                    "not like for like")


# --------------------------------------------------------------------------------------
# The answer cache


class AnswerCache:
    """``answers.jsonl``: one JSON record per line, keyed by ``record["key"]``.

    An append is one ``write`` of one whole line to a file opened with ``O_APPEND``, then an
    fsync: a crash leaves at most a torn last line, which :meth:`load` drops (and cuts off,
    so the next append starts a clean line). Thread-safe (appends come from worker threads).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self.records: dict[str, dict[str, Any]] = {}

    def load(self) -> dict[str, dict[str, Any]]:
        self.records = {}
        if not self.path.exists():
            return self.records
        data = self.path.read_bytes()
        end = data.rfind(b"\n") + 1
        if end < len(data):
            log.warning("%s: dropping a torn last line (%d bytes) left by an interrupted run",
                        self.path, len(data) - end)
            with open(self.path, "r+b") as fh:
                fh.truncate(end)
                fh.flush()
                os.fsync(fh.fileno())
        bad = 0
        for line in data[:end].splitlines():
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
                key = rec["key"]
                rec["answer"]["status"]
            except (ValueError, KeyError, TypeError):
                bad += 1
                continue
            self.records.setdefault(key, rec)  # the first answer of a key wins
        if bad:
            log.warning("%s: ignored %d unreadable line(s)", self.path, bad)
        return self.records

    def append(self, record: Mapping[str, Any]) -> None:
        line = (json.dumps(record, ensure_ascii=False, separators=(",", ":")) + "\n"
                ).encode("utf-8")
        with self._lock:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                view = memoryview(line)
                while view:
                    written = os.write(fd, view)
                    view = view[written:]
                os.fsync(fd)
            finally:
                os.close(fd)
            self.records.setdefault(record["key"], dict(record))


# --------------------------------------------------------------------------------------
# Asking


class EvalProgress:
    """Progress on stderr (:mod:`edge.core.progress`): a tqdm bar on a terminal, else a
    whole line every few seconds."""

    def __init__(self, total: int, cached: int, stream: TextIO | None = None,
                 enabled: bool = True, every_s: float = PLAIN_EVERY_S) -> None:
        self.total, self.cached = total, cached
        self.asked = self.invalid = 0
        self.started = time.monotonic()
        self.bar = Bar("eval-vlm", total, "answers", stream=stream, every_s=every_s,
                       enabled=enabled, initial=cached)

    def note(self) -> str:
        done = self.cached + self.asked
        text = f"{self.cached} cached, {self.asked} asked, {self.invalid} invalid"
        if self.asked:
            rate = (time.monotonic() - self.started) / self.asked
            text += f", {rate:.2f} s per answer, ~{rate * (self.total - done) / 60:.1f} min left"
        return text

    def update(self, answer: VLMAnswer | None = None, final: bool = False) -> None:
        if answer is not None:
            self.asked += 1
            self.invalid += answer.status == INVALID
            self.bar.update(1, self.note())
        if final:
            self.bar.close(self.note())


async def ask_all(plan: Plan, cache: AnswerCache, *,
                  clients: Mapping[str, VLMClient] | None = None,
                  progress: EvalProgress | None = None) -> int:
    """Ask every job not in ``cache`` (in plan order, ``concurrency`` at a time); returns
    the number asked. The first failure (server unreachable after retries, a refused
    request) stops the run; the answers already cached stay for the next run."""
    cfg = plan.config
    cached = cache.records or cache.load()
    # One question per key: two jobs with the same key (the same prompt and photo) share
    # their answer at temperature 0.
    todo = list({job.key: job for job in plan.jobs if job.key not in cached}.values())
    unique = len({job.key for job in plan.jobs})
    progress = progress or EvalProgress(unique, unique - len(todo), enabled=False)
    if not todo:
        progress.update(final=True)
        return 0
    session: aiohttp.ClientSession | None = None
    owned: list[VLMClient] = []
    if clients is None:
        session = aiohttp.ClientSession(
            connector=aiohttp.TCPConnector(limit=cfg.concurrency), trust_env=False)
        clients = {}
        for mode, template in plan.templates.items():
            client = OpenAIVLM(dataclasses.replace(cfg.vlm, mode=mode), template=template,
                               session=session)
            clients[mode] = client
            owned.append(client)
    pending = iter(todo)
    asked = 0

    async def worker() -> None:
        nonlocal asked
        for job in pending:  # shared: each worker takes the next job in plan order
            try:
                answer = await clients[job.condition.mode].ask(
                    job.image, job.description, job.candidates)
            except (EdgeError, ValueError) as exc:
                raise EvalVLMError(
                    f"{job.dataset}/{job.press} ({job.condition.name}): {exc}") from exc
            if answer.prompt != job.prompt:  # the client renders the same template
                raise EvalVLMError(f"{job.key}: the client rendered another prompt")
            write = asyncio.ensure_future(asyncio.to_thread(cache.append, job.record(answer)))
            try:
                await asyncio.shield(write)
            except asyncio.CancelledError:
                await write  # a cancelled run still finishes the line it is writing
                raise
            asked += 1
            progress.update(answer)

    try:
        async with asyncio.TaskGroup() as tg:
            for i in range(min(cfg.concurrency, len(todo))):
                tg.create_task(worker(), name=f"eval-vlm-worker-{i}")
    except BaseExceptionGroup as group:
        first = _first_error(group)
        if isinstance(first, EvalVLMError):
            keys = {j.key for j in plan.jobs}
            missing = len(keys - set(cache.records))
            raise EvalVLMError(f"stopped: {first}; {missing} of {len(keys)} answers "
                               f"still missing (cached in {cache.path}: run the same "
                               "command again to continue)") from first.__cause__
        raise
    finally:
        for client in owned:
            await client.close()
        if session is not None:
            await session.close()
    progress.update(final=True)
    return asked


def _first_error(group: BaseExceptionGroup) -> BaseException:
    for exc in group.exceptions:
        if isinstance(exc, BaseExceptionGroup):
            return _first_error(exc)
        return exc
    return group


# --------------------------------------------------------------------------------------
# The report


def summarise(plan: Plan, records: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Accuracy, invalid answers and confusion per dataset and condition (every job must
    have its answer in ``records``)."""
    missing = [job.key for job in plan.jobs if job.key not in records]
    if missing:
        raise EvalVLMError(f"{len(missing)} answers missing (first: {missing[0]})")
    results: dict[str, dict[str, Any]] = {}
    presses: dict[tuple[str, str], dict[str, Any]] = {}
    for ts in plan.sets:
        results[ts.name] = {}
        for cond in plan.conditions:
            columns = [*ts.candidates, INVALID]
            matrix = np.zeros((len(ts.candidates), len(columns)), dtype=np.int64)
            results[ts.name][cond.name] = {"matrix": matrix, "columns": columns}
    for job in plan.jobs:
        answer = records[job.key]["answer"]
        label = answer.get("label")
        if answer.get("status") != "ok" or label not in job.candidates:
            label = None
        row = results[job.dataset][job.condition.name]
        col = job.candidates.index(label) if label is not None else len(job.candidates)
        row["matrix"][job.candidates.index(job.label), col] += 1
        entry = presses.setdefault((job.dataset, job.press), {
            "dataset": job.dataset, "press": job.press, "label": job.label, "answers": {}})
        entry["answers"][job.condition.name] = {
            "label": label, "status": answer.get("status"), "correct": label == job.label,
            "topk": [lab for lab, _ in job.topk], "attempts": answer.get("attempts")}
    out: dict[str, Any] = {}
    for name, conds in results.items():
        out[name] = {}
        for cond_name, r in conds.items():
            m = r["matrix"]
            n = int(m.sum())
            correct = int(np.trace(m[:, :-1]))
            invalid = int(m[:, -1].sum())
            out[name][cond_name] = {
                "accuracy": correct / n if n else None, "correct": correct, "n": n,
                "invalid_answer": invalid, "valid": n - invalid,
                "confusion": {"rows": list(r["columns"][:-1]), "columns": r["columns"],
                              "matrix": m.tolist()}}
    cfg = plan.config
    return {
        "protocol": "Table I: one query per press (offset-0 input), candidates = the set's "
                    "labels, temperature 0; invalid answers count as wrong",
        "model": cfg.vlm.model, "base_url": cfg.vlm.base_url, "seed": cfg.vlm.seed,
        "model_dir": str(cfg.model_dir), "images": plan.images, "limit": cfg.limit,
        "conditions": [dataclasses.asdict(c) for c in plan.conditions],
        "prompts": {mode: {"source": t.source, "sha256": sha256_hex(t.text.encode("utf-8"))}
                    for mode, t in plan.templates.items()},
        "datasets": [{"name": ts.name, "directory": str(ts.directory),
                      "candidates": list(ts.candidates), "presses": len(ts.press_ids),
                      "origin": ts.origin, "paper_set": paper_set(ts.name, cfg.paper_sets)}
                     for ts in plan.sets],
        "results": out,
        "presses": list(presses.values()),
    }


def _pct(r: Mapping[str, Any]) -> str:
    if not r["n"]:
        return "n/a"
    return f"{100 * r['accuracy']:.1f} % ({r['correct']}/{r['n']})"


def markdown(report: Mapping[str, Any]) -> str:
    sets = [d["name"] for d in report["datasets"]]
    beside = {d["name"]: d.get("paper_set") for d in report["datasets"]}
    titles = [set_title(s, {k: v for k, v in beside.items() if v}) for s in sets]
    conds = report["conditions"]
    head = ["| method | " + " | ".join(titles) + " |", "| --- |" + " --- |" * len(sets)]
    lines = [
        "# VLM evaluation (the paper's Table I protocol)",
        "",
        f"VLM `{report['model']}` at `{report['base_url']}` (temperature 0, seed "
        f"{report['seed']}); tactile model `{report['model_dir']}`; images: "
        f"{report['images']}; one query per press (offset-0 input); candidates: the set's "
        "labels" + (f"; first {report['limit']} presses per set (round-robin over classes)"
                    if report["limit"] else "") + ".",
        "",
        "Accuracy (correct / presses):",
        "",
        *head,
    ]
    for c in conds:
        lines.append(f"| {c['title']} | " + " | ".join(
            _pct(report["results"][s][c["name"]]) for s in sets) + " |")
    lines += ["", "Invalid answers (not a candidate even after the corrective retry; counted "
              "as wrong, never mapped to a label):", "", *head]
    for c in conds:
        lines.append(f"| {c['title']} | " + " | ".join(
            str(report["results"][s][c["name"]]["invalid_answer"]) for s in sets) + " |")
    paper_rows = [c for c in conds if c["name"] in PAPER]
    paper_sets = [beside[s] for s in sets if beside.get(s)]
    if paper_rows and paper_sets:
        lines += ["", "The paper (GPT-4V, real objects), for comparison:", "",
                  "| method | " + " | ".join(DATASET_TITLES[s] for s in paper_sets) + " |",
                  "| --- |" + " --- |" * len(paper_sets)]
        for c in paper_rows:
            lines.append(f"| {c['title']} | " + " | ".join(
                f"{PAPER[c['name']][s]:.1f} %" for s in paper_sets) + " |")
    lines += ["", "The presses: " + "; ".join(
        f"{d['name']}: {describe_origin(d.get('origin'))}" for d in report["datasets"])
        + "."]
    lines += ["", "Answers are a strict JSON enum of the candidates (a label is always a "
              "candidate, or `invalid_answer`); the paper's GPT-4V and LLaVA answered in free "
              "text.", "", "Prompt templates: " + ", ".join(
        f"`{mode}` sha256 {p['sha256'][:12]}" for mode, p in report["prompts"].items())
        + ". Confusion matrices: `eval_vlm.json`, `confusion_<set>.png`.", ""]
    return "\n".join(lines)


def confusion_png(report: Mapping[str, Any], dataset: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conds = report["conditions"]
    ncols = min(2, len(conds))
    nrows = -(-len(conds) // ncols)
    n = len(next(d for d in report["datasets"] if d["name"] == dataset)["candidates"])
    side = 2.5 + 0.28 * n
    fig, axes = plt.subplots(nrows, ncols, figsize=(side * ncols, side * nrows),
                             squeeze=False)
    for ax in axes.flat[len(conds):]:
        ax.axis("off")
    for ax, cond in zip(axes.flat, conds, strict=False):
        r = report["results"][dataset][cond["name"]]
        conf = r["confusion"]
        m = np.asarray(conf["matrix"])
        ax.imshow(m, cmap="Blues", vmin=0, vmax=max(1, int(m.max())))
        ax.set_xticks(range(len(conf["columns"])), conf["columns"], rotation=90, fontsize=6)
        ax.set_yticks(range(len(conf["rows"])), conf["rows"], fontsize=6)
        ax.axvline(len(conf["rows"]) - 0.5, color="0.4", lw=0.8)
        if n <= 8:
            for (i, j), v in np.ndenumerate(m):
                if v:
                    ax.text(j, i, str(v), ha="center", va="center", fontsize=7,
                            color="white" if v > m.max() / 2 else "black")
        ax.set_xlabel("answer", fontsize=7)
        ax.set_ylabel("true class", fontsize=7)
        ax.set_title(f"{textwrap.fill(cond['title'], 40)}\n{_pct(r)}, "
                     f"{r['invalid_answer']} invalid",
                     fontsize=8)
    simulated = " (simulated VLM, no real model)" if str(report["model"]).startswith(
        "simulated-vlm") else ""
    fig.suptitle(f"{DATASET_TITLES.get(dataset, dataset)}: VLM {report['model']}{simulated}",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97))  # room for the title
    save_png(fig, path)
    plt.close(fig)


# Colours kept in a saved figure: a confusion matrix of 22 classes x 6 conditions is 300 kB
# in full colour and under a third of that in this many, with no visible difference.
PNG_COLOURS = 64


def save_png(fig: Any, path: Path, dpi: int = DPI) -> None:
    """A figure as a palette PNG, written atomically (the reports ship in models/)."""
    from PIL import Image

    from edge.core.atomic import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    buf.seek(0)
    with Image.open(buf) as img:
        small = img.convert("RGB").quantize(PNG_COLOURS, method=Image.Quantize.MEDIANCUT)
        out = io.BytesIO()
        small.save(out, format="PNG", optimize=True)
    atomic_write_bytes(path, out.getvalue())


def write_report(plan: Plan, records: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    out = plan.config.out
    report = summarise(plan, records)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / REPORT_JSON, json.dumps(report, indent=1) + "\n")
    atomic_write_text(out / REPORT_MD, markdown(report))
    for ts in plan.sets:
        confusion_png(report, ts.name, out / f"confusion_{slug(ts.name)}.png")
    return report


async def run(cfg: EvalVLMConfig, *, progress: bool = True, stream: TextIO | None = None,
              clients: Mapping[str, VLMClient] | None = None) -> dict[str, Any]:
    """Prepare (off the loop), ask what is not cached, write the report."""
    plan = await asyncio.to_thread(prepare, cfg)
    cache = AnswerCache(cfg.out / ANSWERS_FILE)
    await asyncio.to_thread(cache.load)
    keys = {job.key for job in plan.jobs}
    cached = len(keys & set(cache.records))
    log.info("%d questions (%d sets x %d conditions); %d already answered in %s",
             len(keys), len(plan.sets), len(plan.conditions), cached, cache.path)
    bar = EvalProgress(len(keys), cached, stream, enabled=progress)
    await ask_all(plan, cache, clients=clients, progress=bar)
    return await asyncio.to_thread(write_report, plan, cache.records)


def describe_plan(plan: Plan, records: Iterable[str] = ()) -> str:
    """A dry run: what would be asked, and the first prompt of each condition."""
    keys = set(records)
    lines = [f"{len(plan.jobs)} questions, {sum(j.key in keys for j in plan.jobs)} cached; "
             f"images: {plan.images}"]
    for ts in plan.sets:
        lines.append(f"  {ts.name}: {len(ts.press_ids)} presses, {len(ts.candidates)} "
                     "candidates")
    for cond in plan.conditions:
        job = next(j for j in plan.jobs if j.condition is cond)
        lines += [f"--- {cond.name} ({cond.title}), e.g. {job.dataset}/{job.press}:",
                  job.prompt]
    return "\n".join(lines)

