"""The object catalogue: every class the simulated robot can press.

Each class carries the physical parameters of the press model (:mod:`edge.sim.contact`) and
the one-line description that goes into the tactile-to-text database.

Where the magnitudes come from (orders of magnitude, not measurements of our objects):
- Young's moduli: metals and glass from handbooks (steel 193 GPa, aluminium 69 GPa, glass
  70 GPa); hardwood 10 GPa along the grain; cast acrylic and epoxy/PU resin 1-3 GPa; rubbers
  1-5 MPa, platinum silicones 0.1-0.5 MPa, PU foams 10-100 kPa; food texture literature for
  foods (gelatin gels 5-30 kPa, konjac and tofu gels 10-50 kPa, raw apple 3-6 MPa, kiwi
  ~0.3 MPa, raw pumpkin flesh 5-10 MPa falling several-fold when boiled (a piece squeezed
  across its rind: about twofold), dried kiri mochi tens of MPa against a few kPa boiled).
- Stress relaxation: Prony terms (fraction g, time constant tau) of quasi-linear
  viscoelasticity; food gels and doughs relax 20-60 % within a second, rigid solids do not.
- Yield: foods that crush or dent (macaron shells, bread, bean bags) carry a per-finger force
  past which they deform plastically; rigid solids have none within the gripper's force.
- Friction mu and bulge (Poisson-like lateral expansion of soft bodies) shape the shear.
- The skin of the tactile pad (a silicone layer, ~4e4 N/m) sits in series with the object, so
  objects much stiffer than the skin all feel nearly alike: a real canele (crust ~10 MPa) is
  close to its resin replica, raw and boiled kabocha are close under a gentle push, while
  boiled kiri mochi (kPa) is far softer than raw (tens of MPa).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Shape = Literal["flat", "round"]
Split = Literal["train", "val", "foodreplica", "cube"]

# Pad area of one XR1944 (4 x 4 taxels at 4.7 mm pitch).
PAD_SIDE_M = 4 * 4.7e-3


@dataclass(frozen=True)
class ObjectClass:
    name: str
    description: str
    split: Split
    shape: Shape
    width_m: float  # squeezed dimension, finger to finger
    size_m: float  # flat: side of the contact face; round: radius of curvature
    youngs_pa: float
    # Prony series of the normalised relaxation function: ((g_i, tau_i_s), ...).
    prony: tuple[tuple[float, float], ...] = ()
    damping_ns_per_m: float = 0.0
    yield_n: float | None = None  # per-finger force at which plastic flow starts
    mu: float = 0.5
    bulge: float = 0.0
    width_sd_m: float = 0.3e-3
    youngs_cv: float = 0.05  # per-press coefficient of variation of the modulus
    exponent: float | None = None  # elastic law F = k d**n; default 1 (flat), 1.5 (round)
    # Press threshold for this class when recording references; None: the press default.
    # Very fragile objects (gelatins) are pressed gentler, as in the paper (x_th = 0.003).
    x_th: float | None = None

    @property
    def elastic_exponent(self) -> float:
        if self.exponent is not None:
            return self.exponent
        return 1.0 if self.shape == "flat" else 1.5


def _c(name, description, split, shape, width_mm, size_mm, youngs_pa, **kw) -> ObjectClass:
    return ObjectClass(name, description, split, shape, width_mm * 1e-3, size_mm * 1e-3,
                       youngs_pa, **kw)


# Viscoelastic presets: (fraction, time constant s).
_GEL = ((0.15, 0.08), (0.15, 0.6))
_FOOD = ((0.2, 0.1), (0.2, 0.8))
_DOUGH = ((0.3, 0.05), (0.3, 0.5))
_RUBBER = ((0.05, 0.1),)

REFERENCE: tuple[ObjectClass, ...] = (
    # --- training classes (27) ---
    _c("wood_cube", "wood cube", "train",
       "flat", 25, 25, 10e9, mu=0.45),
    _c("stainless_cube", "stainless steel cube", "train",
       "flat", 25, 25, 193e9, mu=0.3),
    _c("aluminium_cube", "aluminium cube", "train",
       "flat", 25, 25, 69e9, mu=0.35),
    _c("acrylic_cube", "acrylic cube", "train",
       "flat", 25, 25, 3e9, mu=0.4),
    _c("rubber_cube", "rubber cube", "train",
       "flat", 25, 25, 2e6, prony=_RUBBER, mu=0.9, bulge=0.2, youngs_cv=0.08),
    _c("silicone_cube", "silicone rubber cube", "train",
       "flat", 25, 25, 0.3e6, prony=_RUBBER, mu=1.0, bulge=0.35, youngs_cv=0.08),
    _c("sponge_cube", "kitchen sponge cut into a cube",
       "train", "flat", 28, 28, 20e3, exponent=1.6, damping_ns_per_m=5.0, mu=0.8,
       width_sd_m=1.0e-3, youngs_cv=0.12),
    _c("cork_cube", "cork cube", "train",
       "flat", 25, 25, 20e6, prony=((0.1, 0.3),), mu=0.6),
    _c("eraser", "rubber eraser", "train",
       "flat", 20, 20, 5e6, prony=((0.1, 0.2),), mu=0.9, bulge=0.15),
    _c("glass_marble", "glass marble", "train",
       "round", 16, 8, 70e9, mu=0.3, width_sd_m=0.1e-3),
    _c("rubber_ball", "rubber ball", "train",
       "round", 25, 12.5, 3e6, prony=_RUBBER, mu=0.9, bulge=0.2),
    _c("foam_ball", "foam ball", "train",
       "round", 30, 15, 40e3, exponent=1.8, damping_ns_per_m=3.0, mu=0.7,
       width_sd_m=0.8e-3, youngs_cv=0.1),
    _c("gelatin_soft", "gelatin jelly made with 2 % gelatin", "train",
       "flat", 28, 25, 6e3, prony=_GEL, damping_ns_per_m=8.0, mu=0.3, bulge=0.5,
       width_sd_m=1.0e-3, youngs_cv=0.15, x_th=0.003),
    _c("tofu_firm", "momen tofu (Japanese cotton tofu)", "train",
       "flat", 28, 25, 30e3, prony=_FOOD, damping_ns_per_m=6.0, yield_n=2.5, mu=0.35,
       bulge=0.45, width_sd_m=1.0e-3, youngs_cv=0.15),
    _c("marshmallow", "marshmallow", "train",
       "flat", 28, 25, 15e3, prony=((0.25, 0.15), (0.25, 1.0)), exponent=1.4,
       damping_ns_per_m=6.0, mu=0.8, bulge=0.4, width_sd_m=1.5e-3, youngs_cv=0.15),
    _c("bread_cube", "cube of white bread", "train",
       "flat", 28, 25, 12e3, prony=_FOOD, exponent=1.3, yield_n=0.6, mu=0.7,
       bulge=0.1, width_sd_m=1.5e-3, youngs_cv=0.2),
    _c("otedama", "otedama (a small Japanese cloth beanbag filled with beans)", "train",
       "flat", 30, 28, 60e3, prony=((0.3, 0.05), (0.2, 0.4)), damping_ns_per_m=20.0,
       yield_n=0.5, mu=0.8, bulge=0.3, width_sd_m=1.5e-3, youngs_cv=0.15),
    _c("clay", "lump of modelling clay",
       "train", "flat", 25, 22, 0.4e6, prony=_DOUGH, damping_ns_per_m=30.0, yield_n=1.0,
       mu=0.8, bulge=0.3, width_sd_m=1.0e-3, youngs_cv=0.12),
    _c("kiwi_piece", "piece of kiwi fruit", "train",
       "flat", 22, 20, 0.3e6, prony=_FOOD, damping_ns_per_m=5.0, yield_n=3.0, mu=0.15,
       bulge=0.4, width_sd_m=1.5e-3, youngs_cv=0.2),
    _c("apple_piece", "piece of raw apple", "train",
       "flat", 22, 20, 4e6, prony=((0.1, 0.2),), mu=0.3, bulge=0.1,
       width_sd_m=1.0e-3, youngs_cv=0.12),
    _c("banana_piece", "slice of banana", "train",
       "round", 28, 14, 0.15e6, prony=_FOOD, damping_ns_per_m=5.0, yield_n=1.5, mu=0.25,
       bulge=0.4, width_sd_m=1.5e-3, youngs_cv=0.2),
    _c("cheese_cube", "cube of processed cheese",
       "train", "flat", 22, 20, 0.25e6, prony=_DOUGH, mu=0.5, bulge=0.35,
       youngs_cv=0.12),
    _c("quail_egg_boiled", "boiled quail egg", "train",
       "round", 25, 12, 0.12e6, prony=_GEL, mu=0.3, bulge=0.3, youngs_cv=0.12),
    _c("grape", "grape", "train",
       "round", 20, 10, 0.1e6, prony=_FOOD, damping_ns_per_m=3.0, yield_n=4.0, mu=0.3,
       bulge=0.2, width_sd_m=1.0e-3, youngs_cv=0.15),
    _c("gummy_candy", "gummy candy", "train",
       "flat", 20, 18, 0.5e6, prony=((0.2, 0.15), (0.1, 1.0)), mu=0.9, bulge=0.3,
       youngs_cv=0.1),
    _c("dango", "dango (a Japanese rice-flour dumpling)", "train",
       "round", 26, 13, 25e3, prony=_DOUGH, damping_ns_per_m=15.0, yield_n=1.2, mu=0.9,
       bulge=0.45, width_sd_m=1.5e-3, youngs_cv=0.15),
    _c("cotton_ball", "cotton ball", "train",
       "round", 28, 14, 4e3, exponent=2.2, damping_ns_per_m=2.0, yield_n=0.8, mu=0.9,
       width_sd_m=2.0e-3, youngs_cv=0.2),
    # --- validation classes (5) ---
    _c("gelatin_hard", "gelatin jelly made with 6 % gelatin", "val",
       "flat", 28, 25, 30e3, prony=_GEL, damping_ns_per_m=8.0, mu=0.3, bulge=0.5,
       width_sd_m=1.0e-3, youngs_cv=0.15, x_th=0.003),
    _c("cherry_tomato", "cherry tomato", "val",
       "round", 25, 12.5, 0.2e6, prony=_FOOD, damping_ns_per_m=3.0, mu=0.3, bulge=0.2,
       width_sd_m=1.0e-3, youngs_cv=0.15),
    _c("yokan", "yokan (a block of Japanese sweet red-bean jelly)", "val",
       "flat", 22, 22, 80e3, prony=_GEL, damping_ns_per_m=6.0, mu=0.4, bulge=0.45,
       youngs_cv=0.12),
    _c("plastic_cube", "plastic cube", "val",
       "flat", 25, 25, 2e9, mu=0.4),
    _c("soap_bar", "bar of soap", "val",
       "flat", 22, 25, 0.1e9, prony=((0.05, 0.3),), mu=0.2),
)


def _pair(name, description, shape, width_mm, size_mm, youngs_pa, replica_pa, **kw):
    """A real food and its resin twin: same shape and size, different material."""
    real = _c(name, description, "foodreplica", shape, width_mm, size_mm, youngs_pa,
              width_sd_m=1.0e-3, youngs_cv=0.15, **kw)
    replica = _c(f"resin_replica_{name}", f"a resin replica of {name.replace('_', ' ')}",
                 "foodreplica", shape, width_mm, size_mm, replica_pa, mu=0.4,
                 width_sd_m=0.3e-3, youngs_cv=0.05,
                 # Soft-vinyl replicas creep a little; hard resin does not.
                 prony=((0.05, 0.3),) if replica_pa < 0.1e9 else ())
    return real, replica


FOODREPLICA: tuple[ObjectClass, ...] = (
    # Caramelised crust ~10 MPa: stiffer than the skin, so nearly as hard as its replica.
    *_pair("canele", "", "flat", 32, 25, 10e6, 1.5e9, prony=((0.08, 0.3),), mu=0.5),
    # Konjac food samples are moulded soft PVC (Shore ~A90, ~20 MPa): far stiffer than the
    # skin, so pressed from the side the replica feels like the hard-resin chocolate one.
    *_pair("konjac", "", "flat", 25, 22, 40e3, 20e6, prony=((0.1, 0.2),),
           damping_ns_per_m=4.0, mu=0.1, bulge=0.5),
    # Solid chocolate (~0.3 GPa) against resin: expected to be hard to tell apart by touch.
    *_pair("chocolate", "", "flat", 20, 20, 0.3e9, 2e9, mu=0.4),
    *_pair("ikura_sushi", "", "flat", 28, 22, 30e3, 1.5e9, prony=_DOUGH,
           damping_ns_per_m=10.0, yield_n=0.6, mu=0.6, bulge=0.4),
    # A crisp shell that cracks (yields) past ~1.5 N: a gentle press spares it, a late stop
    # does not.
    *_pair("macaron", "", "flat", 25, 30, 2e6, 1.5e9, prony=((0.1, 0.1),), yield_n=1.5,
           mu=0.5),
    *_pair("strawberry", "", "round", 28, 14, 0.2e6, 5e6, prony=_FOOD,
           damping_ns_per_m=3.0, yield_n=3.0, mu=0.4, bulge=0.2),
    *_pair("cream_puff", "", "round", 34, 17, 20e3, 1.5e9, prony=_FOOD, yield_n=0.6,
           mu=0.6, bulge=0.2),
    *_pair("melon_pan", "", "flat", 34, 30, 40e3, 1.5e9, prony=_FOOD, exponent=1.3,
           yield_n=1.0, mu=0.7, bulge=0.1),
    *_pair("gyoza", "", "flat", 22, 20, 50e3, 1.5e9, prony=_DOUGH, damping_ns_per_m=8.0,
           yield_n=1.2, mu=0.6, bulge=0.35),
    *_pair("tamagoyaki", "", "flat", 25, 22, 60e3, 3e6, prony=((0.2, 0.1), (0.1, 0.8)),
           damping_ns_per_m=5.0, mu=0.4, bulge=0.4),
    *_pair("onigiri", "", "flat", 30, 28, 40e3, 1.5e9, prony=_DOUGH,
           damping_ns_per_m=10.0, yield_n=1.0, mu=0.7, bulge=0.35),
)

CUBE: tuple[ObjectClass, ...] = (
    # Raw pumpkin flesh 5-10 MPa; boiled a few-fold softer but still near the skin's
    # stiffness, so the two are close under a gentle push.
    # Kabocha pieces are squeezed across their rind, which stays firm when the flesh softens:
    # the piece's effective modulus only halves (flesh ~8 -> ~3 MPa, rind ~20 MPa in series),
    # both far stiffer than the pad's skin, with a per-piece spread (rind thickness, ripeness)
    # as large as the difference; boiling adds a little creep. So under the gentle push they
    # feel alike, as the paper found (raw read as boiled).
    _c("raw_kabocha_squash", "", "cube", "flat", 20, 20, 10e6, prony=((0.05, 0.2),),
       mu=0.4, width_sd_m=0.8e-3, youngs_cv=0.25),
    _c("boiled_kabocha_squash", "", "cube", "flat", 20, 20, 5e6,
       prony=((0.07, 0.2), (0.03, 0.8)), damping_ns_per_m=1.0, mu=0.4,
       bulge=0.1, width_sd_m=0.8e-3, youngs_cv=0.25),
    # Dried kiri mochi is hard; boiled it is a soft, sticky, flowing dough.
    _c("raw_kiri_mochi", "", "cube", "flat", 20, 20, 50e6, mu=0.4, width_sd_m=0.5e-3,
       youngs_cv=0.1),
    _c("boiled_kiri_mochi", "", "cube", "flat", 22, 20, 8e3,
       prony=((0.35, 0.1), (0.3, 0.7)), damping_ns_per_m=25.0, yield_n=0.8, mu=0.9,
       bulge=0.5, width_sd_m=1.5e-3, youngs_cv=0.2),
)

DATASETS: dict[str, tuple[ObjectClass, ...]] = {
    "reference": REFERENCE,
    "foodreplica": FOODREPLICA,
    "cube": CUBE,
}

_BY_NAME: dict[str, ObjectClass] = {o.name: o for ds in DATASETS.values() for o in ds}


def get(name: str) -> ObjectClass:
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(
            f"unknown object {name!r}; known: {', '.join(sorted(_BY_NAME))}"
        ) from None


def names(dataset: str | None = None) -> list[str]:
    if dataset is None:
        return sorted(_BY_NAME)
    return [o.name for o in DATASETS[dataset]]
