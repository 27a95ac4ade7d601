"""The probe's curve as a PNG with pillow (an edge dependency; matplotlib is a training one):
the tactile norm (left axis) and the squeeze current above free closing (right axis) against
the gripper's closing distance, with the proposed thresholds and the noise floor marked."""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from edge.core.atomic import atomic_write_bytes

if TYPE_CHECKING:
    from edge.ops.calibrate import IdleNoise, ProbeTrace, Proposal

SIZE = (960, 600)
# Plot area inside the image: left, top, right, bottom margins in pixels.
MARGIN = (80, 50, 90, 60)
TICKS = 5
NORM_COLOUR = (31, 119, 180)
CURRENT_COLOUR = (214, 39, 40)
X_TH_COLOUR = (44, 160, 44)
FRAGILE_COLOUR = (255, 127, 14)
FLOOR_COLOUR = (127, 127, 127)


def plot_curve(trace: ProbeTrace, proposal: Proposal, idle: IdleNoise, path: str | Path) -> None:
    img = Image.new("RGB", SIZE, "white")
    draw = ImageDraw.Draw(img)
    try:
        font: ImageFont.ImageFont | ImageFont.FreeTypeFont = ImageFont.load_default(size=14)
    except TypeError:  # Pillow < 10.1: only the small bitmap font
        font = ImageFont.load_default()

    def text(xy: tuple[float, float], words: str, fill: object, anchor: str = "la") -> None:
        # Anchored by hand: a bitmap font (older Pillow) takes no anchor.
        left_, top_, right_, bottom_ = draw.textbbox((0, 0), words, font=font)
        w, h = right_ - left_, bottom_ - top_
        dx = {"l": 0.0, "m": -w / 2, "r": -w}[anchor[0]]
        dy = {"a": 0.0, "t": 0.0, "m": -h / 2, "d": -h}[anchor[1]]
        draw.text((xy[0] + dx, xy[1] + dy), words, fill=fill, font=font)
    left, top = MARGIN[0], MARGIN[1]
    right, bottom = SIZE[0] - MARGIN[2], SIZE[1] - MARGIN[3]
    x = 1e3 * trace.closing_m
    above = trace.squeeze_ma - trace.free_ma
    x_max = max(float(x.max()), 1e-3)
    n_max = max(float(trace.norm.max()), proposal.x_th) * 1.1
    c_lo, c_hi = min(float(above.min()), 0.0), max(float(above.max()), 1.0) * 1.1

    def px(v: float) -> float:
        return left + (right - left) * v / x_max

    def py_norm(v: float) -> float:
        return bottom - (bottom - top) * v / n_max

    def py_cur(v: float) -> float:
        return bottom - (bottom - top) * (v - c_lo) / (c_hi - c_lo)

    draw.rectangle((left, top, right, bottom), outline="black")
    for i in range(TICKS + 1):
        f = i / TICKS
        gx = left + (right - left) * f
        gy = bottom - (bottom - top) * f
        draw.line((gx, bottom, gx, bottom + 5), fill="black")
        text((gx, bottom + 8), f"{f * x_max:.1f}", "black", "mt")
        text((left - 8, gy), f"{f * n_max:.4f}", NORM_COLOUR, "rm")
        text((right + 8, gy), f"{c_lo + f * (c_hi - c_lo):.0f}", CURRENT_COLOUR, "lm")
    text(((left + right) / 2, SIZE[1] - 20), "closing distance (mm of gripper width)", "black",
         "mm")
    text((left, top - 30), "tactile norm (units)", NORM_COLOUR)
    text((right, top - 30), "squeeze above free closing (mA)", CURRENT_COLOUR, "ra")
    for level, colour, label in (
            (proposal.x_th, X_TH_COLOUR, f"x_th {proposal.x_th:.5f} at {proposal.target}"),
            (proposal.fragile, FRAGILE_COLOUR, f"fragile {proposal.fragile:.5f}"),
            (idle.floor, FLOOR_COLOUR, f"noise floor {idle.floor:.5f}")):
        if level <= n_max:
            draw.line((left, py_norm(level), right, py_norm(level)), fill=colour, width=1)
            text((left + 6, py_norm(level) - 3), label, colour, "ld")
    at = px(proposal.at_x_th["closing_mm"])
    draw.line((at, top, at, bottom), fill=X_TH_COLOUR, width=1)
    order = np.argsort(x, kind="stable")
    draw.line([(px(a), py_cur(b)) for a, b in zip(x[order], above[order], strict=True)],
              fill=CURRENT_COLOUR, width=2)
    draw.line([(px(a), py_norm(b)) for a, b in zip(x[order], trace.norm[order], strict=True)],
              fill=NORM_COLOUR, width=2)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    atomic_write_bytes(path, buf.getvalue())
