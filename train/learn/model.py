"""The Seq2Seq GRU VQ-VAE of docs/method.md, 'Encoder', and its beta-VAE variant.

Encoder: 2-layer bidirectional GRU (hidden 32) over the normalised X (B, 25, 96); the last
layer's final forward and backward states, concatenated (64), go through a Linear to
z in R^latent (the beta-VAE's Linear gives a mean and a log-variance instead).

Shipped configuration and the paper's (``PAPER``, trained beside it for the comparison):
the paper's z is 4 numbers and its loss reconstruction only. With the paper's decoder the
reconstruction barely needs z (the decoder sees X[t-1]), so z kept little of what tells
objects apart and lost to a trivial baseline (each channel's mean over the window) on every
retrieval figure. The shipped model keeps the paper's encoder, bottleneck and decoder, with
z of 16 numbers and a metric term on z over the training classes (``metric_loss``): presses
of one class nearer each other than other classes' presses, in the L2 distance retrieval
uses. models/eval/eval.md measures both.

Bottleneck: VQ with a codebook of K = 32 vectors of dim latent; nearest code by L2, straight-through
gradient; loss ``MSE(sg[z], z_q) + 0.25 * MSE(z, sg[z_q])``. Codes no sample chose during an
epoch are counted (``dead``) and, if ``revive_dead``, moved onto encoder outputs of random
training samples at the end of the epoch (a seeded draw).

Decoder (``decoder="teacher"``, the paper's and the default): Linear(4 -> 32) of z_q is the
initial hidden state of both layers of a 2-layer GRU (hidden 32), and the GRU reads the input
sequence X, teacher-forced ("with this initial hidden state z_q and X"): at step t it is given
X[t-1] (zeros at t = 0), never X[t] itself, which it could simply copy to the smoothed X_bar[t]
without using z at all. A Linear(32 -> 96) per step reconstructs the normalised X_bar.

Variant ``decoder="zeros"`` (this project's earlier decoder, kept for the comparison): the
initial state is tanh(Linear(z)) and the GRU's inputs are zeros, so the whole press has to
pass through the bottleneck.

Loss = MSE(X_hat, X_bar) + codebook + commitment (VQ) or + beta_kl * KL / (T * C) (beta-VAE:
the KL summed over latent dims, scaled like a per-element likelihood), + metric * the metric
term (on z, or the beta-VAE's posterior mean) when labels are given.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

Variant = Literal["vq", "beta"]
DecoderKind = Literal["teacher", "zeros"]
DECODERS: tuple[str, ...] = ("teacher", "zeros")
# The triplet margin of the metric term, in z's units.
METRIC_MARGIN = 1.0
# What the paper's configuration changes in ModelConfig: z of 4 numbers, no metric term.
PAPER = {"latent": 4, "metric": 0.0}


@dataclass(frozen=True)
class ModelConfig:
    variant: Variant = "vq"
    channels: int = 96
    steps: int = 25
    hidden: int = 32
    layers: int = 2
    latent: int = 16
    codebook_size: int = 32
    commitment: float = 0.25
    beta_kl: float = 4.0
    revive_dead: bool = True
    decoder: DecoderKind = "teacher"
    # Weight of the metric term on z (0: the paper's loss); see ``metric_loss``.
    metric: float = 1.0

    def __post_init__(self) -> None:
        if self.variant not in ("vq", "beta"):
            raise ValueError(f"variant must be 'vq' or 'beta', got {self.variant!r}")
        if self.metric < 0:
            raise ValueError(f"metric must be >= 0, got {self.metric}")
        if self.decoder not in DECODERS:
            raise ValueError(f"decoder must be one of {', '.join(DECODERS)}, got "
                             f"{self.decoder!r}")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        """A saved configuration; one saved before the decoder had a choice used zeros, one
        saved before the metric term had none."""
        return cls(**({"decoder": "zeros", "metric": 0.0} | dict(d)))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def set_determinism(seed: int, threads: int = 1) -> None:
    """Seed everything and make CPU training bit-reproducible for a thread count."""
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True, warn_only=True)


class Encoder(nn.Module):
    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.gru = nn.GRU(cfg.channels, cfg.hidden, num_layers=cfg.layers,
                          bidirectional=True, batch_first=True)
        out = cfg.latent * (2 if cfg.variant == "beta" else 1)
        self.head = nn.Linear(2 * cfg.hidden, out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _, h = self.gru(x)  # h: (layers * 2, B, H); the last two are the top layer's
        return self.head(torch.cat([h[-2], h[-1]], dim=-1))


class VectorQuantiser(nn.Module):
    def __init__(self, size: int, dim: int) -> None:
        super().__init__()
        self.codebook = nn.Parameter(torch.empty(size, dim).uniform_(-1.0 / size, 1.0 / size))

    def nearest(self, z: torch.Tensor) -> torch.Tensor:
        e = self.codebook
        d2 = (z * z).sum(-1, keepdim=True) - 2.0 * z @ e.t() + (e * e).sum(-1)
        return torch.argmin(d2, dim=-1)

    def forward(self, z: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        code = self.nearest(z)
        z_q = self.codebook[code]
        losses = {"codebook": F.mse_loss(z_q, z.detach()),
                  "commit": F.mse_loss(z, z_q.detach())}
        return z + (z_q - z).detach(), code, losses


class Decoder(nn.Module):
    """z (B, latent) and the normalised input X (B, T, C) -> X_hat (B, T, C)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.kind = cfg.decoder
        self.layers, self.steps = cfg.layers, cfg.steps
        self.init = nn.Linear(cfg.latent, cfg.hidden)
        inputs = cfg.channels if cfg.decoder == "teacher" else 1
        self.gru = nn.GRU(inputs, cfg.hidden, num_layers=cfg.layers, batch_first=True)
        self.out = nn.Linear(cfg.hidden, cfg.channels)

    def forward(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        h = self.init(z)
        if self.kind == "teacher":
            # Step t sees X[t-1]: shifted right by one, a zero frame first.
            inputs = torch.cat([x.new_zeros(x.shape[0], 1, x.shape[2]), x[:, :-1]], dim=1)
        else:
            h = torch.tanh(h)
            inputs = z.new_zeros(z.shape[0], self.steps, 1)
        h0 = h.unsqueeze(0).repeat(self.layers, 1, 1).contiguous()
        y, _ = self.gru(inputs, h0)
        return self.out(y)


@dataclass
class Output:
    x_hat: torch.Tensor
    z: torch.Tensor  # the continuous embedding (beta-VAE: the mean)
    z_q: torch.Tensor | None
    code: torch.Tensor | None
    losses: dict[str, torch.Tensor]


class TactileAutoencoder(nn.Module):
    """Encoder -> bottleneck (VQ or beta-VAE) -> decoder; inputs are normalised."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg)
        self.quantiser = VectorQuantiser(cfg.codebook_size, cfg.latent) \
            if cfg.variant == "vq" else None
        self.decoder = Decoder(cfg)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """The embedding used for retrieval: z (VQ) or the posterior mean (beta-VAE)."""
        h = self.encoder(x)
        return h if self.cfg.variant == "vq" else h[:, :self.cfg.latent]

    def forward(self, x: torch.Tensor, x_bar: torch.Tensor,
                labels: torch.Tensor | None = None) -> Output:
        """``labels`` (B,) class indices: needed only for the metric term."""
        h = self.encoder(x)
        cfg = self.cfg
        if self.quantiser is not None:
            z = h
            z_st, code, losses = self.quantiser(z)
            x_hat = self.decoder(z_st, x)
            losses["recon"] = F.mse_loss(x_hat, x_bar)
            losses["loss"] = losses["recon"] + losses["codebook"] \
                + cfg.commitment * losses["commit"]
            if cfg.metric and labels is not None:
                losses["metric"] = metric_loss(z, labels)
                losses["loss"] = losses["loss"] + cfg.metric * losses["metric"]
            return Output(x_hat, z, z_st.detach(), code, losses)
        mu, logvar = h[:, :cfg.latent], h[:, cfg.latent:].clamp(-10.0, 10.0)
        if self.training:
            sample = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
        else:
            sample = mu
        x_hat = self.decoder(sample, x)
        kl = 0.5 * (mu.pow(2) + logvar.exp() - 1.0 - logvar).sum(-1).mean()
        recon = F.mse_loss(x_hat, x_bar)
        scale = cfg.steps * cfg.channels
        losses = {"recon": recon, "kl": kl, "loss": recon + cfg.beta_kl * kl / scale}
        if cfg.metric and labels is not None:
            losses["metric"] = metric_loss(mu, labels)
            losses["loss"] = losses["loss"] + cfg.metric * losses["metric"]
        return Output(x_hat, mu, None, None, losses)

    @torch.no_grad()
    def revive(self, usage: torch.Tensor, z_pool: torch.Tensor,
               generator: torch.Generator) -> int:
        """Move unused codes onto random encoder outputs; returns how many moved."""
        if self.quantiser is None:
            return 0
        dead = torch.nonzero(usage == 0).flatten()
        if dead.numel() == 0 or z_pool.shape[0] == 0:
            return 0
        pick = torch.randint(0, z_pool.shape[0], (dead.numel(),), generator=generator)
        jitter = 0.01 * z_pool.std(0) * torch.randn(dead.numel(), z_pool.shape[1],
                                                    generator=generator)
        self.quantiser.codebook[dead] = z_pool[pick] + jitter
        return int(dead.numel())


def metric_loss(z: torch.Tensor, labels: torch.Tensor, margin: float = METRIC_MARGIN
                ) -> torch.Tensor:
    """Batch-hard triplet loss on z: each sample's farthest same-class sample should lie
    ``margin`` nearer than its nearest other-class one, in the L2 distance retrieval uses.
    The margin bounds it (a loss that only rewards spread would blow z up); samples without
    both a positive and a negative in the batch do not count."""
    d = torch.cdist(z, z)
    same = labels[:, None] == labels[None, :]
    eye = torch.eye(len(z), dtype=torch.bool, device=z.device)
    pos = torch.where(same & ~eye, d, torch.zeros_like(d)).amax(1)
    neg = torch.where(same, torch.full_like(d, float("inf")), d).amin(1)
    valid = (same & ~eye).any(1) & (~same).any(1)
    if not bool(valid.any()):
        return z.new_zeros(())
    return F.relu(pos - neg + margin)[valid].mean()


class ExportEncoder(nn.Module):
    """What ships: tactile units -> normalise -> encoder -> (z, nearest code index)."""

    def __init__(self, model: TactileAutoencoder, mean: np.ndarray, std: np.ndarray) -> None:
        super().__init__()
        if model.quantiser is None:
            raise ValueError("only the VQ variant exports (it has the codebook)")
        self.encoder = model.encoder
        self.quantiser = model.quantiser
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float32))
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float32))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z = self.encoder((x - self.mean) / self.std)
        return z, self.quantiser.nearest(z)
