"""The tactile skin: from finger force and contact geometry to raw XELA counts.

Two XR1944 pads (4 x 4 taxels, 4.7 mm pitch, x/y/z per taxel), one per finger. The contact
pressure is laid on a 16 x 16 sub-grid of each pad (uniform, slightly tilted, over a flat face;
Hertzian ``sqrt(1 - r^2/a^2)`` over a round object's patch), spread by the silicone skin (a
Gaussian blur), and summed per taxel. Shear comes from the soft object's lateral bulge,
limited by friction, plus a common part from imperfect alignment. Counts: gains per newton,
a little electrical cross-talk from z into x/y, per-press tare offsets near the real idle
values, linear drift, Gaussian noise of ~2 counts, 16-bit saturation.

Channel order everywhere: ``pad * 48 + taxel * 3 + axis``, taxels row-major from the top left.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from edge.sim.contact import ObjectInstance

PADS = 2
TAXELS = 16
CHANNELS = PADS * TAXELS * 3
TAXEL_PITCH_M = 4.7e-3
_SUB = 4  # sub-grid points per taxel per axis
_GRID = 4 * _SUB
_CELL_M = TAXEL_PITCH_M / _SUB
# Sub-grid point coordinates, pad centred on (0, 0).
_COORD = (np.arange(_GRID) - (_GRID - 1) / 2.0) * _CELL_M
_GX, _GY = np.meshgrid(_COORD, _COORD)  # _GX[row, col]

# Sensitivity chosen so that x_th = 0.004 (~262 counts of total norm) is a gentle touch, as
# the paper describes: ~0.37 N per finger spread over a whole flat pad, ~0.13 N concentrated
# on one taxel.
GAIN_Z_COUNTS_PER_N = 2000.0
GAIN_XY_COUNTS_PER_N = 1000.0
XTALK_Z_TO_XY = 0.015
SKIN_SPREAD_M = 1.5e-3
NOISE_COUNTS = 2.0
IDLE_XY = 32768.0
IDLE_Z = 37000.0


@dataclass(frozen=True)
class SkinDraw:
    """Per-press sensor state: tare offsets and drift rates per channel."""

    offsets: np.ndarray  # (96,) counts at idle
    drift_per_s: np.ndarray  # (96,) counts per second

    @classmethod
    def draw(cls, rng: np.random.Generator) -> SkinDraw:
        axis = np.tile(np.array([0, 1, 2]), PADS * TAXELS)
        idle = np.where(axis == 2, IDLE_Z, IDLE_XY)
        spread = np.where(axis == 2, 600.0, 400.0)
        offsets = idle + rng.normal(0.0, 1.0, CHANNELS) * spread
        # Drift of up to ~1000 counts over minutes: a few counts per second.
        drift = rng.normal(0.0, 2.0, CHANNELS)
        return cls(offsets, drift)


class Skin:
    """Renders raw frames for one object instance pressed by both fingers."""

    def __init__(self, inst: ObjectInstance, rng: np.random.Generator,
                 draw: SkinDraw | None = None) -> None:
        self.inst = inst
        self.rng = rng
        self.draw = draw if draw is not None else SkinDraw.draw(rng)
        self._flat_cache: list[np.ndarray | None] = [None, None]

    def _pressure(self, pad: int, contact_radius_m: float) -> np.ndarray:
        """Normalised pressure on the pad's sub-grid (sums to 1), after the skin's spread."""
        cx, cy = self.inst.patch_offsets_m[pad]
        obj = self.inst.cls
        if obj.shape == "flat":
            cached = self._flat_cache[pad]
            if cached is not None:
                return cached
            half = obj.size_m / 2.0
            inside = (np.abs(_GX - cx) <= half) & (np.abs(_GY - cy) <= half)
            tx, ty = self.inst.tilt
            p = np.where(inside, np.clip(1.0 + tx * (_GX - cx) + ty * (_GY - cy), 0.0, None),
                         0.0)
        else:
            a = max(contact_radius_m, 0.6 * _CELL_M)
            r2 = ((_GX - cx) ** 2 + (_GY - cy) ** 2) / (a * a)
            p = np.sqrt(np.clip(1.0 - r2, 0.0, None))
            if p.sum() <= 0.0:
                # Patch smaller than a grid cell: load the nearest point.
                p = np.zeros_like(p)
                p[np.unravel_index(np.argmin(r2), r2.shape)] = 1.0
        p = gaussian_filter(p, SKIN_SPREAD_M / _CELL_M, mode="constant")
        p /= p.sum()
        if obj.shape == "flat":
            self._flat_cache[pad] = p
        return p

    def loads(self, force_n: float, contact_radius_m: float) -> np.ndarray:
        """Noise-free change in counts, shape (96,), for a per-finger force."""
        out = np.zeros((PADS, TAXELS, 3))
        if force_n <= 0.0:
            return out.reshape(-1)
        obj = self.inst.cls
        bulge = min(obj.bulge, obj.mu)
        for pad in range(PADS):
            p = self._pressure(pad, contact_radius_m) * force_n
            cx, cy = self.inst.patch_offsets_m[pad]
            extent = max(obj.size_m / 2.0 if obj.shape == "flat" else contact_radius_m,
                         _CELL_M)
            sx = p * (bulge * (_GX - cx) / extent + self.inst.common_shear[0])
            sy = p * (bulge * (_GY - cy) / extent + self.inst.common_shear[1])
            if pad == 1:
                sx = -sx  # the second pad faces the first: its x axis is mirrored
            for axis, field in enumerate((sx, sy, p)):
                taxel = field.reshape(4, _SUB, 4, _SUB).sum(axis=(1, 3)).reshape(-1)
                out[pad, :, axis] = taxel
        out[..., 0:2] *= GAIN_XY_COUNTS_PER_N
        out[..., 2] *= GAIN_Z_COUNTS_PER_N
        out[..., 0:2] += XTALK_Z_TO_XY * out[..., 2:3]
        return out.reshape(-1)

    def frame(self, t_s: float, force_n: float, contact_radius_m: float) -> np.ndarray:
        """Raw uint16 counts at press time ``t_s`` (seconds since the press began)."""
        values = (self.draw.offsets + self.draw.drift_per_s * t_s
                  + self.loads(force_n, contact_radius_m)
                  + self.rng.normal(0.0, NOISE_COUNTS, CHANNELS))
        return np.clip(np.rint(values), 0, 65535).astype(np.uint16)
