import json
import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.core.errors import DescriptionError, EdgeError, ModelError, RecordingError
from edge.core.model import ClassInfo, ReferenceDatabase, load_model, synthetic_database
from train.ship.database import add_class, build_into, topk_timing


def brute_force(db: ReferenceDatabase, q: np.ndarray, k: int) -> list[tuple[str, float]]:
    d = np.sqrt(((db.z.astype(np.float64) - q.astype(np.float64)) ** 2).sum(1))
    seen: dict[str, float] = {}
    for i in np.argsort(d, kind="stable"):
        label = db.labels[db.label_index[i]]
        seen.setdefault(label, float(d[i]))
        if len(seen) == k:
            break
    return list(seen.items())


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 60), classes=st.integers(1, 8),
       k=st.integers(1, 10))
def test_topk_returns_k_distinct_classes_nearest_first(seed, n, classes, k):
    classes = min(classes, n)
    rng = np.random.default_rng(seed)
    db = synthetic_database(n, classes, seed=seed)
    q = rng.standard_normal(4).astype(np.float32)
    got = db.topk(q, k)
    labels = [lab for lab, _ in got]
    assert len(labels) == len(set(labels)) == min(k, classes)
    dists = [d for _, d in got]
    assert dists == sorted(dists)
    want = brute_force(db, q, k)
    assert [lab for lab, _ in want] == labels
    np.testing.assert_allclose(dists, [d for _, d in want], rtol=1e-5, atol=1e-6)


def test_describe_and_z_q_space():
    classes = [ClassInfo("wood_cube", "wood cube", "train"),
               ClassInfo("stainless_cube", "stainless steel cube", "train"),
               ClassInfo("sponge_cube", "kitchen sponge cut into a cube", "train")]
    z = np.array([[0, 0], [0.1, 0], [1, 1], [5, 5]], dtype=np.float32)
    book = np.array([[0, 0], [1, 1], [5, 5]], dtype=np.float32)
    code = np.array([0, 0, 1, 2])
    db = ReferenceDatabase(classes, z, book[code], code, np.array([0, 1, 1, 2]),
                           ["a", "b", "c", "d"], book)
    assert [lab for lab, _ in db.topk(np.array([0.09, 0.0]), 2)] == \
        ["stainless_cube", "wood_cube"]
    assert db.describe(["wood_cube", "stainless_cube"]) == "wood cube, stainless steel cube"
    with pytest.raises(ModelError, match="not in the reference database"):
        db.describe(["nothing"])
    zq = ReferenceDatabase(classes, z, book[code], code, np.array([0, 1, 1, 2]),
                           ["a", "b", "c", "d"], book, space="z_q")
    # Quantised: wood and steel share code 0 at distance 0; ties go in class order.
    assert zq.topk(np.array([0.09, 0.0]), 2) == [("wood_cube", 0.0), ("stainless_cube", 0.0)]
    with pytest.raises(ModelError, match="classes without references"):
        ReferenceDatabase(classes, z, z, code, np.array([0, 0, 0, 0]), list("abcd"), book)


def test_topk_on_a_million_references_is_fast():
    db = synthetic_database(1_000_000, 1000)
    t = topk_timing(db, queries=30)
    print(f"\ntop-3 of 1,000,000 references (1000 classes): median {t['topk_ms_median']:.2f} "
          f"ms, p90 {t['topk_ms_p90']:.2f} ms")
    assert t["topk_ms_median"] < 1000  # a smoke bound only; the figure is printed


def test_db_add_extends_the_database_and_manifest(model_copy, cube_dir):
    model_dir = model_copy
    before = load_model(model_dir)
    db = add_class(model_dir, cube_dir / "boiled_kiri_mochi", "boiled_kiri_mochi",
                   "boiled kiri mochi (a Japanese rice cake)")
    assert db.labels[-1] == "boiled_kiri_mochi"
    after = load_model(model_dir)  # the manifest was re-hashed: it loads
    # Every offset of every press: 2 presses x 5 offsets.
    assert len(after.database) == len(before.database) + 2 * 5
    added = after.database.label_index == len(after.database.classes) - 1
    assert sorted(after.database.offset[added].tolist()) == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    z, _ = after.encode(np.zeros((25, 96), dtype=np.float32))
    assert len(after.topk(z, 40)) == 33
    index = json.loads((model_dir / "database.json").read_text())
    assert index["classes"][-1]["split"] == "added"
    assert index["classes"][-1]["presses"] == 2 and index["classes"][-1]["references"] == 10
    assert json.loads((model_dir / "manifest.json").read_text())["database"]["added"] == [
        "boiled_kiri_mochi"]
    # The added presses are retrievable: each one's nearest class is itself.
    from train.learn.data import load_presses

    x = load_presses(cube_dir / "boiled_kiri_mochi").inputs(0)
    zs, _ = after.encode(x)
    assert all(after.topk(zi, 1)[0][0] == "boiled_kiri_mochi" for zi in zs)


@pytest.mark.parametrize("description", [
    "a soft, sticky rice cake that flows under the fingers",
    "rice cake, firm", "a springy dumpling", "Hard candy", "mochi that feels like clay"])
def test_db_add_refuses_a_description_that_says_how_it_feels(model_copy, cube_dir,
                                                              description):
    before = (model_copy / "database.json").read_bytes()
    with pytest.raises(DescriptionError) as err:
        add_class(model_copy, cube_dir / "boiled_kiri_mochi", "boiled_kiri_mochi", description)
    message = str(err.value)
    assert "names the object only" in message and "Remove those words" in message
    assert isinstance(err.value, EdgeError) and isinstance(err.value, ValueError)
    assert (model_copy / "database.json").read_bytes() == before  # nothing written


def test_db_add_refuses_mixed_recordings(model_copy, cube_dir):
    model_dir = model_copy
    with pytest.raises(RecordingError, match=r"2 presses labelled 'raw_kiri_mochi' in their "
                       r"metadata, not 'mochi': .* or say --relabel"):
        add_class(model_dir, cube_dir, "mochi", "a rice cake")


def test_db_build_into_a_model_directory(released, reference_dir, tmp_path):
    model_dir = tmp_path / "m"
    model_dir.mkdir()
    shutil.copy(released / "encoder.onnx", model_dir)
    db = build_into(model_dir, reference_dir, space="z_q")
    assert db.space == "z_q" and len(db) == 32 * 2 * 5  # classes x presses x offsets
    model = load_model(model_dir)
    assert model.database.space == "z_q"
    shipped = load_model(released).database
    np.testing.assert_array_equal(db.z, shipped.z)


def test_database_holds_every_offset_of_every_press(released, reference_dir):
    """The paper's TactileReference: 5 subsampled sequences per press, all in the database,
    each encoded exactly as the robot encodes its offset-0 input."""
    from train.learn.data import Splits, load_presses

    db = load_model(released).database
    splits = Splits.of_dataset(reference_dir)
    assert len(db) == len(splits.classes) * 2 * 5 and db.offsets == [0, 1, 2, 3, 4]
    index = json.loads((released / "database.json").read_text())
    assert index["offsets"] == [0, 1, 2, 3, 4] and index["references"] == len(db)
    assert all(c["presses"] == 2 and c["references"] == 10 for c in index["classes"])
    model = load_model(released)
    presses = load_presses(reference_dir, ["yokan"])
    first = sorted(presses.paths)[0]
    mine = np.flatnonzero(db.source == first.rsplit("/", 1)[1])
    assert sorted(db.offset[mine].tolist()) == [0, 1, 2, 3, 4]
    i = presses.paths.index(first)
    for o in range(5):
        z, _ = model.encode(presses.x[i, o])
        row = mine[db.offset[mine] == o][0]
        np.testing.assert_allclose(db.z[row], z, rtol=1e-6, atol=1e-6)


def test_a_database_without_offsets_reads_as_offset_zero(tmp_path):
    db = synthetic_database(10, 3)
    assert db.offsets == [0]
    db.save(tmp_path)
    import io
    import zipfile
    data = (tmp_path / "database.npz").read_bytes()
    with np.load(io.BytesIO(data)) as npz:
        arrays = {k: npz[k] for k in npz.files if k != "offset"}
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    assert "offset.npy" not in zipfile.ZipFile(io.BytesIO(buf.getvalue())).namelist()
    old = ReferenceDatabase.from_bytes(buf.getvalue(), (tmp_path / "database.json").read_bytes())
    assert old.offsets == [0] and len(old) == 10
