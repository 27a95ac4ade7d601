"""The paper's Table I beside ours: its figures, and which of our sets stands beside which
of its sets (FoodReplica, Cube)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from edge.core.errors import EvalVLMError

# The paper's Table I (GPT-4V), percent, for the side-by-side table.
PAPER = {"vision_only": {"foodreplica": 53.6, "cube": 50.0},
         "vq_top3": {"foodreplica": 58.9, "cube": 65.0},
         "vq_top1": {"foodreplica": 58.4, "cube": 52.5},
         "beta_top3": {"foodreplica": 52.5, "cube": 50.0}}
DATASET_TITLES = {"foodreplica": "FoodReplica", "cube": "Cube"}
PAPER_SETS = tuple(DATASET_TITLES)


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
