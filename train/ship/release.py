"""``vt-train release``: regenerate the shipped ``models/`` from the simulated reference set.

One deterministic pipeline for a seed: record (reference, FoodReplica, Cube; reused when the
work directory already holds the same recording of the same catalogue classes) -> train the
VQ-VAE (the paper's decoder, the shipped configuration of :mod:`train.learn.model`), the paper's
configuration of it (``vq_paper``), the VQ-VAE with the zero-input decoder and the beta-VAE
(all three for the comparison) -> export the VQ encoder to ONNX (parity-checked) -> build
the database with the ONNX encoder (every offset of every reference press) -> evaluate ->
copy into ``out`` -> write ``manifest.json`` last. ``out/prompts/`` belongs to the prompt templates:
never written here, only hashed into the manifest as found (``files``, and ``prompts`` with
each template's slots).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from edge.core.atomic import atomic_write_bytes
from edge.core.model import (
    ENCODER_FILE,
    MANIFEST,
    REQUIRED_FILES,
    MeanEncoder,
    OnnxEncoder,
    Origin,
    ReferenceDatabase,
)
from edge.core.preprocess import DEFAULT_WINDOW
from edge.core.recording import DATASET_INDEX
from edge.sim.catalogue import DATASETS
from edge.vlm.prompt import MODES, PromptTemplate
from train.eval import evaluate
from train.learn.data import (
    STD_FLOOR_FRACTION,
    Normaliser,
    PressSet,
    TrainingData,
    load_presses,
    training_data,
)
from train.learn.model import PAPER, ModelConfig
from train.learn.trainer import Progress, TrainConfig, TrainResult, embed, train
from train.ship import database
from train.ship.export import (
    OPSET,
    PARITY_BOUND,
    Parity,
    check_parity,
    codebook_of,
    export_onnx,
    parity,
)
from train.ship.manifest import versions, write_manifest

log = logging.getLogger(__name__)

EVAL_DIR = "eval"


@dataclass(frozen=True)
class ReleaseConfig:
    out: Path = Path("models")
    work: Path = Path("runs/release")
    recordings: Path | None = None  # default: work/recordings (reused when it matches)
    seed: int = 0
    presses: int = 10  # per reference class
    unseen_presses: int = 10  # per FoodReplica / Cube class
    max_epochs: int = 300
    patience: int = 25
    threads: int = 1
    beta: bool = True  # also train the beta-VAE for the comparison table
    zeros: bool = True  # also train the VQ-VAE with the zero-input decoder (comparison)
    paper: bool = True  # also train the paper's configuration (model.PAPER) (comparison)
    workers: int | None = None  # recorder processes
    std_floor: float = STD_FLOOR_FRACTION  # the normaliser's (train.learn.data)

    def command(self) -> str:
        parts = ["vt-train release", f"--out {self.out}", f"--seed {self.seed}",
                 f"--presses {self.presses}", f"--unseen-presses {self.unseen_presses}",
                 f"--max-epochs {self.max_epochs}", f"--patience {self.patience}"]
        if not self.beta:
            parts.append("--no-beta")
        if not self.zeros:
            parts.append("--no-zeros")
        if not self.paper:
            parts.append("--no-paper")
        if self.std_floor != STD_FLOOR_FRACTION:
            parts.append(f"--std-floor {self.std_floor:g}")
        return " ".join(parts)


def _same_classes(meta: dict[str, Any], dataset: str) -> bool:
    """Whether a recorded ``dataset.json`` was made by the robot's press controller (the
    recorder names itself) for the catalogue's classes as they are now (labels, splits,
    descriptions, per-class thresholds): anything else means recording again."""
    if not meta.get("recorder"):
        return False  # an older recorder's data: another press protocol
    from edge.lab.record import DEFAULT_TRANSPORT, PADS_AGE_MEAN_S

    if meta.get("transport") != asdict(DEFAULT_TRANSPORT):
        return False  # pressed with another stop latency than the daemon's today
    if meta.get("pads_age_mean_s") != PADS_AGE_MEAN_S:
        return False  # pressed on pads of another age (their drift ramp)
    have = meta.get("classes", [])
    if [(c.get("label"), c.get("split"), c.get("description")) for c in have] != [
            (o.name, o.split, o.description) for o in DATASETS[dataset]]:
        return False
    return all(o.x_th is None or c.get("x_th") == o.x_th
               for c, o in zip(have, DATASETS[dataset], strict=True))


def _recorded(directory: Path, dataset: str, presses: int, seed: int, workers: int | None
              ) -> bool:
    """Record ``dataset`` into ``directory`` unless it already holds it; True if reused."""
    index = directory / DATASET_INDEX
    if index.exists():
        meta = json.loads(index.read_text())
        if (meta.get("dataset"), meta.get("presses_per_class"), meta.get("seed")) == (
                dataset, presses, seed) and _same_classes(meta, dataset):
            log.info("reusing %s recordings in %s", dataset, directory)
            return True
        shutil.rmtree(directory)
    # The recorder loads the press controller and the virtual robot: only when recording.
    from edge.lab.record import record_dataset

    log.info("recording %s: %d presses per class (seed %d)", dataset, presses, seed)
    record_dataset(dataset, presses, directory, seed=seed, workers=workers)
    return False


def encode_timing(encoder: bytes | MeanEncoder, x: np.ndarray, repeats: int = 200
                  ) -> dict[str, float]:
    """Median wall time of one single-sequence encode: an ONNX graph's bytes with the robot's
    session options, or the trivial feature's encoder."""
    if isinstance(encoder, bytes):
        encoder = OnnxEncoder(encoder)
    one = x[:1]
    for _ in range(10):
        encoder(one)
    times = []
    for i in range(repeats):
        t0 = time.perf_counter()
        encoder(x[i % len(x):i % len(x) + 1])
        times.append(time.perf_counter() - t0)
    return {"encode_ms_median": 1e3 * float(np.median(times)),
            "encode_ms_p90": 1e3 * float(np.percentile(times, 90))}


def prompt_hashes(model_dir: Path) -> dict[str, Any]:
    """Each shipped prompt template's sha256 and slots (the manifest's ``prompts``), so an
    evaluation names the exact wording it was asked with."""
    out: dict[str, Any] = {}
    for mode in MODES:
        path = Path(model_dir) / "prompts" / f"{mode}.txt"
        if not path.is_file():
            continue
        data = path.read_bytes()
        template = PromptTemplate(mode, data.decode("utf-8"), str(path))
        out[mode] = {"file": f"prompts/{mode}.txt",
                     "sha256": hashlib.sha256(data).hexdigest(),
                     "slots": sorted(template.slots)}
    return out


def window_section() -> dict[str, Any]:
    """The manifest's ``encoder.window``: where the model's input is cut around the stop."""
    return {k: getattr(DEFAULT_WINDOW, k) for k in
            ("rate_hz", "before_s", "after_s", "subsample", "sigma_samples")}


def encoder_section(norm: Normaliser, model: ModelConfig, par: dict[str, Any]
                    ) -> dict[str, Any]:
    """The manifest's ``encoder``: what the exported graph takes and gives, and its parity."""
    return {
        "file": ENCODER_FILE, "input": "x", "input_shape": ["batch", model.steps, model.channels],
        "input_units": "tactile units (raw - tare) / 65536, edge.core.preprocess.model_input",
        "normalisation": "inside the graph: (x - mean) / std, per channel, training stats",
        "mean": norm.mean.tolist(), "std": norm.std.tolist(),
        "outputs": {"z": ["batch", model.latent], "code": ["batch"]},
        "embedding_dim": model.latent,
        "codebook_size": model.codebook_size,
        "window": window_section(),
        "opset": OPSET, "exporter": "torch.onnx.export(dynamo=False)",
        "parity": par | {"bound": PARITY_BOUND},
    }


@dataclass(frozen=True)
class Recordings:
    """The release's three recorded sets, and whether all were found already recorded."""

    reference: Path
    foodreplica: Path
    cube: Path
    reused: bool


@dataclass(frozen=True)
class Trainings:
    """The shipped VQ-VAE and the comparison models asked for (None: not trained)."""

    vq: TrainResult
    paper: TrainResult | None
    zeros: TrainResult | None
    beta: TrainResult | None


def release(cfg: ReleaseConfig, progress: Progress | None = None) -> dict[str, Any]:
    """Record, train, export (parity checked), build the database, evaluate, copy into
    ``cfg.out``, write the manifest last; returns the manifest."""
    started = time.perf_counter()
    rec = record(cfg)
    t_rec = time.perf_counter() - started
    data = training_data(rec.reference, floor_fraction=cfg.std_floor)
    runs = train_all(cfg, data, progress)

    stage = Path(cfg.work) / "stage"
    if stage.exists():
        shutil.rmtree(stage)
    stage.mkdir(parents=True)
    unseen = PressSet.concat(load_presses(rec.foodreplica), load_presses(rec.cube))
    real = np.concatenate([data.presses.inputs(0), unseen.inputs(0)])
    onnx_bytes, par = export_checked(runs.vq, data, real, stage, cfg.seed)
    db = database.build_database(onnx_bytes, data.presses, data.splits)
    db.save(stage)
    report = evaluate.evaluate(embedders(onnx_bytes, runs), data.presses, data.splits, unseen,
                               stage / EVAL_DIR, seed=cfg.seed)
    timings = encode_timing(onnx_bytes, real)

    out = Path(cfg.out)
    copy_out(stage, out)
    ref_index = json.loads((rec.reference / DATASET_INDEX).read_text())
    metrics = evaluate.summary_metrics(report) | training_metrics(runs) | {
        "codes_used_by_references": len(np.unique(db.code))}
    timings |= {"record_s": t_rec, "recordings_reused": rec.reused} | training_timings(runs) | {
        "release_s": time.perf_counter() - started}
    sections = manifest_sections(cfg, data, runs, par, db, ref_index, rec.reference, out) | {
        "metrics": metrics, "timings": timings, "versions": versions()}
    manifest = write_manifest(out, sections,
                              reports=[f"{EVAL_DIR}/{name}" for name in evaluate.FILES])
    log.info("release written to %s (%s) in %.0f s", out, MANIFEST, timings["release_s"])
    return manifest


def record(cfg: ReleaseConfig) -> Recordings:
    """The reference, FoodReplica and Cube sets, recorded unless already there."""
    work = Path(cfg.work)
    rec_dir = Path(cfg.recordings) if cfg.recordings is not None else work / "recordings"
    ref_dir, fr_dir, cube_dir = (rec_dir / "reference", rec_dir / "foodreplica",
                                 rec_dir / "cube")
    reused = all([
        _recorded(ref_dir, "reference", cfg.presses, cfg.seed, cfg.workers),
        _recorded(fr_dir, "foodreplica", cfg.unseen_presses, cfg.seed, cfg.workers),
        _recorded(cube_dir, "cube", cfg.unseen_presses, cfg.seed, cfg.workers)])
    return Recordings(ref_dir, fr_dir, cube_dir, reused)


def train_all(cfg: ReleaseConfig, data: TrainingData, progress: Progress | None) -> Trainings:
    """The shipped VQ-VAE, then the comparisons: the paper's configuration, the zero-input
    decoder and the beta-VAE, each where asked."""
    work = Path(cfg.work)
    base = TrainConfig(seed=cfg.seed, max_epochs=cfg.max_epochs, patience=cfg.patience,
                       threads=cfg.threads)
    vq = train(data, base, work / "vq", progress)
    paper = train(data, replace(base, model=ModelConfig(**PAPER)), work / "vq_paper",
                  progress) if cfg.paper else None
    zeros = train(data, replace(base, model=ModelConfig(decoder="zeros")), work / "vq_zeros",
                  progress) if cfg.zeros else None
    beta = train(data, replace(base, model=ModelConfig(variant="beta")), work / "beta",
                 progress) if cfg.beta else None
    return Trainings(vq, paper, zeros, beta)


def export_checked(vq: TrainResult, data: TrainingData, real: np.ndarray, stage: Path,
                   seed: int) -> tuple[bytes, Parity]:
    """The VQ encoder exported to ONNX in ``stage``, its parity with torch checked on the
    ``real`` inputs (the reference and unseen presses)."""
    onnx_bytes = export_onnx(vq.model, data.norm, stage / ENCODER_FILE)
    par = parity(vq.model, data.norm, onnx_bytes, real, seed=seed)
    check_parity(par)
    log.info("ONNX parity: max |dz| %.3g over %d inputs, %d code mismatches",
             par.max_abs_z, par.cases, par.code_mismatches)
    return onnx_bytes, par


def embedders(onnx_bytes: bytes, runs: Trainings
              ) -> dict[str, tuple[evaluate.Embedder, np.ndarray | None]]:
    """What the evaluation compares: the shipped ONNX encoder and each comparison model
    (torch), with its codebook (None: the beta-VAE has none)."""
    paper, zeros, beta = runs.paper, runs.zeros, runs.beta
    codebook = codebook_of(onnx_bytes)
    out: dict[str, tuple[evaluate.Embedder, np.ndarray | None]] = {
        "vq": (evaluate.onnx_embedder(OnnxEncoder(onnx_bytes), codebook), codebook)}
    if paper is not None:
        assert paper.model.quantiser is not None
        out["vq_paper"] = ((lambda x: embed(paper.model, paper.norm, x)),
                           paper.model.quantiser.codebook.detach().numpy().copy())
    if zeros is not None:
        assert zeros.model.quantiser is not None
        out["vq_zeros"] = ((lambda x: embed(zeros.model, zeros.norm, x)),
                           zeros.model.quantiser.codebook.detach().numpy().copy())
    if beta is not None:
        out["beta"] = ((lambda x: embed(beta.model, beta.norm, x)), None)
    return out


def copy_out(stage: Path, out: Path) -> None:
    """The model files and the evaluation's reports from ``stage`` into ``out``, each written
    atomically (the manifest comes last, from :func:`release`)."""
    out.mkdir(parents=True, exist_ok=True)
    names = [*REQUIRED_FILES, *(f"{EVAL_DIR}/{name}" for name in evaluate.FILES)]
    for name in names:
        atomic_write_bytes(out / name, (stage / name).read_bytes())


def training_metrics(runs: Trainings) -> dict[str, Any]:
    vq, paper, zeros, beta = runs.vq, runs.paper, runs.zeros, runs.beta
    return {
        "vq_epochs": vq.epochs, "vq_best_epoch": vq.best_epoch,
        "vq_best_val_loss": vq.best_val,
        "vq_paper_best_epoch": paper.best_epoch if paper else None,
        "vq_paper_best_val_loss": paper.best_val if paper else None,
        "vq_zeros_best_epoch": zeros.best_epoch if zeros else None,
        "vq_zeros_best_val_loss": zeros.best_val if zeros else None,
        "beta_best_epoch": beta.best_epoch if beta else None,
        "beta_best_val_loss": beta.best_val if beta else None,
        "dead_codes_at_best": vq.summary()["dead_codes_at_best"],
    }


def training_timings(runs: Trainings) -> dict[str, float | None]:
    return {"train_vq_s": runs.vq.seconds,
            "train_vq_paper_s": runs.paper.seconds if runs.paper else None,
            "train_vq_zeros_s": runs.zeros.seconds if runs.zeros else None,
            "train_beta_s": runs.beta.seconds if runs.beta else None}


def manifest_sections(cfg: ReleaseConfig, data: TrainingData, runs: Trainings, par: Parity,
                      db: ReferenceDatabase, ref_index: dict[str, Any], ref_dir: Path, out: Path
                      ) -> dict[str, Any]:
    """The manifest's sections that describe the model: how it was made, its encoder, its
    training, evaluation and database, the prompts beside it and its origin."""
    vq, paper, zeros, beta = runs.vq, runs.paper, runs.zeros, runs.beta
    return {
        "created_by": cfg.command(),
        "encoder": encoder_section(data.norm, vq.config.model, par.to_dict()),
        "training": {
            "dataset": {"simulated": True, "seed": ref_index["seed"],
                        "presses_per_class": ref_index["presses_per_class"],
                        "train_classes": list(data.splits.train),
                        "val_classes": list(data.splits.val),
                        "train_samples": len(data.train), "val_samples": len(data.val),
                        "recorder": ref_index["recorder"], "press": ref_index["press"],
                        "transport": ref_index["transport"]},
            "vq": {"config": vq.config.to_dict(), "result": vq.summary()},
            "vq_paper": {"config": paper.config.to_dict(), "result": paper.summary()}
            if paper else None,
            "vq_zeros": {"config": zeros.config.to_dict(), "result": zeros.summary()}
            if zeros else None,
            "beta": {"config": beta.config.to_dict(), "result": beta.summary()} if beta else None,
            "normalisation_floor": f"per-channel std floored at {cfg.std_floor:g} x the "
                                   "RMS of the channel stds",
        },
        "evaluation": {"unseen": {"foodreplica_presses_per_class": cfg.unseen_presses,
                                  "cube_presses_per_class": cfg.unseen_presses},
                       "report": f"{EVAL_DIR}/eval.md"},
        "database": database.summary(db),
        database.CLASS_X_TH: {c["label"]: c["x_th"] for c in ref_index["classes"]},
        database.CLASS_RATE_HZ: {c["label"]: c.get("rate_hz") for c in ref_index["classes"]},
        # So that `vt-train db add` knows the shipped references' presses by content too.
        database.PRESS_SHA256: database.press_digests(
            m for m in database.press_index(ref_dir)
            if m.label in {c.label for c in db.classes}),
        "prompts": prompt_hashes(out),
        # The release always presses its references on the emulated robot; a lab's own
        # database comes from its robot (`vt-edge collect`, `vt-train build`).
        "origin": Origin("emulated", ref_index["recorder"]).to_json(),
    }
