"""Familiarity: a query's nearest-reference distance as a percentile of the database's own
leave-one-out nearest-neighbour distances, leaving out the reference's whole press, in the
space retrieval compares; and the setting that flags a press unfamiliar."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from edge.core.config import config_from_dict
from edge.core.errors import ConfigError
from edge.core.model import ClassInfo, Familiarity, ReferenceDatabase, load_model

MODELS = Path(__file__).resolve().parents[2] / "models"


def _db(z, label_index, source, space="z", codebook=None):
    z = np.asarray(z, dtype=np.float32)
    codebook = z.copy() if codebook is None else np.asarray(codebook, dtype=np.float32)
    code = np.argmin(((z[:, None] - codebook) ** 2).sum(-1), axis=1)
    classes = [ClassInfo(f"c{i}", f"object {i}", "train") for i in range(max(label_index) + 1)]
    return ReferenceDatabase(classes, z, codebook[code], code, label_index, source, codebook,
                             space)


def test_a_press_is_left_out_whole_not_offset_by_offset():
    # Two presses of one class, two offsets each, nearly the same within a press: without
    # leaving out the whole press every reference's nearest would be its twin (0.01 away).
    z = [[0, 0], [0.01, 0], [1, 0], [1.01, 0]]
    db = _db(z, [0, 0, 0, 0], ["a", "a", "b", "b"])
    np.testing.assert_allclose(db.nearest_other_press(), [1.0, 0.99, 0.99, 1.0], atol=1e-6)
    # A press is a source within a class: the same file name in two classes is two presses.
    db = _db(z, [0, 0, 1, 1], ["same", "same", "same", "same"])
    np.testing.assert_allclose(db.nearest_other_press(), [1.0, 0.99, 0.99, 1.0], atol=1e-6)
    # One press alone has no neighbour: no figure rather than a made-up one.
    lone = _db(z[:2], [0, 0], ["a", "a"])
    assert np.all(np.isinf(lone.nearest_other_press()))
    assert Familiarity(lone).percentile(0.5) is None


def test_the_distances_equal_a_brute_force_in_blocks_and_in_the_quantised_space():
    rng = np.random.default_rng(3)
    n = 300
    z = rng.standard_normal((n, 4)).astype(np.float32)
    label_index = np.sort(rng.integers(0, 6, n))
    label_index[:6] = np.arange(6)
    label_index.sort()
    source = [f"p{i}" for i in rng.integers(0, 20, n)]
    codebook = rng.standard_normal((8, 4)).astype(np.float32)
    for space in ("z", "z_q"):
        db = _db(z, label_index, source, space, codebook)
        refs = (db.z if space == "z" else db.z_q).astype(np.float64)
        press = [f"{c}/{s}" for c, s in zip(db.label_index, db.source, strict=True)]
        want = [min((np.linalg.norm(refs[i] - refs[j]) for j in range(n)
                     if press[j] != press[i]), default=np.inf) for i in range(n)]
        np.testing.assert_allclose(db.nearest_other_press(block=7), want, atol=1e-6)


def test_the_percentile_ranks_a_distance_among_the_leave_one_out_distances():
    z = [[0, 0], [1, 0], [3, 0], [7, 0]]  # each its own press: LOO distances 1, 1, 2, 4
    fam = Familiarity(_db(z, [0, 1, 2, 3], ["a", "b", "c", "d"]))
    np.testing.assert_allclose(fam.loo, [1, 1, 2, 4])
    assert fam.percentile(0.0) == 0.0  # closer than every reference's nearest other press
    assert fam.percentile(1.0) == 0.0  # as close as the closest: none strictly closer
    assert fam.percentile(1.5) == 50.0
    assert fam.percentile(3.0) == 75.0
    assert fam.percentile(4.5) == 100.0  # farther than all


def test_familiarity_on_the_shipped_model():
    db = load_model(MODELS).database
    t0 = time.perf_counter()
    fam = Familiarity(db)
    took = time.perf_counter() - t0
    print(f"leave-one-out distances of the shipped {len(db)} references "
          f"({len(db.classes)} classes): {took * 1e3:.0f} ms; median "
          f"{np.median(fam.loo):.4f}, max {fam.loo[-1]:.4f}")
    assert fam.loo.size == len(db) == 1600 and np.all(fam.loo > 0)
    assert took < 5.0  # generous: tens of milliseconds on a quiet host
    # A reference's own press is in the database: its embedding scores 0.
    for i in (0, 777, 1599):
        nearest = db.topk(db.z[i], 1)[0]
        assert nearest[0] == db.labels[db.label_index[i]]
        assert fam.percentile(nearest[1]) == 0.0
    # Each reference's leave-one-out distance ranks as it does among the others: half of
    # them lie below the middle.
    ranks = [fam.percentile(d) for d in db.nearest_other_press()]
    assert 40 < np.median(ranks) < 60
    # A point far from every reference scores 100.
    far = np.full(db.dim, 50.0, dtype=np.float32)
    assert fam.percentile(db.topk(far, 1)[0][1]) == 100.0


@pytest.mark.parametrize("value", [0, -5, 100.5, 1000])
def test_the_unfamiliar_percentile_is_checked_naming_the_field(value):
    with pytest.raises(ConfigError, match=r"runtime\.unfamiliar_percentile = .*: must be a "
                                          r"percentile in \(0, 100\]"):
        config_from_dict({"runtime": {"unfamiliar_percentile": value}})
    assert config_from_dict({}).runtime.unfamiliar_percentile == 95.0
    assert config_from_dict({"runtime": {"unfamiliar_percentile": 100}}
                            ).runtime.unfamiliar_percentile == 100.0
