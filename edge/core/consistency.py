"""Top-3 consistency: do recognitions of the same object retrieve the same classes?

One definition for training's evaluation (unseen classes' presses, ``train/eval``) and the
lab's measurements on the emulated robot (``edge/lab``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


def consistency(retrieved: Sequence[list[str]], labels: Sequence[str]) -> dict[str, Any]:
    """Share of same-class press pairs with the same top-3 set and the same top-1."""
    per_class: dict[str, dict[str, float]] = {}
    same3 = same1 = total = 0
    overlap = 0.0
    for cls in dict.fromkeys(labels):
        idx = [i for i, lab in enumerate(labels) if lab == cls]
        s3 = s1 = n = 0
        ov = 0.0
        for a in range(len(idx)):
            for b in range(a + 1, len(idx)):
                ra, rb = retrieved[idx[a]], retrieved[idx[b]]
                s3 += set(ra) == set(rb)
                s1 += ra[0] == rb[0]
                ov += len(set(ra) & set(rb)) / max(len(ra), 1)
                n += 1
        if n:
            per_class[cls] = {"top3": s3 / n, "top1": s1 / n, "overlap": ov / n}
        same3, same1, total, overlap = same3 + s3, same1 + s1, total + n, overlap + ov
    nan = float("nan")
    return {"top3_consistency": same3 / total if total else nan,
            "top1_consistency": same1 / total if total else nan,
            "top3_overlap": overlap / total if total else nan,
            "per_class": per_class}
