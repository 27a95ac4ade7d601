"""``vt-train build``: one command from a collected dataset to a deployable model directory.

``vt-train release`` regenerates the shipped model from the *simulated* reference set; this
builds one from a lab's own presses (a ``vt-edge collect`` dataset directory: ``dataset.json``
with the classes, their split, description, ``x_th`` and the data's ``origin``, and
``<label>/<label>_NNN.press.npz``), or from another sensor's labelled sequences (a directory
of ``*.seq.npz``, :mod:`train.learn.sequences`; a ``dataset.json`` beside them is optional:
without one the classes split by name, :func:`train.learn.data.sequence_splits`): the
window is cut at the sequences' own rate and the model takes their channels, and the
manifest says so (``sequences``: the robot's runtime refuses such a model, ``vt-train eval``
reads it). Steps, each kept in ``OUT.partial`` with the hash of its
inputs, so a rerun after an interruption skips what is done and says so:

1. check the presses: one threshold and one origin (recording source and sensor model) per
   class, every reference class present (refused, naming the class and the presses); every
   class at one stream rate (within ``preprocess.RATE_TOLERANCE``: a class pressed at
   100 frames/s embeds elsewhere than one at 125), unless ``--mixed-rates``; sequences: one
   rate and one channel count in all;
2. choose the embedding to deploy by held-out evidence (step "choose"): the candidates
   ``shipped`` (the VQ-VAE with the paper's decoder, z of 16 and the metric term),
   ``paper`` (the same in the paper's configuration: z of 4, reconstruction only) and
   ``mean`` (the trivial feature, each channel's mean over the window after the normaliser:
   nothing to train) are trained over ``--seeds`` seeds and scored by how often the
   validation classes' presses have their own class nearest (leave one press out, among every
   reference press; the unseen top-3 consistency breaks a tie). The best challenger replaces
   the shipped network only where its lead is beyond the noise: its lowest seed above the
   network's highest, and the lead above the binomial standard error of that figure at its
   widest, 1 / (2 sqrt(validation presses)): a tiny set's choice would otherwise turn on one
   press and on training that is not bit-for-bit repeatable. ``eval.md`` says what won, by
   how much, and whether beyond the noise. ``--embedding NAME`` deploys that
   one and trains nothing else. Then the deployed network is trained (the first seed's
   training is the choice's own, kept) and, with ``--variant``, the beta-VAE and the
   zero-input decoder for the comparison rows of the evaluation and of Table I;
3. export the encoder: a network to ONNX with its parity check, ``mean`` to ``encoder.npz``
   (the normaliser's statistics; the manifest's ``encoder.kind``);
4. the database of every offset of every press of the train and val classes;
5. the prompt templates copied (the manifest hashes them);
6. the retrieval evaluation (``eval/eval.md``, ``eval/eval.json``), the trivial baseline beside
   the encoder, on the test classes of the dataset and any ``--unseen`` sets;
7. the manifest, written last, with the data's ``origin``, ``plan_sha256``, each class's
   ``x_th`` and stream rate (``class_x_th``, ``class_rate_hz``) and the normaliser's floor
   (``training.std_floor_fraction``, ``--std-floor``);

then ``OUT.partial`` is renamed to ``OUT`` (an ``OUT`` already there is kept as
``OUT.previous``). The daemon loads the result as it is; SIGHUP swaps it in.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from edge.core import preprocess
from edge.core.atomic import atomic_write_bytes, atomic_write_text, swap_in
from edge.core.errors import ModelError, RecordingError
from edge.core.layout import XR1944, PadLayout
from edge.core.model import (
    DATABASE_ARRAYS,
    DATABASE_INDEX,
    ENCODER_FILES,
    MEAN_ENCODER_FILE,
    SEQUENCES,
    MeanEncoder,
    OnnxEncoder,
    Origin,
)
from edge.core.recording import DATASET_INDEX
from edge.core.recording import find as find_recordings
from train.eval import evaluate
from train.learn import sequences
from train.learn.data import (
    STD_FLOOR_FRACTION,
    Normaliser,
    PressSet,
    Splits,
    load_presses,
    sequence_splits,
    training_data_of,
)
from train.learn.model import PAPER, ModelConfig
from train.learn.trainer import CHECKPOINT, Progress, TrainConfig, embed, load_checkpoint
from train.learn.trainer import train as train_model
from train.ship import database
from train.ship.export import check_parity, codebook_of, export_onnx, parity
from train.ship.manifest import PROMPTS_DIR, dumps, versions, write_manifest
from train.ship.release import (
    EVAL_DIR,
    encode_timing,
    encoder_section,
    prompt_hashes,
    window_section,
)

log = logging.getLogger(__name__)

PARTIAL_SUFFIX = ".partial"
STATE_FILE = "build-state.json"
TRAINING_DIR = "training"
SHIPPED_PROMPTS = Path(__file__).resolve().parents[2] / "models" / PROMPTS_DIR
# The comparison variants `--variant` adds: name -> what changes from the shipped VQ-VAE.
VARIANTS = {"beta": {"variant": "beta"}, "zeros": {"decoder": "zeros"}, "paper": PAPER}
# Checkpoint directories under training/, as release names them (vt-train table1 --beta/--zeros).
VARIANT_DIRS = {"vq": "vq", "beta": "beta", "zeros": "vq_zeros", "paper": "vq_paper"}
# The embeddings a build can deploy (--embedding): name -> the network trained for it (None:
# the trivial feature, nothing to train).
EMBEDDINGS = {"shipped": "vq", "paper": "paper", "mean": None}
MEAN_ROW = "mean"  # the evaluation's row of the deployed trivial feature
CHOICE_DIR = "choice"  # under OUT: the choice's evaluations (and its further seeds' training)
# The choice's figure, and the one that breaks a tie (evaluate's row keys).
CHOICE_METRIC = ("loo_1nn_val_classes", "validation classes' LOO 1-NN")
CHOICE_TIE = ("top3_consistency", "unseen top-3 consistency")
SHIPPED = "shipped"  # the embedding a challenger must beat beyond the noise to replace


@dataclass(frozen=True)
class BuildConfig:
    data: Path
    out: Path
    variants: tuple[str, ...] = ()  # comparison variants: beta, zeros, paper
    unseen: tuple[Path, ...] = ()  # further test sets for the evaluation
    prompts: Path = SHIPPED_PROMPTS
    seed: int = 0
    max_epochs: int = 300
    patience: int = 25
    threads: int = 1
    mixed_rates: bool = False  # build from classes pressed at different stream rates
    std_floor: float = STD_FLOOR_FRACTION  # the normaliser's (train.learn.data)
    embedding: str | None = None  # what the model deploys (EMBEDDINGS); None: choose
    seeds: int = 1  # seeds of each candidate the choice is made over

    def command(self) -> str:
        parts = [f"vt-train build --data {self.data} --out {self.out}",
                 *([f"--embedding {self.embedding}"] if self.embedding else
                   [f"--seeds {self.seeds}"]),
                 *(f"--variant {v}" for v in self.variants),
                 *(["--mixed-rates"] if self.mixed_rates else []),
                 *([f"--std-floor {self.std_floor:g}"]
                   if self.std_floor != STD_FLOOR_FRACTION else []),
                 *(f"--unseen {u}" for u in self.unseen),
                 f"--seed {self.seed}", f"--max-epochs {self.max_epochs}",
                 f"--patience {self.patience}"]
        return " ".join(parts)


# --------------------------------------------------------------------------------------
# The dataset


@dataclass(frozen=True)
class Dataset:
    directory: Path
    index: dict[str, Any]
    origin: dict[str, Any]
    splits: Splits
    test: tuple[str, ...]  # test classes of the dataset (the evaluation's unseen presses)
    x_th: dict[str, float]  # per class, as pressed
    presses: dict[str, int]  # per class
    sha256: str  # of dataset.json and every press file
    layout: PadLayout = XR1944  # the pads every press was made with
    rate_hz: dict[str, float | None] = field(default_factory=dict)  # per class, as pressed
    # The reference presses by content (database.press_digests).
    press_sha256: dict[str, str] = field(default_factory=dict)
    # Where the model's input is cut, at the data's rate.
    window: preprocess.WindowSpec = preprocess.DEFAULT_WINDOW
    # Another sensor's sequences: their rate and channels (the manifest's ``sequences``);
    # None for the robot's own presses.
    sequences: dict[str, Any] | None = None

    @property
    def channels(self) -> int:
        return self.layout.channels if self.sequences is None else self.sequences["channels"]


def read_dataset(directory: str | Path, progress: bool = True, mixed_rates: bool = False
                 ) -> Dataset:
    """Read and check a collected dataset directory; refuse mixed thresholds or origins within
    a class, naming the class and its presses, and classes at different stream rates unless
    ``mixed_rates``."""
    directory = Path(directory)
    path = directory / DATASET_INDEX
    if directory.is_dir() and sequences.find(directory):
        if find_recordings(directory):
            raise RecordingError(f"{directory}: holds both the robot's press recordings "
                                 f"and other sensors' sequences ({sequences.SUFFIX}): a model "
                                 "is built from one sensor's presses; move one kind out")
        return read_sequences(directory)
    try:
        index = json.loads(path.read_text())
    except OSError as exc:
        raise RecordingError(f"{path}: {exc.strerror or exc} (a dataset directory written by "
                             "`vt-edge collect --plan`)") from None
    except json.JSONDecodeError as exc:
        raise RecordingError(f"{path}: not valid JSON: {exc}") from None
    if index.get("origin") is None:
        log.warning("%s has no 'origin': taken as pressed by the emulated robot", path)
    try:  # the manifest's own reader: one definition of a well-formed origin
        origin = Origin.of_dataset(index, str(path)).to_json()
    except ModelError as exc:
        raise RecordingError(str(exc)) from None
    unlabelled = [i for i, c in enumerate(index.get("classes", []))
                  if not isinstance(c, dict) or not isinstance(c.get("label"), str)
                  or not c["label"]]
    if unlabelled:
        raise RecordingError(f"{path}: classes[{unlabelled[0]}] has no 'label' (each class "
                             "needs one: the name of its presses' directory)")
    splits = Splits.from_file(path)
    declared = {c["label"]: c.get("x_th") for c in index.get("classes", [])}
    test = tuple(c["label"] for c in index.get("classes", []) if c.get("split") == "test")
    metas = database.press_index(directory, progress)
    digest = hashlib.sha256(path.read_bytes())
    for meta in metas:
        digest.update(meta.path.relative_to(directory).as_posix().encode())
        digest.update(hashlib.sha256(meta.path.read_bytes()).digest())
    thresholds = database.grouped(metas, "x_th")
    origins = database.grouped(metas, "origin")
    problems = []
    for label in splits.classes + test:
        if label not in thresholds:
            problems.append(f"class {label!r} has no presses in {directory}")
            continue
        mix = [database.mixed(label, "thresholds x_th", thresholds[label]),
               database.mixed(label, "origins", origins[label])]
        problems += [m for m in mix if m]
        x_th = next(iter(thresholds[label]))
        if not mix[0] and declared.get(label) is not None and x_th != round(
                declared[label], database.X_TH_DIGITS):
            problems.append(f"class {label!r}: presses at x_th {x_th:g} but dataset.json "
                            f"says {declared[label]:g}")
    layouts = database.grouped(metas, "layout")
    mixed_pads = {lay for per_label in layouts.values() for lay in per_label}
    if len(mixed_pads) > 1:
        problems.append("presses of different pads: " + "; ".join(
            f"{lay.channels} channels, {lay.text()} (class "
            f"{', '.join(label for label, per in layouts.items() if lay in per)})"
            for lay in sorted(mixed_pads, key=lambda lay: lay.channels)))
    if problems:
        raise RecordingError(f"{directory}: " + "; ".join(problems)
                             + " (re-collect the class, or move the odd presses out)")
    rates = database.class_rates(metas)
    rate_mix = database.rate_mix({c: rates.get(c) for c in splits.classes + test})
    if rate_mix and not mixed_rates:
        raise RecordingError(f"{directory}: {rate_mix}: the crop interpolates each from a "
                             "different number of frames (docs/method.md); re-collect the odd "
                             f"classes at the others' rate ({preprocess.RATE_SETTING}), or say "
                             "--mixed-rates to build from them anyway")
    if rate_mix:
        log.warning("--mixed-rates: %s", rate_mix)
    return Dataset(directory, index, origin, splits, test,
                   {c: next(iter(t)) for c, t in thresholds.items()},
                   {c: sum(map(len, t.values())) for c, t in thresholds.items()},
                   digest.hexdigest(), next(iter(mixed_pads), XR1944), rates,
                   database.press_digests(m for m in metas if m.label in splits.classes))


def read_sequences(directory: Path) -> Dataset:
    """Read and check a directory of another sensor's sequences: one rate and one channel
    count in all (the model's window is cut at that rate), splits and descriptions from a
    ``dataset.json`` beside them if there is one, else by name (:func:`sequence_splits`)."""
    path = directory / DATASET_INDEX
    if path.exists():
        try:
            index = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise RecordingError(f"{path}: cannot read: {exc}") from None
        splits = Splits.from_file(path)
        test = tuple(c["label"] for c in index.get("classes", []) if c.get("split") == "test")
    else:
        splits, test = sequence_splits(directory), ()
        log.info("%s has no %s: classes split by name, train %s, val %s (write one to split "
                 "or describe them otherwise)", directory, DATASET_INDEX,
                 ", ".join(splits.train), ", ".join(splits.val))
        index = {"dataset": directory.name, "recorder": f"sequences ({sequences.SUFFIX})",
                 "classes": [{"label": c, "split": "train" if c in splits.train else "val",
                              "description": splits.descriptions[c]} for c in splits.classes]}
    digest = hashlib.sha256(path.read_bytes() if path.exists() else b"")
    seqs = []
    for file in sequences.find(directory):
        digest.update(file.relative_to(directory).as_posix().encode())
        digest.update(hashlib.sha256(file.read_bytes()).digest())
        seqs.append(sequences.load(file))
    kinds: dict[tuple[float, int], list[str]] = {}
    for seq in seqs:
        kinds.setdefault((seq.rate_hz, seq.samples.shape[1]), []).append(seq.label)
    if len(kinds) > 1:
        raise RecordingError(f"{directory}: sequences at different rates or channel counts: "
                             + "; ".join(f"{rate:g} Hz x {channels} channels (class "
                                         f"{', '.join(dict.fromkeys(labels))})"
                                         for (rate, channels), labels in kinds.items())
                             + ": a model is cut at one rate from one sensor's channels")
    (rate, channels), = kinds
    counts = {c: sum(seq.label == c for seq in seqs) for c in splits.classes + test}
    missing = [c for c, n in counts.items() if not n]
    if missing:
        raise RecordingError(f"{directory}: no sequences of class {', '.join(missing)}")
    origin = index.get("origin") or {
        "kind": "robot", "recorder": f"another sensor's sequences ({sequences.SUFFIX}) in "
        f"{directory}", "robot": None, "sensor": None}
    try:
        origin = Origin.from_json(origin, str(path)).to_json()
    except ModelError as exc:
        raise RecordingError(str(exc)) from None
    return Dataset(
        directory, index, origin, splits, test, {}, counts, digest.hexdigest(),
        rate_hz={c: rate for c in counts},
        press_sha256={hashlib.sha256(seq.samples.tobytes()).hexdigest():
                      f"{seq.label}/{Path(seq.path).name}" for seq in seqs
                      if seq.label in splits.classes},
        window=preprocess.DEFAULT_WINDOW.at_rate(rate),
        sequences={"rate_hz": rate, "channels": channels, "format": sequences.SUFFIX})


# --------------------------------------------------------------------------------------
# Steps kept between runs


def _key(*parts: Any) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class Steps:
    """``OUT.partial/build-state.json``: each finished step's input hash and result."""

    def __init__(self, work: Path) -> None:
        self.path = work / STATE_FILE
        self.state: dict[str, Any] = {}
        if self.path.exists():
            try:
                self.state = json.loads(self.path.read_text())
            except (OSError, ValueError) as exc:
                log.warning("%s: unreadable (%s): every step runs again", self.path, exc)
            if not isinstance(self.state, dict):
                log.warning("%s: not an object: every step runs again", self.path)
                self.state = {}
        self.skipped: list[str] = []
        self.ran: list[str] = []

    def run(self, name: str, key: str, outputs: list[Path],
            fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        done = self.state.get(name)
        if done and done.get("key") == key and all(p.exists() for p in outputs):
            log.info("step %s: done already (same inputs), skipped", name)
            self.skipped.append(name)
            return done["result"]
        log.info("step %s ...", name)
        started = time.perf_counter()
        result = fn()
        result["seconds"] = round(time.perf_counter() - started, 2)
        self.state[name] = {"key": key, "result": result}
        atomic_write_text(self.path, dumps(self.state))
        self.ran.append(name)
        return result


# --------------------------------------------------------------------------------------
# The build


def partial_dir(out: Path) -> Path:
    return out.with_name(out.name + PARTIAL_SUFFIX)


@dataclass
class Job:
    """One build under way: what it reads, where it writes, what each step gave."""

    cfg: BuildConfig
    ds: Dataset
    work: Path
    steps: Steps
    unseen: PressSet | None  # the evaluation's test presses
    unseen_key: str
    model_config: ModelConfig
    progress: Progress | None
    embedding: str  # the embedding deployed: the one asked for, or the choice's winner
    _reference: PressSet | None = None

    def reference(self) -> PressSet:
        """The train and val classes' presses, loaded once, when a step first needs them."""
        if self._reference is None:
            self._reference = load_presses(self.ds.directory, self.ds.splits.classes)
        return self._reference

    @property
    def network(self) -> str | None:
        """The trained network the model deploys (a VARIANTS name), None for ``mean``."""
        return EMBEDDINGS[self.embedding]

    @property
    def encoder(self) -> Path:
        return self.work / ENCODER_FILES["onnx" if self.network else "mean"]

    @property
    def row(self) -> str:
        """The deployed embedding's row in the evaluation."""
        return VARIANT_DIRS[self.network] if self.network else MEAN_ROW

    def checkpoint(self, name: str, seed_index: int = 0) -> Path:
        """A network's checkpoint; the choice's further seeds are kept apart."""
        where = self.work / TRAINING_DIR
        if seed_index:
            where = where / CHOICE_DIR / f"seed{seed_index}"
        return where / VARIANT_DIRS[name] / CHECKPOINT


def build(cfg: BuildConfig, progress: Progress | None = None) -> dict[str, Any]:
    """Build ``cfg.out`` from ``cfg.data``; returns the manifest written."""
    started = time.perf_counter()
    prompts = _check_request(cfg)
    ds = read_dataset(cfg.data, progress=progress is None or progress.enabled,
                      mixed_rates=cfg.mixed_rates)
    job = _start(cfg, ds, progress)
    choice = _choose(job) if cfg.embedding is None else None
    if choice is not None:
        job.embedding = choice["winner"]
    trained = _train(job)
    exported = _export(job)
    db_summary = _database(job)
    _copy_prompts(job.work, prompts)
    metrics = _evaluate(job, trained, choice)
    manifest = write_manifest(
        job.work, _manifest_sections(job, trained, exported, db_summary, metrics, started),
        reports=[f"{EVAL_DIR}/{name}" for name in evaluate.FILES])
    swap_in(job.work, Path(cfg.out))
    log.info("model written to %s in %.0f s (steps run: %s; skipped: %s)", cfg.out,
             time.perf_counter() - started, ", ".join(job.steps.ran) or "none",
             ", ".join(job.steps.skipped) or "none")
    return manifest


def _check_request(cfg: BuildConfig) -> list[Path]:
    """Refuse unknown variants and a prompt directory without templates; the templates."""
    if cfg.seeds < 1:
        raise ValueError(f"--seeds must be at least 1, got {cfg.seeds}")
    if cfg.embedding is not None and cfg.embedding not in EMBEDDINGS:
        raise ValueError(f"unknown embedding {cfg.embedding!r}; choose from "
                         f"{', '.join(EMBEDDINGS)}")
    unknown = [v for v in cfg.variants if v not in VARIANTS]
    if unknown:
        raise ValueError(f"unknown variant {', '.join(unknown)}; choose from "
                         f"{', '.join(VARIANTS)}")
    prompts = sorted(Path(cfg.prompts).glob("*.txt"))
    if not prompts:
        raise ModelError(f"{cfg.prompts}: no prompt templates (*.txt); the daemon needs them "
                         "(--prompts DIR)")
    return prompts


def _start(cfg: BuildConfig, ds: Dataset, progress: Progress | None) -> Job:
    """``OUT.partial`` with the steps kept so far, and the evaluation's test presses."""
    out = Path(cfg.out)
    work = partial_dir(out)
    if not work.exists() and (out / STATE_FILE).exists():
        # A finished build's steps are the cache of the next one.
        shutil.copytree(out, work, symlinks=True)
    work.mkdir(parents=True, exist_ok=True)
    unseen_sets = [load_presses(ds.directory, ds.test)] if ds.test else []
    unseen_sets += [load_presses(u) for u in cfg.unseen]
    unseen = PressSet.concat(*unseen_sets) if unseen_sets else None
    unseen_key = _key(ds.test, [(str(p), _sha(Path(p))) for p in unseen.paths]
                      if unseen else [])
    # The model takes the channels the presses were made with, in the steps of their window.
    model_config = replace(ModelConfig(), channels=ds.channels, steps=ds.window.n_steps)
    return Job(cfg, ds, work, Steps(work), unseen, unseen_key, model_config, progress,
               cfg.embedding or "shipped")


def _train(job: Job, names: tuple[str, ...] | None = None, seed_index: int = 0
           ) -> dict[str, dict[str, Any]]:
    """Step "train NAME": the deployed network, then each comparison variant asked for (or
    the networks ``names`` at the ``seed_index``-th seed, for the choice)."""
    cfg = job.cfg
    base = TrainConfig(seed=cfg.seed + seed_index, max_epochs=cfg.max_epochs,
                       patience=cfg.patience, threads=cfg.threads)
    trained: dict[str, dict[str, Any]] = {}
    if names is None:
        names = tuple(dict.fromkeys(((job.network,) if job.network else ()) + cfg.variants))
    for name in names:
        config = replace(base, model=replace(job.model_config, **VARIANTS.get(name, {})))
        where = job.checkpoint(name, seed_index).parent

        def fit(config: TrainConfig = config, where: Path = where) -> dict[str, Any]:
            data = training_data_of(job.reference(), job.ds.splits, cfg.std_floor)
            result = train_model(data, config, where, job.progress)
            return {"config": config.to_dict(), "result": result.summary()}

        # The default floor keeps the key builds made before the floor was a setting.
        floor = [] if cfg.std_floor == STD_FLOOR_FRACTION else [cfg.std_floor]
        step = f"train {name}" + (f" seed {seed_index}" if seed_index else "")
        trained[name] = job.steps.run(
            step, _key(job.ds.sha256, config.to_dict(), *floor),
            [job.checkpoint(name, seed_index)], fit) | {
            "checkpoint": job.checkpoint(name, seed_index).relative_to(job.work).as_posix()}
    return trained


def _choose(job: Job) -> dict[str, Any]:
    """Step "choose": every candidate over ``--seeds`` seeds, scored on the validation
    classes (and the unseen classes' consistency for a tie); the winner and the figures."""
    cfg = job.cfg
    if not job.ds.splits.val:  # said before any training
        raise _no_validation_class()
    networks = tuple(n for n in EMBEDDINGS.values() if n)
    trained = [_train(job, networks, i) for i in range(cfg.seeds)]

    def choose() -> dict[str, Any]:
        norm = Normaliser.fit(job.reference().select(job.ds.splits.train).x, cfg.std_floor)
        mean = MeanEncoder(MeanEncoder.to_bytes(norm.mean, norm.std),
                           job.reference().x.shape[2])
        scores: dict[str, dict[str, list[float]]] = {
            name: {CHOICE_METRIC[0]: [], CHOICE_TIE[0]: []} for name in EMBEDDINGS}
        for i, runs in enumerate(trained):
            embedders: dict[str, tuple[evaluate.Embedder, np.ndarray | None]] = {}
            for name, network in EMBEDDINGS.items():
                if network is None:
                    embedders[name] = ((lambda x: (mean(x)[0], None)), None)
                    continue
                model, n, _ = load_checkpoint(job.work / runs[network]["checkpoint"])
                embedders[name] = ((lambda x, m=model, n=n: (embed(m, n, x)[0], None)), None)
            report = evaluate.evaluate(embedders, job.reference(), job.ds.splits, job.unseen,
                                       job.work / CHOICE_DIR / f"seed{i}",
                                       primary=(next(iter(EMBEDDINGS)), "z"),
                                       seed=cfg.seed + i)
            rows = {r["variant"]: r for r in report["rows"]}
            for name in EMBEDDINGS:
                for key in scores[name]:
                    value = rows[name].get(key)
                    if value is not None and math.isfinite(value):  # nan: not measured
                        scores[name][key].append(float(value))
        return choice_of(scores, cfg.seeds,
                         sum(job.ds.presses[c] for c in job.ds.splits.val))

    shas = [{n: _sha(job.work / t["checkpoint"]) for n, t in runs.items()} for runs in trained]
    return job.steps.run("choose", _key(job.ds.sha256, job.unseen_key, shas, cfg.std_floor),
                         [], choose)


def noise_floor(presses: int) -> float:
    """The binomial standard error of a share of ``presses`` at its widest (a share of 1/2):
    the least lead on ``CHOICE_METRIC`` that is more than one press's luck."""
    return 0.5 / math.sqrt(presses)


def choice_of(scores: dict[str, dict[str, list[float]]], seeds: int, presses: int
              ) -> dict[str, Any]:
    """The embedding to deploy from each candidate's ``CHOICE_METRIC`` over the seeds, on
    ``presses`` validation presses. The best challenger (by the mean, ``CHOICE_TIE`` then
    the candidates' order breaking a tie) replaces the shipped network only where its lead is
    beyond the noise: its lowest seed above the network's highest and the lead above
    :func:`noise_floor`. Returned: the winner, the runner-up, the margin between them, the
    challenger's lead, whether the winner's lowest seed is above the runner-up's highest
    (``beyond_spread``) and whether the shipped network was kept though behind."""
    # None where the figure was not measured (no validation or no unseen classes).
    figures = {name: {key: {"mean": float(np.mean(v)), "min": min(v), "max": max(v),
                            "seeds": v} if v else None
                      for key, v in by.items()} for name, by in scores.items()}
    order = list(EMBEDDINGS)

    def rank(name: str) -> tuple[float, float, int]:
        metric, tie = (figures[name][key] for key in (CHOICE_METRIC[0], CHOICE_TIE[0]))
        return (metric["mean"] if metric else -1.0, tie["mean"] if tie else -1.0,
                -order.index(name))

    challenger = max((n for n in EMBEDDINGS if n != SHIPPED), key=rank)
    c, s = figures[challenger][CHOICE_METRIC[0]], figures[SHIPPED][CHOICE_METRIC[0]]
    if c is None or s is None or presses < 1:
        raise _no_validation_class()
    lead, floor = c["mean"] - s["mean"], noise_floor(presses)
    replaces = lead > floor and c["min"] > s["max"]
    winner, runner = (challenger, SHIPPED) if replaces else (SHIPPED, challenger)
    w, r = figures[winner][CHOICE_METRIC[0]], figures[runner][CHOICE_METRIC[0]]
    one_seed = seeds < 2
    return {"winner": winner, "runner_up": runner, "metric": CHOICE_METRIC[0],
            "tie_break": CHOICE_TIE[0], "seeds": seeds, "margin": w["mean"] - r["mean"],
            "challenger": challenger, "lead": lead, "noise_floor": floor,
            "validation_presses": presses,
            "beyond_spread": bool(w["min"] > r["max"] and not one_seed),
            "kept_within_noise": not replaces and lead > 0,
            "one_seed": one_seed, "figures": figures}


def _no_validation_class() -> ModelError:
    return ModelError(f"the choice of embedding needs {CHOICE_METRIC[1]}: the dataset has no "
                      "validation class (split val); add one, or name the embedding "
                      "(--embedding)")


def choice_markdown(choice: dict[str, Any]) -> str:
    """``eval.md``'s section on the choice: what won, by how much, beyond the noise or not."""
    metric, tie = CHOICE_METRIC[1], CHOICE_TIE[1]
    figures, winner, runner = choice["figures"], choice["winner"], choice["runner_up"]

    def cell(f: dict[str, Any] | None) -> str:
        if f is None:
            return "n/a"
        return f"{f['mean']:.3f}" if f["min"] == f["max"] else \
            f"{f['mean']:.3f} ({f['min']:.3f}-{f['max']:.3f})"

    seeds = choice["seeds"]
    noise = (f"the seed spread, and the binomial standard error of {choice['validation_presses']}"
             f" validation presses at its widest, {choice['noise_floor']:.3f}")
    lines = ["", "## The embedding deployed", "",
             f"Chosen by {metric} (each validation-class press's nearest reference press, "
             f"its own press left out; {tie} breaks a tie) over {seeds} seed"
             f"{'s' * (seeds != 1)} (`vt-train build --seeds N`; `--embedding NAME` deploys "
             f"one without the choice). A challenger replaces `{SHIPPED}` only with a lead "
             f"beyond the noise: {noise}.", "",
             f"| candidate | {metric} | {tie} |", "| --- | --- | --- |"]
    for name, f in figures.items():
        mark = " (deployed)" if name == winner else ""
        lines.append(f"| {name}{mark} | {cell(f[CHOICE_METRIC[0]])} | "
                     f"{cell(f[CHOICE_TIE[0]])} |")
    if choice["beyond_spread"]:
        spread = "beyond the seed spread"
    elif choice["one_seed"]:
        spread = "one seed, so no spread to judge it by (--seeds)"
    else:
        spread = "inside the seed spread: this data does not tell them apart"
    if winner != SHIPPED:
        verdict = (f"`{winner}` replaced `{SHIPPED}`, {choice['margin']:.3f} above it on "
                   f"{metric}: beyond the noise (above {choice['noise_floor']:.3f}; "
                   + ("one seed, no spread measured: --seeds N" if choice["one_seed"] else
                      "its lowest seed above the network's highest") + ").")
    elif choice["kept_within_noise"]:
        verdict = (f"`{choice['challenger']}` led `{SHIPPED}` by {choice['lead']:.3f} on "
                   f"{metric}, within the noise: kept the shipped network.")
    else:
        verdict = f"`{winner}` won, {choice['margin']:.3f} above `{runner}` on {metric}: {spread}."
    lines += ["", verdict]
    return "\n".join(lines) + "\n"


def _export(job: Job) -> dict[str, Any]:
    """Step "export": the deployed network's encoder to ONNX, parity-checked on the real
    presses; for ``mean``, the normaliser fitted on the train classes to ``encoder.npz``."""
    # An encoder of the other kind left by an earlier build of this directory goes.
    for other in set(ENCODER_FILES.values()) - {job.encoder.name}:
        (job.work / other).unlink(missing_ok=True)
    if job.network is None:
        return _export_mean(job)

    def export() -> dict[str, Any]:
        model, norm, _ = load_checkpoint(job.checkpoint(job.network))
        onnx_bytes = export_onnx(model, norm, job.encoder)
        real = job.reference().inputs(0)
        if job.unseen is not None:
            real = np.concatenate([real, job.unseen.inputs(0)])
        par = parity(model, norm, onnx_bytes, real, seed=job.cfg.seed)
        check_parity(par)
        return {"parity": par.to_dict(), "timing": encode_timing(onnx_bytes, real)}

    return job.steps.run("export", _key(_sha(job.checkpoint(job.network))), [job.encoder],
                         export)


def _export_mean(job: Job) -> dict[str, Any]:
    """The trivial feature's encoder: the statistics a network's normaliser would have."""
    cfg = job.cfg

    def export() -> dict[str, Any]:
        train_x = job.reference().select(job.ds.splits.train).x
        norm = Normaliser.fit(train_x, cfg.std_floor)
        data = MeanEncoder.to_bytes(norm.mean, norm.std)
        atomic_write_bytes(job.encoder, data)
        real = job.reference().inputs(0)
        return {"norm": norm.to_dict(),
                "timing": encode_timing(MeanEncoder(data, real.shape[1]), real)}

    return job.steps.run("export", _key(job.ds.sha256, "mean", cfg.std_floor), [job.encoder],
                         export)


def _encoder(job: Job) -> OnnxEncoder | MeanEncoder:
    """The deployed encoder as the robot loads it."""
    data = job.encoder.read_bytes()
    if job.network is None:
        return MeanEncoder(data, job.reference().x.shape[2])
    return OnnxEncoder(data)


def _database(job: Job) -> dict[str, Any]:
    """Step "database": every offset of every train and val press, encoded by the graph."""
    def build_db() -> dict[str, Any]:
        db = database.build_database(job.encoder.read_bytes(), job.reference(),
                                     job.ds.splits, kind="onnx" if job.network else "mean")
        db.save(job.work)
        return database.summary(db) | {"codes_used": len(np.unique(db.code))}

    return job.steps.run("database", _key(_sha(job.encoder), job.ds.sha256),
                         [job.work / DATABASE_ARRAYS, job.work / DATABASE_INDEX], build_db)


def _copy_prompts(work: Path, prompts: list[Path]) -> None:
    shutil.rmtree(work / PROMPTS_DIR, ignore_errors=True)  # none left from another --prompts
    (work / PROMPTS_DIR).mkdir()
    for template in prompts:
        shutil.copyfile(template, work / PROMPTS_DIR / template.name)


def _evaluate(job: Job, trained: dict[str, dict[str, Any]], choice: dict[str, Any] | None
              ) -> dict[str, Any]:
    """Step "eval": retrieval through the deployed encoder and each variant's checkpoint,
    the trivial baseline beside them; with a choice made, what won and by how much."""
    work = job.work

    def run_eval() -> dict[str, Any]:
        encoder = _encoder(job)
        embedders: dict[str, tuple[evaluate.Embedder, np.ndarray | None]] = {}
        if isinstance(encoder, MeanEncoder):
            embedders[job.row] = ((lambda x: (encoder(x)[0], None)), None)
        else:
            codebook = codebook_of(job.encoder.read_bytes())
            embedders[job.row] = (evaluate.onnx_embedder(encoder, codebook), codebook)
        for name in job.cfg.variants:
            if name == job.network:
                continue
            model, norm, _ = load_checkpoint(work / trained[name]["checkpoint"])
            book = None if model.quantiser is None else \
                model.quantiser.codebook.detach().numpy().copy()
            embedders[VARIANT_DIRS[name]] = (
                (lambda x, m=model, n=norm: embed(m, n, x)), book)
        report = evaluate.evaluate(embedders, job.reference(), job.ds.splits, job.unseen,
                                   work / EVAL_DIR, primary=(job.row, "z"), seed=job.cfg.seed)
        if choice is not None:
            md = work / EVAL_DIR / "eval.md"
            atomic_write_text(md, md.read_text() + choice_markdown(choice))
        return evaluate.summary_metrics(report) | ({"choice": choice} if choice else {})

    variant_shas = {name: _sha(work / t["checkpoint"]) for name, t in trained.items()}
    return job.steps.run(
        "eval", _key(_sha(job.encoder), job.ds.sha256, job.unseen_key, variant_shas, choice),
        [work / EVAL_DIR / name for name in evaluate.FILES], run_eval)


def _manifest_sections(job: Job, trained: dict[str, dict[str, Any]], exported: dict[str, Any],
                       db_summary: dict[str, Any], metrics: dict[str, Any], started: float
                       ) -> dict[str, Any]:
    """What the manifest says of the build: the data, the training, the evaluation."""
    cfg, ds = job.cfg, job.ds
    sections: dict[str, Any] = {
        "created_by": cfg.command(),
        "origin": ds.origin,
        database.CLASS_X_TH: {c: ds.x_th[c] for c in ds.splits.classes if c in ds.x_th},
        database.CLASS_RATE_HZ: {c: ds.rate_hz.get(c) for c in ds.splits.classes},
        database.PRESS_SHA256: ds.press_sha256,
        "encoder": _encoder_section(job, exported),
        "training": {
            "dataset": {"simulated": ds.origin["kind"] == "emulated",
                        "directory": str(ds.directory), "sha256": ds.sha256,
                        "name": ds.index.get("dataset"), "recorder": ds.index.get("recorder"),
                        "train_classes": list(ds.splits.train),
                        "val_classes": list(ds.splits.val), "test_classes": list(ds.test),
                        "presses": ds.presses, "x_th": ds.x_th, "rate_hz": ds.rate_hz,
                        "mixed_rates": cfg.mixed_rates},
            "std_floor_fraction": cfg.std_floor,
            **{VARIANT_DIRS[name]: t for name, t in trained.items()},
        },
        "evaluation": {"unseen": [str(ds.directory)] * bool(ds.test)
                       + [str(u) for u in cfg.unseen], "report": f"{EVAL_DIR}/eval.md"},
        "database": {k: v for k, v in db_summary.items() if k not in ("codes_used", "seconds")},
        "prompts": prompt_hashes(job.work),
        "metrics": metrics,
        "timings": exported["timing"] | {"build_s": time.perf_counter() - started,
                                         "steps_skipped": job.steps.skipped},
        "versions": versions(),
    }
    # Both keys written either way (null, not absent): the manifest merges into what OUT.partial
    # holds, so a key an earlier build of the other kind left there would otherwise stay.
    if ds.sequences is None:
        sections |= {SEQUENCES: None,
                     "sensor_layout": {"pads": ds.layout.pads, "taxels_per_pad": ds.layout.taxels,
                                       "taxel_rows": ds.layout.rows}}
    else:
        sections |= {SEQUENCES: ds.sequences, "sensor_layout": None}
    if ds.index.get("plan_sha256"):
        sections["plan_sha256"] = ds.index["plan_sha256"]
    return sections


def _encoder_section(job: Job, exported: dict[str, Any]) -> dict[str, Any]:
    """The manifest's ``encoder``, with its ``kind`` (``onnx`` or ``mean``); another sensor's
    sequences: their window and units."""
    section = _encoder_of_kind(job, exported)
    if job.ds.sequences is not None:
        section |= {"window": {k: getattr(job.ds.window, k) for k in window_section()},
                    "input_units": f"the sensor's own units, as in its {sequences.SUFFIX} "
                                   "files (train.learn.sequences)"}
    return section


def _encoder_of_kind(job: Job, exported: dict[str, Any]) -> dict[str, Any]:
    if job.network is not None:
        config = replace(job.model_config, **VARIANTS.get(job.network, {}))
        return {"kind": "onnx", "embedding": job.embedding} | encoder_section(
            load_checkpoint(job.checkpoint(job.network))[1], config, exported["parity"])
    norm = Normaliser.from_dict(exported["norm"])
    steps, channels = job.model_config.steps, job.model_config.channels
    return {
        "kind": "mean", "embedding": job.embedding, "file": MEAN_ENCODER_FILE,
        "input": "x", "input_shape": ["batch", steps, channels],
        "input_units": "tactile units (raw - tare) / 65536, edge.core.preprocess.model_input",
        "normalisation": "(x - mean) / std, per channel, training stats, then the mean over "
                         "the window: z is each channel's mean (edge.core.model.MeanEncoder)",
        "mean": norm.mean.tolist(), "std": norm.std.tolist(),
        "outputs": {"z": ["batch", channels], "code": ["batch"]},
        "embedding_dim": channels, "codebook_size": 0,
        "window": window_section(),
    }


def checkpoints(model_dir: str | Path) -> dict[str, Path]:
    """The comparison checkpoints a build kept (``beta``, ``vq_zeros``), for Table I."""
    root = Path(model_dir) / TRAINING_DIR
    return {name: root / name / CHECKPOINT for name in ("beta", "vq_zeros")
            if (root / name / CHECKPOINT).exists()}

