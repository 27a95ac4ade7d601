"""Retrieval as the robot does it: a tactile encoder and its reference database (the
shipped model, or one built from a training checkpoint), and the touch sentence of the nearest
classes."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from edge.core.errors import ModelError
from edge.core.model import Familiarity, ReferenceDatabase
from edge.vlm.prompt import weak_match
from train.eval.eval_vlm.config import Condition
from train.learn.data import PressSet, load_presses


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


def unfamiliar(source: Tactile, x: np.ndarray, percentile: float) -> list[bool]:
    """Whether each press of ``x`` is flagged unfamiliar as the daemon flags it (its
    familiarity at or past ``percentile``)."""
    familiarity = Familiarity(source.database)
    return [(p := familiarity.percentile(z, f)) is not None and p >= percentile
            for z, f in zip(source.embed(x), x.mean(axis=1), strict=True)]


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


def describe(condition: Condition, db: ReferenceDatabase, labels: Sequence[str],
             unfamiliar: bool = False) -> str:
    """The touch sentence of ``labels`` under ``condition``: the database's descriptions
    (object names), for the adjective ablation the hand-written tactile adjectives, for the
    weak-match one the names saying so where the press is ``unfamiliar``."""
    if condition.descriptions == "weak" and unfamiliar:
        return weak_match(db.describe(labels))
    if condition.descriptions == "adjectives":
        from train.eval.ablation import TACTILE_ADJECTIVES

        return ", ".join(TACTILE_ADJECTIVES.get(label) or db.description(label)
                         for label in labels)
    return db.describe(labels)
