"""A readable table of presses on the virtual robot (``vt-edge sim press``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from edge.core import preprocess
from edge.core.errors import EdgeError
from edge.lab.record import PressRecord, record_press


def press_row(name: str, pressed: PressRecord) -> dict:
    rec = pressed.recording
    units = preprocess.recording_units(rec)
    level = preprocess.norm(units)
    hold = (rec.recv_time >= rec.t_stop) & (rec.recv_time < rec.t_stop + 0.2)
    x = preprocess.model_input(rec.recv_time, units, rec.t_stop)
    return {
        "object": name,
        "x_th": rec.threshold,
        "stop_ms": pressed.outcome.stop_latency_s * 1e3,
        "peak_n": pressed.peak_force_n,
        "peak_norm": float(level.max()),
        "relax": float(level[hold][-1] / level[hold].max()) if hold.any() else float("nan"),
        "x_shape": x.shape,
        "tries": pressed.tries,
    }


def print_press_table(objects: Sequence[str], seed: int, x_th: float | None = None) -> None:
    header = (f"{'object':24s} {'x_th':>6s} {'stop':>6s} {'peak F':>7s} {'peak norm':>9s} "
              f"{'hold':>6s}  model input")
    print(header)
    print("-" * len(header))
    for i, name in enumerate(objects):
        try:
            pressed = record_press(name, np.random.default_rng([seed, i]), x_th=x_th)
        except EdgeError as exc:
            print(f"{name:24s} no recording: {exc}")
            continue
        r = press_row(name, pressed)
        print(f"{name:24s} {r['x_th']:6.4f} {r['stop_ms']:4.1f}ms {r['peak_n']:6.2f}N "
              f"{r['peak_norm']:9.4f} {r['relax']:6.2f}  X {r['x_shape'][0]}x{r['x_shape'][1]}")
    print("\nThe daemon's press controller on the virtual-clock emulated robot "
          "(configs/sim.toml). x_th: norm of (raw - tare)/65536 over 96 channels; stop: frame "
          "over x_th -> stop packet; hold: norm at the end of the 0.2 s hold / its peak "
          "(below 1: relaxation)")
