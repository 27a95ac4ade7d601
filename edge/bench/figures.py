"""Measured figures and their targets: the schema both benches write.

A figure is a JSON object: ``p50``, ``p99``, ``max`` and ``n`` of its samples, ``unit``,
``target`` (a list of conditions on the figure's own keys, all of which must hold, or None)
and ``met`` (True, False, or None without a target), plus whatever else describes it
(``what``, counts, sub-statistics). ``vt-edge bench`` and ``vt-train bench`` build them here
and put them in one results file (:mod:`edge.bench.results`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

Figure = dict[str, Any]
Target = list[dict[str, Any]]


def stats(values: Sequence[float | None]) -> dict[str, Any]:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)),
            "max": float(v.max()), "n": int(v.size)}


def target(*conditions: tuple[str, str, float]) -> Target:
    """Conditions on a figure's own keys, e.g. ``("p99", "<=", 2.0)``; all must hold."""
    return [{"stat": s, "op": op, "value": value} for s, op, value in conditions]


def _holds(value: Any, op: str, bound: float) -> bool:
    if value is None:
        return False
    return {"<=": value <= bound, ">=": value >= bound, "==": value == bound}[op]


def figure(values: Sequence[float | None], unit: str, goal: Target | None = None,
           **extra: Any) -> Figure:
    fig = {**stats(values), "unit": unit, **extra}
    return finish(fig, goal)


def finish(fig: Figure, goal: Target | None) -> Figure:
    fig["target"] = goal
    fig["met"] = None if not goal else all(_holds(fig.get(c["stat"]), c["op"], c["value"])
                                           for c in goal)
    return fig


def ratio_figure(num: Figure, den: Figure, goal: Target | None = None,
                 **extra: Any) -> Figure:
    """``num / den`` statistic by statistic (p50 of one over p50 of the other, ...)."""
    fig: Figure = {"unit": "ratio"}
    for key in ("p50", "p99", "max"):
        a, b = num.get(key), den.get(key)
        fig[key] = a / b if a is not None and b else None
    fig["n"] = min(num.get("n", 0), den.get("n", 0))
    fig.update(extra)
    return finish(fig, goal)


def is_figure(value: Any) -> bool:
    return isinstance(value, dict) and "unit" in value and "met" in value


def target_text(goal: Target | None) -> str:
    if not goal:
        return "-"
    return " and ".join(f"{c['stat']} {c['op']} {c['value']:g}" for c in goal)


def short(v: Any) -> str:
    """A value for one line of text: floats to 3 significant digits, long JSON cut."""
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, list | dict):
        text = json.dumps(v)
        return text if len(text) < 120 else text[:117] + "..."
    return str(v)


def explain(figures: Mapping[str, Figure], why: Mapping[str, str]) -> list[str]:
    """One line per missed target: its figures, then why (``why[key]``) and what would
    close it."""
    out = []
    for key, fig in figures.items():
        if fig.get("met") is False:
            out.append(f"MISSED `{key}` ({target_text(fig['target'])}): p50 "
                       f"{short(fig['p50'])}, p99 {short(fig['p99'])}, max "
                       f"{short(fig['max'])} {fig['unit']}. {why.get(key, '')}".rstrip())
    return out


# Timed calls alternate in blocks: runtimes compared see the same (shared, noisy) host, and
# each runs warm (alternating single calls evicts onnxruntime's small working set: its median
# doubled in a trial).
BLOCK = 50


def timed_in_blocks(calls: Mapping[str, Callable[[Any], Any]], inputs: Sequence[Any], n: int,
                    block: int = BLOCK) -> dict[str, list[float]]:
    """``n`` timed calls (ms) of each of ``calls`` on ``inputs`` in turn, in blocks of
    ``block`` calls alternating between them; one untimed block of each warms up first."""
    times: dict[str, list[float]] = {name: [] for name in calls}
    for start in range(-block, n, block):
        for name, fn in calls.items():
            for i in range(start, start + block):
                x = inputs[i % len(inputs)]
                t0 = time.perf_counter()
                fn(x)
                if i >= 0:
                    times[name].append(1e3 * (time.perf_counter() - t0))
    return times
