"""What an evaluation asks: the conditions (prompt template, tactile encoder, how many
reference classes) and a run's configuration, checked before anything loads."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from edge.core.config import VLMConfig
from edge.core.errors import EvalVLMError

# An answer that is no candidate even after the corrective retry: counted wrong, in its own
# column, never mapped to a label.
INVALID = "invalid_answer"
DEFAULT_CONCURRENCY = 4


@dataclass(frozen=True)
class Condition:
    name: str
    title: str
    mode: str  # the prompt template: vision_only / vision_tactile / tactile_only
    variant: str | None  # the tactile encoder: vq / beta / vq_zeros, None: no tactile sentence
    k: int  # distinct reference classes in the description (0: none)
    # Where the descriptions come from: the database (object names, the method), the
    # ablation's hand-written tactile adjectives, or the names saying the match is weak where
    # the press is unfamiliar (the weak-match ablation).
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
    Condition("vq_top3_weak", "Vision + tactile (VQ-VAE, top-3), an unfamiliar touch said to "
              "match only weakly (ablation)", "vision_tactile", "vq", 3, "weak"),
    Condition("tactile_only", "Tactile only (VQ-VAE, top-3, no image)", "tactile_only", "vq",
              3),
)}
DEFAULT_CONDITIONS = ("vision_only", "vq_top3", "vq_top1", "beta_top3")
# Conditions whose encoder comes from a training checkpoint, not the shipped model.
CHECKPOINT_VARIANTS = ("beta", "vq_zeros")


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
