"""Readable summaries of simulated presses (the demo's output)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from edge.core import preprocess
from edge.sim.press import PressParams, PressResult, simulate_press


def press_row(name: str, result: PressResult) -> dict:
    rec = result.recording
    units = preprocess.recording_units(rec)
    level = preprocess.norm(units)
    row = {"object": name, "contact": result.contact}
    if not result.contact:
        return row
    hold = (rec.recv_time >= result.t_stop) & (rec.recv_time < result.t_stop + 0.2)
    x = preprocess.model_input(rec.recv_time, units, rec.t_stop)
    row.update(
        t_cross_ms=(result.t_cross - result.t_contact) * 1e3,
        stop_ms=(result.t_stop - result.t_cross) * 1e3,
        peak_n=result.peak_force_n,
        peak_norm=float(level.max()),
        relax=float(level[hold][-1] / level[hold].max()) if hold.any() else float("nan"),
        x_shape=x.shape,
    )
    return row


def print_press_table(objects: Sequence[str], seed: int, params: PressParams) -> None:
    header = (f"{'object':24s} {'contact':>7s} {'touch->x_th':>11s} {'stop':>6s} "
              f"{'peak F':>7s} {'peak norm':>9s} {'hold':>6s}  model input")
    print(header)
    print("-" * len(header))
    for i, name in enumerate(objects):
        result = simulate_press(name, np.random.default_rng([seed, i]), params)
        r = press_row(name, result)
        if not r["contact"]:
            print(f"{name:24s} {'no':>7s}  (closed fully without crossing x_th)")
            continue
        print(f"{name:24s} {'yes':>7s} {r['t_cross_ms']:9.1f}ms {r['stop_ms']:4.1f}ms "
              f"{r['peak_n']:6.2f}N {r['peak_norm']:9.4f} {r['relax']:6.2f}  "
              f"X {r['x_shape'][0]}x{r['x_shape'][1]}")
    print(f"\nx_th = {params.x_th} (norm of (raw - tare)/65536 over 96 channels); "
          f"stop = reaction latency {params.reaction_latency_s * 1e3:.0f} ms; "
          "hold = norm at the end of the 0.2 s hold / its peak (below 1: relaxation)")
