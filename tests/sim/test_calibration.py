"""The simulated world behaves like the paper's, the only real observations there are
(DESIGN section 1, a gentle push at x_th = 0.004), seen through the shipped encoder: by touch
boiled kiri mochi's neighbours are soft references and raw kiri mochi's hard ones; raw and
boiled kabocha, a real canele and its replica, and the konjac and chocolate replicas differ
far less by touch than raw and boiled kiri mochi."""

from __future__ import annotations

import numpy as np
import pytest

from edge.core.model import load_model, model_ref
from edge.lab.record import record_press
from edge.runtime.compute import analyse_press
from edge.sim.catalogue import DATASETS, get
from tests.support.daemon import ROOT
from train.eval.evaluate import pair_auc

PRESSES = 8
SEED = 7
# Reference classes by what the catalogue makes them: far softer or far stiffer than the
# pad's skin (about 4e4 N/m per finger, a few MPa for these sizes): below 1 MPa, or from
# 10 MPa up (cork, soap and every rigid cube; the line sat at 100 MPa until a release placed
# raw kiri mochi beside cork and soap, both far stiffer than the skin).
SOFT = {c.name for c in DATASETS["reference"] if c.youngs_pa < 1e6}
HARD = {c.name for c in DATASETS["reference"] if c.youngs_pa >= 1e7}


@pytest.fixture(scope="module")
def embed():
    ref = model_ref(ROOT / "models")
    cache: dict[str, np.ndarray] = {}

    def z_of(name: str) -> np.ndarray:
        if name not in cache:
            get(name)
            presses = [record_press(name, np.random.default_rng([SEED, i])).recording
                       for i in range(PRESSES)]
            cache[name] = np.array([analyse_press(ref, rec).z for rec in presses])
        return cache[name]

    return z_of


def test_kiri_mochi_pair_separates_as_in_the_paper(embed):
    auc = pair_auc(embed("raw_kiri_mochi"), embed("boiled_kiri_mochi"))["auc"]
    print(f"raw vs boiled kiri mochi: AUC {auc:.2f}")
    assert auc >= 0.9


@pytest.mark.parametrize(("a", "b"), [
    ("raw_kabocha_squash", "boiled_kabocha_squash"),
    ("canele", "resin_replica_canele"),
    ("resin_replica_konjac", "resin_replica_chocolate"),
])
def test_pairs_the_paper_found_alike_lie_far_nearer_than_kiri_mochi(embed, a, b):
    # What the world must give is the contrast: these pairs differ far less by touch than
    # raw and boiled kiri mochi. Whether an encoder still separates them (the shipped one
    # does raw and boiled kabocha, where the paper's did not) is the evaluation's to report.
    kiri = pair_auc(embed("raw_kiri_mochi"), embed("boiled_kiri_mochi"))["separation"]
    sep = pair_auc(embed(a), embed(b))["separation"]
    print(f"{a} vs {b}: separation {sep:.2f} against kiri mochi's {kiri:.2f}")
    assert sep < 0.5 * kiri


def test_kiri_mochi_neighbours_by_touch(embed):
    model = load_model(ROOT / "models")
    def neighbours(name: str) -> list[str]:
        votes: dict[str, int] = {}
        for z in embed(name):
            for label, _ in model.topk(z, 3):
                votes[label] = votes.get(label, 0) + 1
        return sorted(votes, key=votes.get, reverse=True)[:3]

    boiled, raw = neighbours("boiled_kiri_mochi"), neighbours("raw_kiri_mochi")
    print(f"boiled kiri mochi feels like {boiled}; raw like {raw}")
    assert sum(n in SOFT for n in boiled) >= 2
    assert sum(n in HARD for n in raw) >= 2
