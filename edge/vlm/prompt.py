"""Prompt templates for the VLM (docs/method.md, 'Prompt').

A template is a text file (``models/prompts/<mode>.txt``) read with :class:`string.Template`
and two slots: ``${topk_refs}`` (the tactile description: the names of the reference objects
a press felt like, e.g. "wood cube, stainless steel cube, rubber eraser") and
``${test_time_classes}`` (the candidate labels, known only at run time). Loading refuses
unknown slots, a missing slot and a stray ``$``, so a typo in a template fails at start-up,
not as a silently odd prompt on the robot.

Candidates are rendered as JSON strings joined by ", " (``"raw_kiri_mochi",
"boiled_kiri_mochi"``): each label exactly as given and unambiguous even if a label holds a
comma or a space.
"""

from __future__ import annotations

import json
import string
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

from edge.core.errors import PromptError

PromptMode = Literal["vision_tactile", "vision_only", "tactile_only"]
MODES: tuple[str, ...] = get_args(PromptMode)

DESCRIPTION_SLOT = "topk_refs"
CANDIDATES_SLOT = "test_time_classes"
SLOTS = frozenset({DESCRIPTION_SLOT, CANDIDATES_SLOT})

# The shipped templates: <repo>/models/prompts/<mode>.txt
DEFAULT_PROMPT_DIR = Path(__file__).resolve().parents[2] / "models" / "prompts"

# A label is a short identifier-like name; refuse anything that could not be one.
MAX_LABEL_CHARS = 200

# What the weak-match ablation adds to the tactile description of an unfamiliar press (Table
# I's ``vq_top3_weak`` row); the paper's prompt, the default, never says it.
WEAK_MATCH = "but only weakly: the touch matched none of them closely"


def weak_match(description: str) -> str:
    """``description`` (the nearest classes' names) saying that the match is weak."""
    return f"{description}, {WEAK_MATCH}"



@dataclass(frozen=True)
class PromptTemplate:
    """A validated template; :meth:`render` fills the slots."""

    mode: str
    text: str
    source: str = "<string>"

    def __post_init__(self) -> None:
        _check_template(self.text, self.mode, self.source)

    @property
    def uses_image(self) -> bool:
        return self.mode != "tactile_only"

    @property
    def slots(self) -> frozenset[str]:
        """The slot names the template uses."""
        return frozenset(string.Template(self.text).get_identifiers())

    @property
    def uses_description(self) -> bool:
        return DESCRIPTION_SLOT in self.slots

    def render(self, description: str, candidates: Sequence[str]) -> str:
        """The prompt with ``description`` and ``candidates`` filled in."""
        labels = check_candidates(candidates)
        description = " ".join(str(description).split())
        if self.uses_description and not description:
            raise PromptError(f"{self.mode} prompt needs a tactile description, got none")
        return string.Template(self.text).substitute(
            {DESCRIPTION_SLOT: description, CANDIDATES_SLOT: format_candidates(labels)}
        ).strip()


def load_template(mode: str, directory: str | Path | None = None) -> PromptTemplate:
    """Read ``<directory>/<mode>.txt`` (default: the shipped ``models/prompts``)."""
    if mode not in MODES:
        raise PromptError(f"unknown prompt mode {mode!r}; known: {', '.join(MODES)}")
    path = Path(directory if directory is not None else DEFAULT_PROMPT_DIR) / f"{mode}.txt"
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise PromptError(f"prompt template {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise PromptError(f"prompt template {path} cannot be read: {exc}") from None
    return PromptTemplate(mode=mode, text=text, source=str(path))


def format_candidates(candidates: Sequence[str]) -> str:
    return ", ".join(json.dumps(c, ensure_ascii=False) for c in candidates)


def check_candidates(candidates: Sequence[str]) -> list[str]:
    """The candidate labels as a list, refusing what could not be answered unambiguously."""
    if isinstance(candidates, str):
        raise PromptError("candidates must be a list of labels, not one string")
    labels = list(candidates)
    if not labels:
        raise PromptError("no candidate labels given")
    for label in labels:
        if not isinstance(label, str) or not label.strip():
            raise PromptError(f"candidate label {label!r} must be a non-empty string")
        if label != label.strip() or not label.isprintable() or len(label) > MAX_LABEL_CHARS:
            raise PromptError(
                f"candidate label {label[:MAX_LABEL_CHARS]!r} must be printable, without "
                f"surrounding spaces, at most {MAX_LABEL_CHARS} characters"
            )
    if len(set(labels)) != len(labels):
        dupes = sorted({c for c in labels if labels.count(c) > 1})
        raise PromptError(f"duplicate candidate labels: {', '.join(dupes)}")
    return labels


def _check_template(text: str, mode: str, source: str) -> None:
    if mode not in MODES:
        raise PromptError(f"{source}: unknown prompt mode {mode!r}; known: {', '.join(MODES)}")
    template = string.Template(text)
    if not template.is_valid():
        raise PromptError(
            f"{source}: invalid placeholder (a '$' not followed by a slot name; write '$$' "
            f"for a literal dollar); slots are ${{{DESCRIPTION_SLOT}}}, ${{{CANDIDATES_SLOT}}}"
        )
    found = set(template.get_identifiers())
    unknown = sorted(found - SLOTS)
    if unknown:
        raise PromptError(
            f"{source}: unknown slot(s) {', '.join('${' + u + '}' for u in unknown)}; "
            f"known: ${{{DESCRIPTION_SLOT}}}, ${{{CANDIDATES_SLOT}}}"
        )
    required = {CANDIDATES_SLOT} if mode == "vision_only" else set(SLOTS)
    missing = sorted(required - found)
    if missing:
        raise PromptError(
            f"{source}: {mode} template lacks slot(s) "
            + ", ".join("${" + m + "}" for m in missing)
        )
    if mode == "vision_only" and DESCRIPTION_SLOT in found:
        raise PromptError(
            f"{source}: the vision_only baseline must not use ${{{DESCRIPTION_SLOT}}} "
            "(it is the template with the tactile sentences removed)"
        )
