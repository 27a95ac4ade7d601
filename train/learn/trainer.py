"""Training: Adam (lr 0.01), batch 256, early stopping on the validation loss.

The best model (lowest validation loss) is kept in memory and written atomically to
``checkpoint.pt`` whenever it improves; training ends after ``patience`` epochs without an
improvement of at least ``min_delta`` (relative) and returns the best model. Every epoch
appends one JSON line to ``train.jsonl`` (losses, code usage, time); stderr gets a progress
bar on a terminal, else a whole line every few seconds (:mod:`edge.core.progress`), so CI
logs stay short.

Deterministic on CPU for a seed and thread count: the shuffles come from a seeded numpy
generator, the beta-VAE noise and the revival of dead codes from seeded torch generators, and
``torch.use_deterministic_algorithms`` is on.
"""

from __future__ import annotations

import io
import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import torch

from edge.core.atomic import atomic_write_bytes
from edge.core.errors import ModelError
from edge.core.progress import PLAIN_EVERY_S
from edge.core.progress import Progress as Bar
from train.learn.data import Normaliser, Samples, TrainingData
from train.learn.model import METRIC_MARGIN, ModelConfig, TactileAutoencoder, set_determinism

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.pt"
TRAIN_LOG = "train.jsonl"
CHECKPOINT_FORMAT = "vtzero-checkpoint-1"


@dataclass(frozen=True)
class TrainConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    seed: int = 0
    lr: float = 0.01
    batch_size: int = 256
    max_epochs: int = 300
    patience: int = 25
    min_delta: float = 1e-3  # relative improvement of the validation loss that counts
    threads: int = 1
    grad_clip: float = 1.0  # max gradient norm (GRUs at lr 0.01 spike now and then)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        d = dict(d)
        d["model"] = ModelConfig.from_dict(d.get("model", {}))
        return cls(**d)


@dataclass
class TrainResult:
    model: TactileAutoencoder
    norm: Normaliser
    config: TrainConfig
    best_epoch: int
    epochs: int
    best_val: float
    seconds: float
    stopped: str  # "early stop" or "max epochs"
    history: list[dict[str, Any]]
    classes: dict[str, list[str]]

    def summary(self) -> dict[str, Any]:
        last = self.history[self.best_epoch - 1]
        return {"variant": self.config.model.variant, "epochs": self.epochs,
                "best_epoch": self.best_epoch, "best_val_loss": self.best_val,
                "stopped": self.stopped, "train_loss_at_best": last["train"]["loss"],
                "dead_codes_at_best": last.get("dead_codes"),
                "train_samples": last["train_samples"], "val_samples": last["val_samples"]}


class Progress:
    """Training progress on stderr (:mod:`edge.core.progress`: a tqdm bar on a terminal,
    a whole line every few seconds otherwise). One object can follow several trainings in a
    row (the release trains the VQ-VAE, then the beta-VAE)."""

    def __init__(self, stream: TextIO | None = None, every_s: float = PLAIN_EVERY_S,
                 enabled: bool = True) -> None:
        self.stream = stream
        self.every_s = every_s
        self.enabled = enabled
        self._bar: Bar | None = None

    def begin(self, desc: str, total: int) -> None:
        if self._bar is not None:
            self._bar.close()
        self._bar = Bar(desc, total, "epochs", stream=self.stream, every_s=self.every_s,
                        enabled=self.enabled)

    def update(self, epoch: int, line: str, final: bool = False) -> None:
        if self._bar is None:
            self.begin("train", 0)
        assert self._bar is not None
        self._bar.set(epoch, line)
        if final:
            self._bar.close()
            self._bar = None


def _batches(n: int, size: int, rng: np.random.Generator) -> list[np.ndarray]:
    perm = rng.permutation(n)
    return [perm[i:i + size] for i in range(0, n, size)]


def _evaluate(model: TactileAutoencoder, data: Samples, negatives: Samples | None = None,
              batch: int = 2048) -> dict[str, float]:
    """Mean losses over ``data``; with ``negatives`` (``data`` one class) its metric term is
    :func:`_one_class_metric`'s."""
    model.eval()
    totals: dict[str, float] = {}
    with torch.no_grad():
        for i in range(0, len(data), batch):
            x = torch.from_numpy(data.x[i:i + batch])
            out = model(x, torch.from_numpy(data.x_bar[i:i + batch]),
                        torch.from_numpy(data.label_index[i:i + batch]))
            for key, value in out.losses.items():
                totals[key] = totals.get(key, 0.0) + float(value) * x.shape[0]
        losses = {key: value / len(data) for key, value in totals.items()}
        if negatives is not None:
            metric = _one_class_metric(model, data, negatives, batch)
            losses["loss"] += model.cfg.metric * (metric - losses.get("metric", 0.0))
            losses["metric"] = metric
    return losses


def _one_class_metric(model: TactileAutoencoder, data: Samples, negatives: Samples,
                      batch: int) -> float:
    """:func:`~train.learn.model.metric_loss` of one class's samples with ``negatives`` (the
    training samples) as the other class: each of its samples' farthest same-class sample
    should lie ``METRIC_MARGIN`` nearer than its nearest training sample. The training
    samples are negatives only, never anchors (their own term is the training loss's)."""
    def embed_all(samples: Samples) -> torch.Tensor:
        return torch.cat([model.embed(torch.from_numpy(samples.x[i:i + batch]))
                          for i in range(0, len(samples), batch)])

    z, z_neg = embed_all(data), embed_all(negatives)
    pos = torch.cdist(z, z).amax(1)
    neg = torch.cat([torch.cdist(z, z_neg[i:i + batch]).amin(1, keepdim=True)
                     for i in range(0, len(z_neg), batch)], dim=1).amin(1)
    return float(torch.nn.functional.relu(pos - neg + METRIC_MARGIN).mean())


def save_checkpoint(path: str | Path, model: TactileAutoencoder, norm: Normaliser,
                    config: TrainConfig, classes: dict[str, list[str]], epoch: int,
                    val_loss: float) -> None:
    buf = io.BytesIO()
    torch.save({
        "format": CHECKPOINT_FORMAT,
        "train_config": config.to_dict(),
        "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
        "norm": {"mean": torch.from_numpy(norm.mean), "std": torch.from_numpy(norm.std)},
        "classes": classes,
        "epoch": epoch,
        "val_loss": val_loss,
    }, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path: str | Path) -> tuple[TactileAutoencoder, Normaliser, dict[str, Any]]:
    """The model (eval mode), its normaliser and the checkpoint's metadata."""
    path = Path(path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ModelError(f"{path}: missing checkpoint") from None
    except Exception as exc:  # torch raises many types for a bad file
        raise ModelError(f"{path}: not a readable checkpoint: {exc}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise ModelError(f"{path}: not a {CHECKPOINT_FORMAT} checkpoint")
    config = TrainConfig.from_dict(ckpt["train_config"])
    model = TactileAutoencoder(config.model)
    model.load_state_dict(ckpt["state_dict"])
    model.eval()
    norm = Normaliser(ckpt["norm"]["mean"].numpy(), ckpt["norm"]["std"].numpy())
    meta = {k: v for k, v in ckpt.items() if k not in ("state_dict", "norm")}
    meta["train_config"] = config
    return model, norm, meta


def train(data: TrainingData, config: TrainConfig, out_dir: str | Path | None = None,
          progress: Progress | None = None,
          on_epoch: Callable[[dict[str, Any]], None] | None = None) -> TrainResult:
    """Train one model on ``data``; returns the best one (lowest validation loss)."""
    set_determinism(config.seed, config.threads)
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / TRAIN_LOG).write_text("")
    progress = progress or Progress()
    cfg = config.model
    # One validation class has no other class in its own samples: its metric term would be
    # 0 and early stopping would watch the reconstruction alone. Its presses are held against
    # the training presses instead (:func:`_one_class_metric`).
    negatives = data.train if cfg.metric and len(data.splits.val) == 1 else None
    expected = (cfg.steps, cfg.channels)
    if data.train.x.shape[1:] != expected:
        raise ValueError(f"samples are {data.train.x.shape[1:]}, the model takes {expected}")
    model = TactileAutoencoder(cfg)
    optimiser = torch.optim.Adam(model.parameters(), lr=config.lr)
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, 1]))
    revive_gen = torch.Generator().manual_seed(config.seed + 2)
    classes = {"train": list(data.splits.train), "val": list(data.splits.val)}
    x_all = torch.from_numpy(data.train.x)
    xb_all = torch.from_numpy(data.train.x_bar)
    labels_all = torch.from_numpy(data.train.label_index)

    best_val, best_epoch, best_state, wait = float("inf"), 0, None, 0
    history: list[dict[str, Any]] = []
    started = time.perf_counter()
    stopped = "max epochs"
    epoch = 0
    name = cfg.variant + ("" if cfg.decoder == "teacher" else f"_{cfg.decoder}")
    progress.begin(f"train {name}", config.max_epochs)
    for epoch in range(1, config.max_epochs + 1):
        t0 = time.perf_counter()
        model.train()
        totals: dict[str, float] = {}
        usage = torch.zeros(cfg.codebook_size, dtype=torch.long)
        z_pool = []
        for idx in _batches(len(data.train), config.batch_size, rng):
            ti = torch.from_numpy(idx)
            out_b = model(x_all[ti], xb_all[ti], labels_all[ti])
            optimiser.zero_grad(set_to_none=True)
            out_b.losses["loss"].backward()
            if config.grad_clip:
                torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            optimiser.step()
            for key, value in out_b.losses.items():
                totals[key] = totals.get(key, 0.0) + float(value.detach()) * len(idx)
            if out_b.code is not None:
                usage += torch.bincount(out_b.code, minlength=cfg.codebook_size)
                z_pool.append(out_b.z.detach())
        train_losses = {k: v / len(data.train) for k, v in totals.items()}
        dead = int((usage == 0).sum()) if cfg.variant == "vq" else None
        revived = 0
        if cfg.variant == "vq" and cfg.revive_dead and dead:
            revived = model.revive(usage, torch.cat(z_pool), revive_gen)
        val_losses = _evaluate(model, data.val, negatives)
        val = val_losses["loss"]
        improved = val < best_val * (1.0 - config.min_delta) if best_val < float("inf") \
            else True
        if improved:
            best_val, best_epoch, wait = val, epoch, 0
            best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            if out is not None:
                save_checkpoint(out / CHECKPOINT, model, data.norm, config, classes, epoch, val)
        else:
            wait += 1
        probs = usage.double() / max(1, int(usage.sum()))
        perplexity = float(torch.exp(-(probs[probs > 0] * probs[probs > 0].log()).sum())) \
            if cfg.variant == "vq" else None
        row = {"epoch": epoch, "train": train_losses, "val": val_losses,
               "dead_codes": dead, "revived": revived, "perplexity": perplexity,
               "best": improved, "seconds": time.perf_counter() - t0,
               "train_samples": len(data.train), "val_samples": len(data.val)}
        history.append(row)
        if out is not None:
            with (out / TRAIN_LOG).open("a") as fh:
                fh.write(json.dumps(row, sort_keys=True) + "\n")
        if on_epoch:
            on_epoch(row)
        codes = f" dead {dead:2d}/{cfg.codebook_size}" if dead is not None else ""
        progress.update(epoch, f"train {train_losses['loss']:.4f} (recon "
                               f"{train_losses['recon']:.4f}) val {val:.4f} best "
                               f"{best_val:.4f}@{best_epoch}{codes}")
        if wait >= config.patience:
            stopped = "early stop"
            break
    seconds = time.perf_counter() - started
    assert best_state is not None
    model.load_state_dict(best_state)
    model.eval()
    progress.update(epoch, f"{stopped}: best val {best_val:.4f} at epoch {best_epoch}",
                    final=True)
    log.info("trained %s: %d epochs, best val %.4f at %d, %.1f s",
             name, epoch, best_val, best_epoch, seconds)
    return TrainResult(model, data.norm, config, best_epoch, epoch, best_val, seconds,
                       stopped, history, classes)


@torch.no_grad()
def embed(model: TactileAutoencoder, norm: Normaliser, x_units: np.ndarray,
          batch: int = 2048) -> tuple[np.ndarray, np.ndarray | None]:
    """Embeddings of inputs in tactile units with torch: z (N, D) and z_q (VQ) or None."""
    model.eval()
    zs, zqs = [], []
    for i in range(0, len(x_units), batch):
        z = model.embed(torch.from_numpy(norm(x_units[i:i + batch])))
        zs.append(z.numpy())
        if model.quantiser is not None:
            zqs.append(model.quantiser.codebook[model.quantiser.nearest(z)].numpy())
    return np.concatenate(zs), (np.concatenate(zqs) if zqs else None)
