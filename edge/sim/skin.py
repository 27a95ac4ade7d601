"""The tactile skin: from finger force and contact geometry to raw XELA counts.

Two XR1944 pads (4 x 4 taxels, 4.7 mm pitch, x/y/z per taxel), one per finger, or the pads of
another layout (:class:`edge.core.layout.PadLayout` from ``[sensor]``, e.g. 4 x 6). The contact
pressure is laid on a sub-grid of 4 x 4 points per taxel of each pad (uniform, slightly tilted,
over a flat face; Hertzian ``sqrt(1 - r^2/a^2)`` over a round object's patch), spread by the
silicone skin (a Gaussian blur), and summed per taxel. Shear comes from the soft object's
lateral bulge, limited by friction, plus a common part from imperfect alignment. Counts: gains
per newton, a little electrical cross-talk from z into x/y, then what the pads do with no load
at all (:class:`SkinDraw`, :class:`PadNoise`), fitted to real XR1944 recordings
(``tests/fixtures/xela/real-xr1944/``, compared by ``tests/sim/test_pad_noise.py``):

- idle offsets: a level per pad and axis (x ~15.9k, y ~16.4k, z ~38k counts) and a spread
  across the taxels of a pad (std ~220 / ~160 / ~500 counts);
- noise of three kinds, each per axis: white noise per sample; a per-taxel wander (a damped
  oscillation of a few Hz), which is why the std over a second (~3.4 / ~2.5 / ~6 counts) is
  about twice the sample-to-sample noise (~1.9 / ~1.2 / ~4.2); and a disturbance shared by
  every taxel of both pads (a damped ~7.5 Hz oscillation), strong in x and z, that the
  second pad, facing the first, sees mirrored: this cross-talk makes x correlate between
  the taxels of a pad (~0.5) and the pad means of x and z with each other (~0.9);
- drift: a per-channel rate of a few counts per second at the start that levels off over
  minutes, at hundreds of counts;
- 16-bit saturation.

The noise is a continuous-time process: a frame at any time ``t`` (any rate, uneven spacing)
continues the previous one exactly.

Channel order everywhere: ``(pad * taxels_per_pad + taxel) * 3 + axis`` (``pad * 48 + taxel *
3 + axis`` on the XR1944), taxels row-major from the top left.
"""

from __future__ import annotations

import cmath
import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from edge.core.layout import XR1944, PadLayout
from edge.sim.contact import ObjectInstance

_AXES = 3
PADS = 2
TAXELS = 16
CHANNELS = PADS * TAXELS * 3
TAXEL_PITCH_M = 4.7e-3
_SUB = 4  # sub-grid points per taxel per axis
_CELL_M = TAXEL_PITCH_M / _SUB


def pad_grid(layout: PadLayout) -> tuple[np.ndarray, np.ndarray]:
    """Sub-grid point coordinates (x[row, col], y[row, col]), pad centred on (0, 0). Every
    layout keeps the XR1944's pitch (docs/hardware.md, 'Other pad layouts')."""
    return _pad_grid(layout.rows, layout.cols)


def pad_size_m(layout: PadLayout) -> tuple[float, float]:
    """The face of a pad of ``layout``: (width, height) in metres."""
    return layout.cols * TAXEL_PITCH_M, layout.rows * TAXEL_PITCH_M


@functools.cache
def _pad_grid(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    def coord(n: int) -> np.ndarray:
        return (np.arange(n * _SUB) - (n * _SUB - 1) / 2.0) * _CELL_M

    return np.meshgrid(coord(cols), coord(rows))


# Sensitivity chosen so that x_th = 0.004 (~262 counts of total norm) is a gentle touch, as
# the paper describes: ~0.37 N per finger spread over a whole flat pad, ~0.13 N concentrated
# on one taxel.
GAIN_Z_COUNTS_PER_N = 2000.0
GAIN_XY_COUNTS_PER_N = 1000.0
# Not fitted to the fixture: its x follows z at about -0.3 x dz in two of its recordings, but
# those show an object moved by the arm, where real shear cannot be told from cross-talk.
XTALK_Z_TO_XY = 0.015
SKIN_SPREAD_M = 1.5e-3

# What the pads do unloaded. Every figure is per axis (x, y, z), in raw counts, measured on the
# real XR1944 recordings in tests/fixtures/xela/real-xr1944/ (two pads on a Franka gripper,
# ~60 frames/s; the first second of each of three recordings, while the arm only starts to
# move off (17 mm in that second) and the pad means stay within 10 counts; whether the
# gripper already held the object is not recorded; rows repeated by the recorder dropped) by
# tests/sim/test_pad_noise.py, which prints the fixture's figures next to the simulated pads'
# (pytest -s). "Fixture" below is the range over its 6 pad-recordings.
#
# Idle level of a pad: fixture pad means 15.75-15.96k / 16.38-16.45k / 37.66-38.64k (other
# uSkin models idle near 32.8k / 33.2k / 37k; the runtime tares, so only headroom depends on it).
IDLE_LEVEL_COUNTS = (15_850.0, 16_420.0, 38_050.0)
# Pad-to-pad (and day-to-day) spread of that level: the fixture's pad means differ by ~200 /
# ~60 / ~1000 counts across its pads and days.
PAD_LEVEL_SD_COUNTS = (100.0, 30.0, 400.0)
# Spread of the idle offsets across the taxels of one pad: fixture std 208-238 / 125-192 /
# 411-567 (max - min 717-882 / 420-737 / 1433-1994).
TAXEL_OFFSET_SD_COUNTS = (220.0, 160.0, 490.0)
# White noise per sample, independent per channel.
WHITE_NOISE_COUNTS = (0.5, 0.7, 2.0)
# A wander per channel: a damped oscillation (std, decay time, frequency; the fixture's
# autocorrelation turns negative after ~3 / ~5 / ~3 frames at 60 Hz, so it is not a plain
# low-pass). With the white noise and the disturbance below it gives the sample-to-sample
# noise (std of first differences / sqrt 2: fixture 1.77-2.20 / 1.15-1.57 / 4.02-4.79), the
# std over the idle second (3.21-3.87 / 2.08-3.52 / 5.02-6.58) and the lag-1 autocorrelation
# at ~60 Hz (0.63-0.72 / 0.67-0.81 / 0.45-0.59).
LOCAL_NOISE_COUNTS = (2.5, 2.45, 5.3)
LOCAL_NOISE_TAU_S = (0.2, 0.4, 0.05)
LOCAL_NOISE_HZ = (4.0, 3.3, 4.5)
# The shared disturbance: one process for both pads (unit std, autocorrelation
# exp(-|dt|/tau) cos(2 pi f dt): the fixture's pad means swing with a period of ~8 frames at
# 60 Hz), times a gain per axis: the std of the pad mean (fixture 2.11-2.70 / 0.54-0.97 /
# 2.32-3.13), the correlation of sample-to-sample changes between the taxels of a pad
# (0.46-0.56 / 0.08-0.11 / 0.04-0.10) and between the pad means of x and z (0.86-0.93) come
# from it. Each channel's gain varies by FIELD_GAIN_CV around the axis's; the second pad's is
# negated (pad-mean correlation between the pads in the fixture: -0.93 / -0.29..-0.53 /
# -0.67..-0.82). The fixture's pads were on a Franka arm: part of this may be that arm's, not
# the pads'; it is kept as measured.
FIELD_GAIN_COUNTS = (2.4, 0.6, 2.3)
FIELD_GAIN_CV = 0.2
FIELD_TAU_S = 0.16
FIELD_HZ = 7.5
# Drift: a rate per channel (std) at the start, levelling off with DRIFT_TAU_S, so a channel
# moves by up to rate * tau (hundreds of counts in z) over minutes. The fixture's slope over
# its idle second (median |slope| over taxels 0.48-0.95 / 0.38-0.92 / 1.84-3.72 counts/s) is
# mostly the wander above in x and y; z needs a rate of its own. Its offsets moved by ~60 /
# ~40 / ~300 counts per taxel (std) between recordings hours apart.
DRIFT_RATE_SD_COUNTS_PER_S = (0.2, 0.2, 2.5)
DRIFT_TAU_S = 300.0
def _per_axis(values: tuple[float, float, float], axis: np.ndarray) -> np.ndarray:
    return np.asarray(values, dtype=float)[axis]


@dataclass(frozen=True)
class SkinDraw:
    """Per-robot sensor state: idle offsets, drift rates and disturbance gains per channel."""

    offsets: np.ndarray  # (C,) counts at idle
    drift_per_s: np.ndarray  # (C,) counts per second at t = 0; it levels off (DRIFT_TAU_S)
    field_gain: np.ndarray | None = None  # (C,) counts per unit of the shared disturbance
    # Sensitivity to load relative to the XR1944 model above (GAIN_*_COUNTS_PER_N): another
    # pad, or another sensor, reads the same force on another scale with the same idle noise.
    gain: float = 1.0
    layout: PadLayout = XR1944

    @classmethod
    def draw(cls, rng: np.random.Generator, layout: PadLayout = XR1944) -> SkinDraw:
        pads, taxels = layout.pads, layout.taxels
        channels = pads * taxels * _AXES
        axis = np.tile(np.arange(_AXES), pads * taxels)
        pad = np.repeat(np.arange(pads), taxels * _AXES)
        level = (_per_axis(IDLE_LEVEL_COUNTS, axis)
                 + rng.normal(0.0, 1.0, (pads, _AXES))[pad, axis]
                 * _per_axis(PAD_LEVEL_SD_COUNTS, axis))
        offsets = level + rng.normal(0.0, 1.0, channels) * _per_axis(TAXEL_OFFSET_SD_COUNTS, axis)
        drift = rng.normal(0.0, 1.0, channels) * _per_axis(DRIFT_RATE_SD_COUNTS_PER_S, axis)
        # Facing pads: the second one sees the shared disturbance mirrored.
        mirror = np.where(pad % 2 == 1, -1.0, 1.0)
        gain = (mirror * _per_axis(FIELD_GAIN_COUNTS, axis)
                * (1.0 + FIELD_GAIN_CV * rng.normal(0.0, 1.0, channels)))
        return cls(offsets, drift, gain, layout=layout)

    def drift(self, t_s: float) -> np.ndarray:
        """Drift in counts at ``t_s`` seconds: ``rate * t`` at first, ``rate * tau`` at most."""
        return self.drift_per_s * (DRIFT_TAU_S * -np.expm1(-max(t_s, 0.0) / DRIFT_TAU_S))


class PadNoise:
    """The noise of unloaded pads as a continuous-time process, one :meth:`sample` per frame.

    White noise per sample, a damped-oscillation wander per channel and the disturbance
    shared by all channels (each the real part of a rotating complex Ornstein-Uhlenbeck
    process), the last two advanced exactly over the time since the previous sample, so they
    do not depend on the frame rate or on even spacing. The first sample starts every
    process in its stationary distribution.
    """

    def __init__(self, draw: SkinDraw, rng: np.random.Generator) -> None:
        channels = len(draw.offsets)
        # State and parameters as (taxels, axis): per-axis figures broadcast, no gathers.
        self._shape = (channels // _AXES, _AXES)
        self._rng = rng
        self._white = np.asarray(WHITE_NOISE_COUNTS, dtype=float)
        self._local_sd = np.asarray(LOCAL_NOISE_COUNTS, dtype=float)
        self._tau = np.asarray(LOCAL_NOISE_TAU_S, dtype=float)
        self._omega = 2 * np.pi * np.asarray(LOCAL_NOISE_HZ, dtype=float)
        self._gain = (np.zeros(self._shape) if draw.field_gain is None
                      else np.asarray(draw.field_gain, dtype=float).reshape(self._shape))
        self._t: float | None = None
        self._local = np.zeros(self._shape, dtype=complex)
        self._field = 0j

    def sample(self, t_s: float) -> np.ndarray:
        """Noise in counts, shape (C,), at time ``t_s`` (s; later than the last sample)."""
        m = self._shape[0] * _AXES
        z = self._rng.standard_normal(3 * m + 2)
        white = z[:m].reshape(self._shape)
        # Each process is the real part of a rotating complex Ornstein-Uhlenbeck process
        # with unit variance per part: over dt it decays by exp(-dt/tau), turns by
        # omega * dt, and takes a kick of sqrt(1 - decay^2) standard complex normal. Its
        # real part then has unit variance and autocorrelation exp(-|dt|/tau) cos(omega dt).
        # (Pairs of independent normals read as complex numbers: no copy.)
        local_kick = z[m:3 * m].view(np.complex128).reshape(self._shape)
        field_kick = complex(z[-2], z[-1])
        if self._t is None:
            self._local, self._field = local_kick, field_kick
        else:
            dt = max(t_s - self._t, 0.0)
            decay = np.exp(-dt / self._tau)
            self._local = (self._local * (decay * np.exp(1j * self._omega * dt))
                           + np.sqrt(1.0 - decay * decay) * local_kick)
            fdecay = math.exp(-dt / FIELD_TAU_S)
            self._field = (self._field * fdecay * cmath.exp(2j * math.pi * FIELD_HZ * dt)
                           + math.sqrt(1.0 - fdecay * fdecay) * field_kick)
        self._t = t_s
        out = (self._white * white + self._local_sd * self._local.real
               + self._gain * self._field.real)
        return out.reshape(-1)


class Skin:
    """Renders raw frames for one object instance pressed by both fingers."""

    def __init__(self, inst: ObjectInstance, rng: np.random.Generator,
                 draw: SkinDraw | None = None) -> None:
        self.inst = inst
        self.rng = rng
        self.draw = draw if draw is not None else SkinDraw.draw(rng)
        self.noise = PadNoise(self.draw, rng)
        self.layout = self.draw.layout
        self._gx, self._gy = pad_grid(self.layout)
        self._flat_cache: list[np.ndarray | None] = [None] * self.layout.pads

    def _pressure(self, pad: int, contact_radius_m: float) -> np.ndarray:
        """Normalised pressure on the pad's sub-grid (sums to 1), after the skin's spread."""
        cx, cy = self.inst.patch_offsets_m[pad % 2]
        gx, gy = self._gx, self._gy
        obj = self.inst.cls
        if obj.shape == "flat":
            cached = self._flat_cache[pad]
            if cached is not None:
                return cached
            half = obj.size_m / 2.0
            inside = (np.abs(gx - cx) <= half) & (np.abs(gy - cy) <= half)
            tx, ty = self.inst.tilt
            p = np.where(inside, np.clip(1.0 + tx * (gx - cx) + ty * (gy - cy), 0.0, None),
                         0.0)
        else:
            a = max(contact_radius_m, 0.6 * _CELL_M)
            r2 = ((gx - cx) ** 2 + (gy - cy) ** 2) / (a * a)
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

    def forces(self, force_n: float, contact_radius_m: float) -> np.ndarray:
        """Force on each taxel in newtons, x, y, z, shape (C,): what a calibrated sensor
        reports (xela_server's ``calibrated``), whatever the pads' gain."""
        return self._forces(force_n, contact_radius_m).reshape(-1)

    def loads(self, force_n: float, contact_radius_m: float) -> np.ndarray:
        """Noise-free change in counts, shape (C,), for a per-finger force."""
        out = self._forces(force_n, contact_radius_m)
        out[..., 0:2] *= GAIN_XY_COUNTS_PER_N
        out[..., 2] *= GAIN_Z_COUNTS_PER_N
        out[..., 0:2] += XTALK_Z_TO_XY * out[..., 2:3]
        return self.draw.gain * out.reshape(-1)

    def _forces(self, force_n: float, contact_radius_m: float) -> np.ndarray:
        lay = self.layout
        out = np.zeros((lay.pads, lay.taxels, 3))
        if force_n <= 0.0:
            return out
        obj = self.inst.cls
        bulge = min(obj.bulge, obj.mu)
        for pad in range(lay.pads):
            p = self._pressure(pad, contact_radius_m) * force_n
            cx, cy = self.inst.patch_offsets_m[pad % 2]
            extent = max(obj.size_m / 2.0 if obj.shape == "flat" else contact_radius_m,
                         _CELL_M)
            sx = p * (bulge * (self._gx - cx) / extent + self.inst.common_shear[0])
            sy = p * (bulge * (self._gy - cy) / extent + self.inst.common_shear[1])
            if pad % 2 == 1:
                sx = -sx  # the second pad faces the first: its x axis is mirrored
            for axis, field in enumerate((sx, sy, p)):
                taxel = field.reshape(lay.rows, _SUB, lay.cols, _SUB).sum(axis=(1, 3)).reshape(-1)
                out[pad, :, axis] = taxel
        return out

    def frame(self, t_s: float, force_n: float, contact_radius_m: float) -> np.ndarray:
        """Raw uint16 counts at press time ``t_s`` (seconds since the press began)."""
        values = (self.draw.offsets + self.draw.drift(t_s)
                  + self.loads(force_n, contact_radius_m)
                  + self.noise.sample(t_s))
        return np.clip(np.rint(values), 0, 65535).astype(np.uint16)
