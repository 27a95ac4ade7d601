"""The unseen test sets: their presses in evaluation order (round-robin over classes, so a
limit keeps every class in play) and their candidate labels."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from edge.core.errors import EvalVLMError, RecordingError
from edge.core.model import Origin
from edge.core.recording import DATASET_INDEX
from train.learn.data import PressSet, load_presses


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


def load_sets(unseen: Sequence[Path], limit: int | None, spec: Any) -> tuple[UnseenSet, ...]:
    sets = tuple(load_test_set(d, limit, spec) for d in unseen)
    names = [s.name for s in sets]
    if len(set(names)) != len(names):
        raise EvalVLMError(f"two unseen sets share a name: {', '.join(names)}")
    return sets
