"""Taught references: an overlay beside the shipped model, in the state directory. Added and
refused as ``db add`` would, removed, kept across a restart, set aside when another model
embedded them, refused clearly when damaged, exported as a collection the build reads, and
used by the next press looked up in the compute process with no restart."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import replace

import numpy as np
import pytest

from edge.core import preprocess, recording
from edge.core.errors import BadRequest, ModelError, NotFoundError
from edge.core.model import load_model, model_ref
from edge.lab.record import record_press, sim_config
from edge.runtime import compute
from edge.runtime.compute import ComputeWorker, analyse_press, teach_press
from edge.runtime.references import (
    INDEX,
    PRESSES,
    ReferenceStore,
    TaughtReference,
    references_dir,
)
from tests.support.daemon import ROOT
from tests.support.featured import featured_model
from tests.support.presses import recording_of

MODELS = ROOT / "models"
# An object the shipped model has no class for (FoodReplica), and one it has.
NEW = "boiled_kiri_mochi"
KNOWN = "otedama"


@pytest.fixture(scope="module")
def model():
    return load_model(MODELS)


@pytest.fixture(scope="module")
def featured(tmp_path_factory):
    """A model directory whose database has features (a few of the shipped classes)."""
    return featured_model(tmp_path_factory.mktemp("featured"))


@pytest.fixture
def store(tmp_path):
    return ReferenceStore(references_dir(tmp_path / "state"))


def _unknown(rec: recording.Recording) -> recording.Recording:
    """The press as the daemon keeps it in an episode: labelled "unknown"."""
    return replace(rec, label="unknown")


def test_a_new_object_is_taught_with_its_press_embedding_and_provenance(model, store):
    rec = _unknown(recording_of(NEW, 1))
    ref = store.add(model, rec, NEW, "boiled kiri mochi (a rice cake)", source="api",
                    episode="20261127T120000000Z-abcdef", now=1_800_000_000.0)
    assert ref.label == NEW and ref.source == "api" and ref.model == model.digest
    assert ref.episode == "20261127T120000000Z-abcdef"
    assert ref.taught_at == "2027-01-15T08:00:00.000Z"
    assert ref.x_th == pytest.approx(rec.threshold)
    print(f"taught press streamed at {ref.rate_hz:.1f} frames/s")
    assert ref.rate_hz == pytest.approx(125, abs=2)
    # One entry per press, one embedding row per offset the database holds (5).
    assert ref.offsets == tuple(model.database.offsets) == (0, 1, 2, 3, 4)
    assert np.asarray(ref.z).shape == (5, model.database.dim) and len(ref.code) == 5
    # Offset 0 is what a recognition of that press computes.
    x = preprocess.model_input(rec.recv_time, preprocess.recording_units(rec), rec.t_stop)
    np.testing.assert_allclose(ref.z[0], model.encode(x)[0], atol=1e-6)
    # The press is kept beside the index, labelled as taught (episodes may be removed).
    kept = recording.load(store.root / ref.press_file)
    assert kept.label == NEW and np.array_equal(kept.frames, rec.frames)
    overlay = store.load(model.digest)
    assert [r.id for r in overlay.current] == [ref.id] and overlay.stale == ()
    listed = overlay.to_json()
    assert listed[0]["label"] == NEW and listed[0]["stale"] is False and "z" not in listed[0]
    # Merged: the model's 1600 references and 5 taught ones, a new class.
    lookup = overlay.lookup(model)
    assert len(lookup.database) == len(model.database) + 5
    assert lookup.database.labels[-1] == NEW
    assert lookup.database.description(NEW) == "boiled kiri mochi (a rice cake)"


def test_a_label_the_database_has_takes_presses_only_when_appended(model, store):
    rec = _unknown(recording_of(KNOWN, 7))
    with pytest.raises(BadRequest, match=r"'otedama' is in the model's database already: "
                                         "say append"):
        store.add(model, rec, KNOWN, "a beanbag", source="page")
    ref = store.add(model, rec, KNOWN, None, source="page", append=True)
    assert ref.description == model.database.description(KNOWN)  # the class's own
    lookup = store.load(model.digest).lookup(model)
    assert len(lookup.database) == len(model.database) + 5
    assert lookup.database.labels == model.database.labels  # no new class
    # A taught label is refused the same way, and appended to.
    store.add(model, _unknown(recording_of(NEW, 2)), NEW, "kiri mochi", source="cli")
    with pytest.raises(BadRequest, match="in the taught references already"):
        store.add(model, _unknown(recording_of(NEW, 3)), NEW, "kiri mochi", source="cli")
    again = store.add(model, _unknown(recording_of(NEW, 3)), NEW, None, source="mqtt",
                      append=True)
    assert again.description == "kiri mochi"
    # One press is taught once, whatever the label.
    with pytest.raises(BadRequest, match=f"this press is taught already, as '{NEW}'"):
        store.add(model, _unknown(recording_of(NEW, 3)), "another_name", "a rice cake",
                  source="cli")


def test_a_new_label_needs_a_description_that_names_the_object(model, store):
    rec = _unknown(recording_of(NEW, 4))
    with pytest.raises(BadRequest, match="is a new class: it needs a description"):
        store.add(model, rec, NEW, None, source="api")
    with pytest.raises(BadRequest, match=r"says how the object feels \(soft, squishy\)"):
        store.add(model, rec, NEW, "a soft squishy rice cake", source="api")
    with pytest.raises(BadRequest, match="label 'kiri mochi!'"):
        store.add(model, rec, "kiri mochi!", "a rice cake", source="api")
    with pytest.raises(BadRequest, match="source 'ssh'"):
        store.add(model, rec, NEW, "a rice cake", source="ssh")  # type: ignore[arg-type]
    assert not (store.root / INDEX).exists()


def test_a_press_at_another_threshold_or_rate_is_refused_in_one_line(model, store):
    # A real press stopped at twice the shipped model's x_th (0.004).
    high = _unknown(record_press("wood_cube", 11, x_th=0.008).recording)
    with pytest.raises(BadRequest) as refused:
        store.add(model, high, "wood_cube", None, source="api", append=True)
    print(refused.value)
    text = str(refused.value)
    assert "\n" not in text and "x_th = 0.008" in text and "x_th = 0.004" in text
    # The fragile gelatin_soft class was pressed at 0.003: 0.004 is 1.33x, refused too.
    with pytest.raises(BadRequest, match=r"x_th = 0\.003"):
        store.add(model, _unknown(recording_of(KNOWN, 12)), "gelatin_soft", None,
                  source="api", append=True)
    # A real press of a stream at 100 frames/s, against the class's 125.
    cfg = sim_config()
    slow = _unknown(record_press(KNOWN, 13, cfg=replace(
        cfg, sim=replace(cfg.sim, sensor_rate_hz=100.0))).recording)
    with pytest.raises(BadRequest) as refused:
        store.add(model, slow, KNOWN, None, source="api", append=True)
    print(refused.value)
    text = str(refused.value)
    assert "\n" not in text and re.search(r"stream at (9\d|10\d)\.\d frames/s is 2\d % off "
                                         r"125 Hz", text)
    # A new class is held to the model's classes' threshold and rate alike.
    with pytest.raises(BadRequest, match=r"x_th = 0\.004"):
        store.add(model, high, NEW, "kiri mochi", source="api")
    assert not (store.root / INDEX).exists()


def test_removed_by_id_or_label_and_gone_from_the_next_lookup(model, store):
    a = store.add(model, _unknown(recording_of(NEW, 5)), NEW, "kiri mochi", source="api")
    b = store.add(model, _unknown(recording_of(NEW, 6)), NEW, None, source="api",
                  append=True)
    c = store.add(model, _unknown(recording_of(KNOWN, 5)), KNOWN, None, source="api",
                  append=True)
    assert store.remove(a.id) == a
    assert not (store.root / a.press_file).exists()
    assert [r.id for r in store.load(model.digest).current] == [b.id, c.id]
    with pytest.raises(NotFoundError, match=f"no taught reference '{a.id}'"):
        store.remove(a.id)
    assert [r.id for r in store.remove_label(NEW)] == [b.id]
    lookup = store.load(model.digest).lookup(model)
    assert NEW not in lookup.database.labels
    assert len(lookup.database) == len(model.database) + 5
    with pytest.raises(NotFoundError, match="no taught references of 'kiri'"):
        store.remove_label("kiri")
    assert sorted(p.name for p in (store.root / PRESSES).iterdir()) == [
        f"{c.id}{recording.SUFFIX}"]


def test_a_press_left_by_a_crash_before_its_entry_is_not_used_and_is_cleared(model, store):
    a = store.add(model, _unknown(recording_of(NEW, 8)), NEW, "kiri mochi", source="api")
    before = (store.root / INDEX).read_bytes()
    orphan = store.root / PRESSES / f"0123456789ab{recording.SUFFIX}"
    recording.save(recording_of(NEW, 9), orphan)  # the press of an add cut off here
    assert [r.id for r in store.load(model.digest).current] == [a.id]
    assert (store.root / INDEX).read_bytes() == before
    store.add(model, _unknown(recording_of(NEW, 10)), NEW, None, source="api", append=True)
    assert not orphan.exists()


def test_a_taught_reference_carries_its_feature_and_the_familiarity_uses_it(featured,
                                                                            tmp_path):
    model = load_model(featured)
    store = ReferenceStore(references_dir(tmp_path / "state"))
    ref = model_ref(featured, store.root)
    rec = _unknown(recording_of(NEW, 20))
    before = analyse_press(ref, rec, agreement=False)
    taught = store.add(model, rec, NEW, "kiri mochi", source="api")
    # Per offset, each channel's mean over the model input, as the database's references.
    x = preprocess.model_input(rec.recv_time, preprocess.recording_units(rec), rec.t_stop)
    assert np.asarray(taught.feature).shape == (5, x.shape[1])
    np.testing.assert_allclose(taught.feature[0], x.mean(axis=0), rtol=1e-6)
    assert "feature" not in store.load(model.digest).to_json()[0]
    lookup = store.load(model.digest).lookup(model)
    assert lookup.familiarity.uses_feature
    assert lookup.database.feature.shape == (len(model.database) + 5, x.shape[1])
    np.testing.assert_allclose(lookup.database.feature[-5:], taught.feature, rtol=1e-6)
    # The taught press looked up again lies on its own reference: as familiar as can be.
    after = analyse_press(ref, rec, agreement=False)
    print(f"a press of {NEW}: familiarity {before.familiarity:.1f} before it was taught, "
          f"{after.familiarity:.1f} after")
    assert before.familiarity > 10.0 and after.familiarity == 0.0


def test_an_entry_taught_before_features_gets_them_from_its_press_or_falls_back(
        featured, tmp_path, caplog):
    model = load_model(featured)
    store = ReferenceStore(references_dir(tmp_path / "state"))
    taught = store.add(model, _unknown(recording_of(NEW, 22)), NEW, "kiri mochi",
                       source="api")
    index = json.loads((store.root / INDEX).read_text())
    del index["references"][0]["feature"]  # written before features were kept
    (store.root / INDEX).write_text(json.dumps(index))
    old = store.load(model.digest)
    assert old.current[0].feature is None
    lookup = old.lookup(model)  # from the press kept beside the index
    np.testing.assert_allclose(lookup.database.feature[-5:], taught.feature, rtol=1e-6)
    # Its press gone too: no features in the merged database, the embedding ratio, said.
    (store.root / taught.press_file).unlink()
    lookup = store.load(model.digest).lookup(model)
    assert lookup.database.feature is None and not lookup.familiarity.uses_feature
    assert f"1 taught references have no feature and no readable press ({taught.id})" \
        in caplog.text
    out = analyse_press(model_ref(featured, store.root), _unknown(recording_of(NEW, 23)))
    assert out.familiarity is not None and NEW in dict(out.topk)


@pytest.mark.asyncio
async def test_the_references_survive_a_restart_and_the_next_press_uses_them(model, tmp_path):
    """Through the compute process, as the daemon runs it: taught, then the next press of
    that object finds it, with no reload; a new worker (a restart) reads them again."""
    refs = references_dir(tmp_path / "state")
    ref = model_ref(MODELS, refs)
    press, later = _unknown(recording_of(NEW, 14)), _unknown(recording_of(NEW, 15))
    async with ComputeWorker() as worker:
        await worker.run(compute.warm_up, ref)  # no references yet: fine
        before = await worker.run(analyse_press, ref, later)
        taught = await worker.run(teach_press, ref, press, NEW, "kiri mochi", "api",
                                  "20261127T120000000Z-abcdef")
        after = await worker.run(analyse_press, ref, later)
    async with ComputeWorker() as worker:  # a restart
        await worker.run(compute.warm_up, ref)
        restarted = await worker.run(analyse_press, ref, later)
    print(f"before: {before.topk[0]} familiarity {before.familiarity}; after teaching one "
          f"press: {after.topk[0]} familiarity {after.familiarity}")
    assert NEW not in dict(before.topk) and before.references == ""
    assert isinstance(taught, TaughtReference) and taught.episode.endswith("abcdef")
    assert after.topk[0][0] == NEW and after.references != ""
    assert after.topk[0][1] < before.topk[0][1]
    assert restarted.topk == after.topk and restarted.references == after.references
    assert restarted.familiarity == after.familiarity


def test_references_of_another_model_are_set_aside_not_used(model, store, tmp_path, caplog):
    a = store.add(model, _unknown(recording_of(NEW, 16)), NEW, "kiri mochi", source="api")
    store.add(model, _unknown(recording_of(KNOWN, 16)), KNOWN, None, source="api",
              append=True)
    index = json.loads((store.root / INDEX).read_text())
    index["references"][0]["model"] = "0" * 64  # embedded by another encoder
    (store.root / INDEX).write_text(json.dumps(index))
    overlay = store.load(model.digest)
    assert [r.id for r in overlay.stale] == [a.id] and len(overlay.current) == 1
    assert "1 taught references were embedded by another model" in caplog.text
    assert [e["stale"] for e in overlay.to_json()] == [False, True]
    lookup = overlay.lookup(model)
    assert NEW not in lookup.database.labels  # never used ...
    assert (store.root / a.press_file).exists()  # ... but kept
    # The same through the compute process: the next press is looked up without them.
    out = analyse_press(model_ref(MODELS, store.root), _unknown(recording_of(NEW, 17)))
    assert NEW not in dict(out.topk)


@pytest.mark.parametrize("damage, message", [
    (lambda text: text[: len(text) // 2], "not valid JSON"),
    (lambda text: text.replace('"x_th": 0.004', '"x_th": "high"'),
     r"references\[0\]\.x_th: must be a threshold > 0, got 'high'"),
    (lambda text: text.replace('"schema_version": 1', '"schema_version": 9'),
     "schema_version: not a version 1 index"),
    (lambda text: text.replace('"source": "api"', '"source": "ftp"'),
     r"references\[0\]\.source: must be one of api, mqtt, cli, page"),
])
def test_a_damaged_index_is_refused_naming_the_file_and_field(model, store, damage, message):
    store.add(model, _unknown(recording_of(NEW, 18)), NEW, "kiri mochi", source="api")
    path = store.root / INDEX
    path.write_text(damage(path.read_text()))
    with pytest.raises(ModelError, match=message) as refused:
        store.load(model.digest)
    assert str(path) in str(refused.value)
    # At start and on reload (the compute process loads them with the model).
    ref = model_ref(MODELS, store.root)
    with pytest.raises(ModelError, match=message):
        compute.reload_model(ref)
    # A teaching does not write over a damaged index either.
    with pytest.raises(ModelError, match=message):
        store.add(model, _unknown(recording_of(NEW, 19)), NEW, None, source="api",
                  append=True)


def test_an_embedding_of_another_size_is_refused_when_merged(model, store):
    store.add(model, _unknown(recording_of(NEW, 20)), NEW, "kiri mochi", source="api")
    index = json.loads((store.root / INDEX).read_text())
    index["references"][0]["z"] = [row[:8] for row in index["references"][0]["z"]]
    (store.root / INDEX).write_text(json.dumps(index))
    with pytest.raises(ModelError, match="z has 8 dims, the model embeds in 16"):
        store.load(model.digest).lookup(model)


def test_the_export_is_a_collection_the_build_reads(model, store, tmp_path):
    from train.learn.data import load_presses
    from train.ship.build import read_dataset

    store.add(model, _unknown(recording_of(NEW, 21)), NEW, "kiri mochi", source="api")
    store.add(model, _unknown(recording_of(NEW, 22)), NEW, None, source="api", append=True)
    store.add(model, _unknown(recording_of(KNOWN, 21)), KNOWN, None, source="page",
              append=True)
    dest = store.export(tmp_path / "taught")
    ds = read_dataset(dest, progress=False)
    assert set(ds.splits.train) == {NEW, KNOWN} and ds.splits.val == ()
    assert ds.presses == {NEW: 2, KNOWN: 1}
    assert ds.x_th == {NEW: 0.004, KNOWN: 0.004}
    assert all(abs(r - 125) < 2 for r in ds.rate_hz.values())
    assert ds.splits.descriptions[NEW] == "kiri mochi"
    assert ds.splits.descriptions[KNOWN] == model.database.description(KNOWN)
    assert ds.origin["kind"] == "emulated"
    presses = load_presses(dest, [NEW, KNOWN])
    assert sorted(presses.labels) == sorted([KNOWN, NEW, NEW])
    with pytest.raises(BadRequest, match="exists: export into a new directory"):
        store.export(dest)
    shutil.rmtree(store.root)
    with pytest.raises(NotFoundError, match="no taught references to export"):
        store.export(tmp_path / "empty")


def test_a_press_is_flagged_unfamiliar_at_the_configured_percentile():
    ref = model_ref(MODELS)
    rec = recording_of(KNOWN, 7)
    out = analyse_press(ref, rec)  # the default, [runtime] unfamiliar_percentile's 95
    print(f"a fresh press of {KNOWN}: nearest {out.topk[0]}, familiarity {out.familiarity}")
    assert out.familiarity is not None and 0 <= out.familiarity <= 100
    assert out.unfamiliar == (out.familiarity >= 95)
    assert analyse_press(ref, rec, out.familiarity).unfamiliar
    assert not analyse_press(ref, rec, out.familiarity + 0.01).unfamiliar


def test_writers_at_once_lose_none_of_each_others_presses(model, store):
    """The daemon teaching while a CLI run removes: each read-modify-write holds the lock."""
    from concurrent.futures import ThreadPoolExecutor

    first = store.add(model, _unknown(recording_of(NEW, 30)), NEW, "kiri mochi",
                      source="api")
    presses = [_unknown(recording_of(NEW, seed)) for seed in range(31, 37)]
    with ThreadPoolExecutor(4) as pool:
        added = list(pool.map(lambda rec: store.add(model, rec, NEW, None, source="api",
                                                    append=True), presses))
        removed = pool.submit(store.remove, first.id).result()
    assert removed == first
    assert {r.id for r in store.load(model.digest).current} == {r.id for r in added}
    assert len(list((store.root / PRESSES).iterdir())) == len(presses)
