"""Familiarity: where the database has features, the query's nearest-reference distance on
standardised channel means, as a percentile of every reference's nearest distance to another
press; where it has none, how much nearer its nearest class is than its eighth nearest in
the embedding, as a percentile of the references' same ratio; a reference's whole press left
out either way. That it tells new objects' presses from known ones' through the daemon's
path; the database's features saved and read; and the setting that flags a press
unfamiliar."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from edge.core import preprocess, recording
from edge.core.config import config_from_dict
from edge.core.errors import ConfigError, ModelError
from edge.core.model import (
    FAMILIARITY_CLASSES,
    ClassInfo,
    Familiarity,
    ReferenceDatabase,
    load_model,
    model_ref,
)
from edge.core.preprocess import DEFAULT_WINDOW
from edge.lab.teaching_eval import roc_auc
from edge.runtime.compute import analyse_press
from tests.support.featured import FEATURED_CLASSES, featured_model
from tests.support.lab_data import write_lab_dataset
from tests.support.presses import recording_of

MODELS = Path(__file__).resolve().parents[2] / "models"


def _db(z, label_index, source, space="z", codebook=None, feature=None):
    z = np.asarray(z, dtype=np.float32)
    codebook = z.copy() if codebook is None else np.asarray(codebook, dtype=np.float32)
    code = np.argmin(((z[:, None] - codebook) ** 2).sum(-1), axis=1)
    classes = [ClassInfo(f"c{i}", f"object {i}", "train") for i in range(max(label_index) + 1)]
    return ReferenceDatabase(classes, z, codebook[code], code, label_index, source, codebook,
                             space, feature=feature)


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
    fam = Familiarity(db, embedding=True)
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


def _clusters(seed: int = 0):
    """Three classes of four presses, two offsets each; 4 channels, the last never moves.
    Class c's channel means lie around 10 * c on the first channel (spread 1), the second
    and third around 0 (spread 1 and 100: standardised, both count alike)."""
    rng = np.random.default_rng(seed)
    label_index = np.repeat([0, 1, 2], 8)
    feature = np.column_stack([10.0 * label_index + rng.standard_normal(24),
                               rng.standard_normal(24), 100 * rng.standard_normal(24),
                               np.full(24, 7.0)])
    source = [f"p{i // 2}" for i in range(24)]
    z = rng.standard_normal((24, 3))  # the embedding plays no part
    return _db(z, label_index, source, feature=feature), feature


def test_with_features_a_new_cluster_of_channel_means_ranks_high_a_known_one_low():
    db, feature = _clusters()
    fam = Familiarity(db)
    assert fam.uses_feature and fam.loo.size == 24
    # The leave-one-out figures are each reference's nearest standardised distance to
    # another press (its own press's other offset left out), brute force.
    mean, std = feature.mean(axis=0), feature.std(axis=0)
    std[3] = 1.0  # the channel that never moves is left unscaled
    f = (feature - mean) / std
    d = np.linalg.norm(f[:, None] - f[None], axis=2)
    press = np.arange(24) // 2
    d[press[:, None] == press[None, :]] = np.inf
    np.testing.assert_allclose(fam.loo, np.sort(d.min(axis=1)), rtol=1e-6)
    z = np.zeros(3)
    known = [fam.percentile(z, [10.0 * c, 0.0, 0.0, 7.0]) for c in range(3)]
    new = fam.percentile(z, [45.0, 0.0, 0.0, 7.0])  # beyond every class on channel 0
    between = fam.percentile(z, [5.0, 3.0, 300.0, 7.0])
    print(f"known clusters' centres {known}, a new cluster {new}, between {between}")
    assert max(known) <= 50.0 and new == 100.0 and between == 100.0
    # The channel that never moves is not scaled up: 1 unit off adds 1, not infinity.
    assert fam.distance([0.0, 0.0, 0.0, 8.0]) == pytest.approx(
        fam.distance([0.0, 0.0, 0.0, 7.0]) + 1.0, abs=0.5)
    # The query's feature is needed; the embedding's ratio is there on request.
    with pytest.raises(ModelError, match="the query's feature"):
        fam.percentile(z)
    with pytest.raises(ModelError, match="must be 4 finite values"):
        fam.percentile(z, [1.0, 2.0])
    assert not Familiarity(db, embedding=True).uses_feature


def test_features_are_saved_and_read_and_an_older_database_falls_back(tmp_path):
    db, feature = _clusters()
    db.save(tmp_path)
    back = ReferenceDatabase.load(tmp_path)
    assert back.feature.dtype == np.float32
    np.testing.assert_array_equal(back.feature, db.feature)
    np.testing.assert_allclose(back.feature, feature, rtol=1e-6)
    np.testing.assert_array_equal(Familiarity(back).loo, Familiarity(db).loo)
    # A database.npz written before features were stored loads, and ranks in the embedding.
    with np.load(tmp_path / "database.npz") as npz:
        arrays = {k: npz[k] for k in npz.files if k != "feature"}
    np.savez_compressed(tmp_path / "database.npz", **arrays)
    old = ReferenceDatabase.load(tmp_path)
    assert old.feature is None
    fam = Familiarity(old)
    assert not fam.uses_feature
    np.testing.assert_array_equal(fam.loo, Familiarity(db, embedding=True).loo)
    assert fam.percentile(old.z[0]) == Familiarity(db, embedding=True).percentile(old.z[0])
    # Malformed features are refused, naming the array.
    with pytest.raises(ModelError, match=r"feature must be \(N=24, channels\) finite"):
        _db(db.z, db.label_index, db.source.tolist(), feature=feature[:5])


def test_the_feature_space_costs_little_at_the_shipped_size():
    # The shipped database's 1600 references with features of its 96 channels.
    db = load_model(MODELS).database
    rng = np.random.default_rng(5)
    with_features = ReferenceDatabase(
        db.classes, db.z, db.z_q, db.code, db.label_index, db.source.tolist(), db.codebook,
        offset=db.offset, feature=rng.standard_normal((len(db), 96)) * 50 + 100)
    t0 = time.perf_counter()
    fam = Familiarity(with_features)
    load = time.perf_counter() - t0
    queries = rng.standard_normal((200, 96)) * 50 + 100
    t0 = time.perf_counter()
    for q in queries:
        fam.percentile(db.z[0], q)
    query = (time.perf_counter() - t0) / len(queries)
    print(f"{len(db)} references: load {load * 1e3:.0f} ms, a query {query * 1e3:.3f} ms")
    assert fam.loo.size == 1600
    assert load < 5.0 and query < 0.05  # generous: about 0.05 s and 0.1 ms on a busy host


def test_the_builders_store_each_references_channel_means(tmp_path):
    # vt-train db build (the featured model) and db add: each reference's feature is its
    # press's model input at its own offset, averaged over time per channel.
    from train.ship.database import add_class

    directory = featured_model(tmp_path)
    db = load_model(directory).database
    assert db.feature.shape == (len(db), 96)
    for i in (0, 7, len(db) - 1):
        label, name = db.labels[db.label_index[i]], db.source[i]
        rec = recording.load(tmp_path / "recordings" / label / name)
        window = preprocess.crop(rec.recv_time, preprocess.recording_units(rec), rec.t_stop,
                                 DEFAULT_WINDOW)
        x = preprocess.subsample(window, int(db.offset[i]), DEFAULT_WINDOW)
        np.testing.assert_allclose(db.feature[i], x.mean(axis=0), rtol=1e-5)
    added = write_lab_dataset(tmp_path / "more", {"onigiri": ("train", 2, False)}, seed=9)
    grown = add_class(directory, added / "onigiri", "onigiri", "onigiri (a rice ball)")
    assert grown.feature.shape == (len(db) + 10, 96)
    assert Familiarity(load_model(directory).database).uses_feature


NEW = ("canele", "resin_replica_konjac", "chocolate", "raw_kiri_mochi", "onigiri",
       "resin_replica_macaron")


def test_fresh_presses_of_new_objects_score_less_familiar_than_of_known_ones(tmp_path):
    """Recorder presses (not references) of the known objects of a database built with
    features and of six of FoodReplica and Cube it lacks, looked up as the daemon does."""
    ref = model_ref(featured_model(tmp_path))

    def score(name: str, seed: int) -> float:
        return analyse_press(ref, recording_of(name, seed), agreement=False).familiarity

    known = [score(n, s) for n in FEATURED_CLASSES for s in (101, 102)]
    new = [score(n, s) for n in NEW for s in (101, 102)]
    auc = roc_auc(new, known)
    print(f"known: median {np.median(known):.0f} {np.round(known)}; new: median "
          f"{np.median(new):.0f} {np.round(new)}; AUC {auc:.2f}")
    # Here 0.58; on 420 presses against the shipped references 0.576 (docs/method.md,
    # 'Familiarity'): the channel means tell new objects only somewhat better than chance.
    assert auc > 0.5 and np.median(new) > np.median(known)


@pytest.mark.parametrize("value", [0, -5, 100.5, 1000])
def test_the_unfamiliar_percentile_is_checked_naming_the_field(value):
    with pytest.raises(ConfigError, match=r"runtime\.unfamiliar_percentile = .*: must be a "
                                          r"percentile in \(0, 100\]"):
        config_from_dict({"runtime": {"unfamiliar_percentile": value}})
    assert config_from_dict({}).runtime.unfamiliar_percentile == 95.0
    assert config_from_dict({"runtime": {"unfamiliar_percentile": 100}}
                            ).runtime.unfamiliar_percentile == 100.0
