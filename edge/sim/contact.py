"""Contact mechanics of one object squeezed between two gripper fingers.

Per finger, the approach ``d = (width - gap) / 2`` is shared between the silicone skin of the
tactile pad (a linear spring ``k_skin``) and the object, in series:

    k_skin * (d - delta) = F_obj(delta)

The object force is quasi-linear viscoelastic (Fung): an elastic law ``F_e = k * delta_e**n``
convolved with a normalised relaxation function ``G(t) = g_inf + sum g_i exp(-t/tau_i)``
(Prony series), plus viscous damping ``c * d(delta)/dt``. Plastic flow keeps ``F_e`` at the
yield force while the object is pushed past it; the permanent set ``delta_p`` is not
recovered on release. The object never pulls on the finger (no adhesion): the force is
clamped at zero, and contact is lost once the approach falls below the permanent set.

The model is deterministic; per-press variation comes from :class:`ObjectInstance`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edge.sim.catalogue import PAD_SIDE_M, ObjectClass

# Effective stiffness of the pad's silicone skin, per finger (see catalogue notes).
K_SKIN_N_PER_M = 4.0e4
# The series split is solved to this force tolerance (well under one count of noise).
_FORCE_TOL_N = 1e-7
_MAX_ITERS = 60


@dataclass(frozen=True)
class ObjectInstance:
    """One press's draw of an object class: the class with per-press variation applied."""

    cls: ObjectClass
    width_m: float
    k: float  # elastic law coefficient, N / m**n
    n: float
    patch_offsets_m: tuple[tuple[float, float], tuple[float, float]]  # per pad (x, y)
    tilt: tuple[float, float]  # pressure gradient across a flat face, 1/m
    common_shear: tuple[float, float]  # tangential/normal ratio from imperfect alignment

    @classmethod
    def draw(cls, obj: ObjectClass, rng: np.random.Generator,
             pad_m: tuple[float, float] = (PAD_SIDE_M, PAD_SIDE_M)) -> ObjectInstance:
        """``pad_m``: the pad's face (width, height): a flat face larger than it is loaded
        over the pad only."""
        width = max(obj.width_m + rng.normal(0.0, obj.width_sd_m), 0.3 * obj.width_m)
        youngs = obj.youngs_pa * math.exp(rng.normal(0.0, obj.youngs_cv))
        n = obj.elastic_exponent
        if obj.shape == "flat":
            # Compression of the loaded column: F = E A (2 delta / w).
            k = 2.0 * youngs * min(obj.size_m, pad_m[0]) * min(obj.size_m, pad_m[1]) / width
            if n != 1.0:
                # Strain-stiffening foams: same stiffness at 1 mm, steeper beyond.
                k = k * (1e-3) ** (1.0 - n)
        else:
            # Hertz, rigid flat finger on an incompressible sphere (nu = 0.5).
            k = (4.0 / 3.0) * youngs / 0.75 * math.sqrt(obj.size_m)
            if n != 1.5:
                k = k * (1e-3) ** (1.5 - n)
        offsets = tuple(
            (float(rng.normal(0.0, 1.5e-3)), float(rng.normal(0.0, 1.5e-3)))
            for _ in range(2)
        )
        tilt = (float(rng.normal(0.0, 15.0)), float(rng.normal(0.0, 15.0)))
        shear = (float(rng.normal(0.0, 0.04)), float(rng.normal(0.0, 0.04)))
        return cls(obj, width, k, n, offsets, tilt, shear)  # type: ignore[arg-type]


class Contact:
    """State of the squeeze; :meth:`step` advances it by ``dt`` for a given finger gap."""

    def __init__(self, inst: ObjectInstance, k_skin: float = K_SKIN_N_PER_M) -> None:
        self.inst = inst
        self.k_skin = k_skin
        obj = inst.cls
        # Plain floats, not arrays: a Prony series has one or two terms, and this runs at
        # 2 kHz in the emulators and the recorder, where numpy's per-call cost dominates.
        self._g = tuple(g for g, _ in obj.prony)
        self._tau = tuple(t for _, t in obj.prony)
        self._g_total = sum(self._g)
        self._g_inf = 1.0 - self._g_total
        if self._g_inf <= 0.0:
            raise ValueError(f"{obj.name}: Prony fractions must sum below 1")
        self._h = [0.0] * len(self._g)  # Prony internal forces
        self._decay_dt = -1.0
        self._decay: tuple[float, ...] = ()
        self.delta = 0.0  # object indentation per finger (elastic + plastic)
        self.delta_p = 0.0  # permanent set
        self.force = 0.0  # per-finger normal force, N
        self.approach = 0.0  # d: total per-finger approach including skin
        self._fe = 0.0  # elastic force at the last step

    def _elastic(self, delta: float) -> float:
        de = delta - self.delta_p
        if de <= 0.0:
            return 0.0
        fe = self.inst.k * de**self.inst.n
        y = self.inst.cls.yield_n
        return fe if y is None else min(fe, y)

    def _object_force(self, delta: float, h_sum: float, c_dt: float,
                      prev_delta: float) -> tuple[float, float]:
        """Object force at indentation ``delta`` after this step, and its derivative;
        ``h_sum`` is the decayed Prony forces less their share of the last elastic force."""
        fe = self._elastic(delta)
        f = self._g_inf * fe + h_sum + self._g_total * fe + c_dt * (delta - prev_delta)
        de = max(delta - self.delta_p, 1e-12)
        n = self.inst.n
        y = self.inst.cls.yield_n
        dfe = 0.0 if y is not None and fe >= y else self.inst.k * n * de ** (n - 1.0)
        return f, dfe + c_dt

    def step(self, gap_m: float, dt: float) -> float:
        """Advance by ``dt`` seconds with the fingers ``gap_m`` apart; return the force."""
        d = 0.5 * (self.inst.width_m - gap_m)
        self.approach = d
        obj = self.inst.cls
        if dt != self._decay_dt:
            self._decay_dt = dt
            self._decay = tuple(math.exp(-dt / tau) for tau in self._tau)
        h_decayed = [h * a for h, a in zip(self._h, self._decay, strict=True)]
        c_dt = obj.damping_ns_per_m / dt
        prev = self.delta
        if d <= self.delta_p and prev == self.delta_p and all(abs(h) <= 1e-9
                                                              for h in h_decayed):
            # Fully relaxed and clear of the fingers: nothing to solve.
            self._h = h_decayed
            self._fe = 0.0
            self.force = 0.0
            return 0.0
        # sum(h_decayed + g * (fe - fe_last)) = h_sum + g_total * fe.
        h_sum = sum(h_decayed) - self._g_total * self._fe

        def obj_force(x: float) -> tuple[float, float]:
            return self._object_force(x, h_sum, c_dt, prev)

        if d > self.delta_p and obj_force(d)[0] > 0.0:
            # In contact: the skin and the object share the approach.
            def squeeze(x: float) -> tuple[float, float]:
                f, df = obj_force(x)
                return f - self.k_skin * (d - x), df + self.k_skin

            delta = _solve_increasing(squeeze, self.delta_p, d, prev)
            force = self.k_skin * (d - delta)
        else:
            # Clear of the finger: the surface recovers on its own, no force on the pad.
            hi = max(prev, self.delta_p)
            if obj_force(self.delta_p)[0] >= 0.0:
                delta = self.delta_p
            elif obj_force(hi)[0] <= 0.0:
                delta = hi
            else:
                delta = _solve_increasing(obj_force, self.delta_p, hi, prev)
            force = 0.0
        fe = self._elastic(delta)
        y = obj.yield_n
        if y is not None and fe >= y:
            # Plastic flow: the elastic part stays at yield, the rest becomes permanent.
            de_yield = (y / self.inst.k) ** (1.0 / self.inst.n)
            self.delta_p = max(self.delta_p, delta - de_yield)
        self._h = [h + g * (fe - self._fe) for h, g in zip(h_decayed, self._g, strict=True)]
        self._fe = fe
        self.delta = delta
        self.force = max(force, 0.0)
        return self.force

    def contact_radius(self) -> float:
        """Radius of the contact patch on a pad for a round object (Hertz a = sqrt(R d))."""
        return math.sqrt(self.inst.cls.size_m * max(self.approach, 0.0))


def _solve_increasing(fn, lo: float, hi: float, start: float) -> float:
    """Root of an increasing ``fn`` (returning value, slope) in [lo, hi]: safeguarded Newton."""
    x = min(max(start, lo), hi)
    for _ in range(_MAX_ITERS):
        r, dr = fn(x)
        if abs(r) < _FORCE_TOL_N:
            break
        if r > 0:
            hi = x
        else:
            lo = x
        nxt = x - r / dr if dr > 0 else 0.5 * (lo + hi)
        x = nxt if lo < nxt < hi else 0.5 * (lo + hi)
    return x
