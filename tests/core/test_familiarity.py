"""Familiarity: how much nearer a query's nearest class is than its eighth nearest, as a
percentile of the same ratio of every reference against the rest of the database, leaving
out the reference's whole press, in the space retrieval compares; that it tells new objects'
presses from known ones'; and the setting that flags a press unfamiliar."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from edge.core import preprocess
from edge.core.config import config_from_dict
from edge.core.errors import ConfigError
from edge.core.model import (
    FAMILIARITY_CLASSES,
    ClassInfo,
    Familiarity,
    ReferenceDatabase,
    load_model,
)
from edge.lab.teaching_eval import roc_auc
from tests.support.presses import recording_of

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
    np.testing.assert_allclose(db.nearest_other_press()[:, 0], [1.0, 0.99, 0.99, 1.0],
                               atol=1e-6)
    # A press is a source within a class: the same file name in two classes is two presses;
    # each reference has a figure per class.
    db = _db(z, [0, 0, 1, 1], ["same", "same", "same", "same"])
    np.testing.assert_allclose(db.nearest_other_press(),
                               [[np.inf, 1.0], [np.inf, 0.99], [0.99, np.inf], [1.0, np.inf]],
                               atol=1e-6)
    # One press alone has no neighbour: no figure rather than a made-up one.
    lone = _db(z[:2], [0, 0], ["a", "a"])
    assert np.all(np.isinf(lone.nearest_other_press()))
    assert Familiarity(lone).percentile(np.array([0.5, 0.0])) is None


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
        want = [[min((np.linalg.norm(refs[i] - refs[j]) for j in range(n)
                      if press[j] != press[i] and db.label_index[j] == c), default=np.inf)
                 for c in range(6)] for i in range(n)]
        np.testing.assert_allclose(db.nearest_other_press(block=7), want, atol=1e-6)


def test_the_ratio_is_the_nearest_class_over_the_eighth_nearest():
    # Ten classes on a line at 0..9, two presses each (at x and x + 0.25): a query at -1 is
    # 1, 2, ... 10 from them, so its ratio is 1 / 8.
    z = [[x + dx, 0] for x in range(10) for dx in (0, 0.25)]
    db = _db(z, [i // 2 for i in range(20)], [f"p{i % 2}" for i in range(20)])
    fam = Familiarity(db)
    assert FAMILIARITY_CLASSES == 8
    assert fam.ratio(np.array([-1.0, 0.0])) == pytest.approx(1 / 8)
    # Fewer classes than that: over the farthest.
    three = Familiarity(_db(z[:6], [0, 0, 1, 1, 2, 2], ["a", "b"] * 3))
    assert three.ratio(np.array([-1.0, 0.0])) == pytest.approx(1 / 3)
    # One class: nothing to compare with.
    assert Familiarity(_db(z[:4], [0, 0, 0, 0], ["a", "b", "c", "d"])).ratio(
        np.array([0.5, 0.0])) is None


def test_the_percentile_ranks_the_ratio_among_the_references_own():
    # Two classes of two presses: A at 0 and 1, B at 10 and 12. Each reference, its press
    # left out: A0 1/10, A1 1/9, B10 2/9, B12 2/11.
    z = [[0, 0], [1, 0], [10, 0], [12, 0]]
    fam = Familiarity(_db(z, [0, 0, 1, 1], ["a", "b", "c", "d"]))
    np.testing.assert_allclose(fam.loo, [1 / 10, 1 / 9, 2 / 11, 2 / 9])

    def at(x: float) -> float | None:
        return fam.percentile(np.array([x, 0.0]))

    assert at(0.0) == 0.0  # on a reference: ratio 0, inside its class more than any
    assert at(1.5) == 0.0  # 0.5 / 8.5
    assert at(2.0) == 50.0  # 1 / 8: above A0's and A1's, below B's
    assert at(2.4) == 75.0  # 1.4 / 7.6
    assert at(5.5) == 100.0  # halfway: as near one class as the other, ratio 1


def test_familiarity_on_the_shipped_model():
    db = load_model(MODELS).database
    t0 = time.perf_counter()
    fam = Familiarity(db)
    took = time.perf_counter() - t0
    print(f"leave-one-out ratios of the shipped {len(db)} references "
          f"({len(db.classes)} classes): {took * 1e3:.0f} ms; median "
          f"{np.median(fam.loo):.4f}, max {fam.loo[-1]:.4f}")
    assert fam.loo.size == len(db) == 1600 and np.all((fam.loo > 0) & (fam.loo <= 1))
    assert took < 5.0  # generous: about 0.1 s on a busy host
    # A reference's own press is in the database: its embedding scores 0.
    for i in (0, 777, 1599):
        assert fam.percentile(db.z[i]) == 0.0
    # A point far from every reference is about as far from each class: ratio near 1, 100.
    far = np.full(db.dim, 50.0, dtype=np.float32)
    assert fam.ratio(far) > 0.95 and fam.percentile(far) == 100.0


KNOWN = ("wood_cube", "sponge_cube", "apple_piece", "marshmallow", "glass_marble", "yokan")
NEW = ("canele", "resin_replica_konjac", "chocolate", "raw_kiri_mochi", "onigiri",
       "resin_replica_macaron")


def test_fresh_presses_of_new_objects_score_less_familiar_than_of_known_ones():
    """Recorder presses (not references) of six known objects and six of FoodReplica and
    Cube that the database lacks, read as the daemon reads them (offset 0)."""
    model = load_model(MODELS)
    fam = Familiarity(model.database)

    def score(name: str, seed: int) -> float:
        rec = recording_of(name, seed)
        window = preprocess.crop(rec.recv_time, preprocess.recording_units(rec), rec.t_stop,
                                 model.window)
        z = np.asarray(model.encode(preprocess.subsample(window, 0, model.window))[0])
        return fam.percentile(z.reshape(-1))

    known = [score(n, s) for n in KNOWN for s in (101, 102)]
    new = [score(n, s) for n in NEW for s in (101, 102)]
    auc = roc_auc(new, known)
    print(f"known: median {np.median(known):.0f} {np.round(known)}; new: median "
          f"{np.median(new):.0f} {np.round(new)}; AUC {auc:.2f}")
    # Measured on 420 presses: 0.77 (docs/method.md, 'Familiarity'); the figure it replaced
    # was 0.49.
    assert auc > 0.6 and np.median(new) > np.median(known)


@pytest.mark.parametrize("value", [0, -5, 100.5, 1000])
def test_the_unfamiliar_percentile_is_checked_naming_the_field(value):
    with pytest.raises(ConfigError, match=r"runtime\.unfamiliar_percentile = .*: must be a "
                                          r"percentile in \(0, 100\]"):
        config_from_dict({"runtime": {"unfamiliar_percentile": value}})
    assert config_from_dict({}).runtime.unfamiliar_percentile == 95.0
    assert config_from_dict({"runtime": {"unfamiliar_percentile": 100}}
                            ).runtime.unfamiliar_percentile == 100.0
