import json
import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.core.errors import ModelError, RecordingError
from edge.core.model import ClassInfo, ReferenceDatabase, load_model, synthetic_database
from train.database import add_class, build_into, topk_timing


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
    classes = [ClassInfo("wood_cube", "a cube of hard wood that does not give at all", "train"),
               ClassInfo("stainless_cube", "a cube of smooth steel, rigid and unyielding",
                         "train"),
               ClassInfo("sponge_cube", "a squashy sponge", "train")]
    z = np.array([[0, 0], [0.1, 0], [1, 1], [5, 5]], dtype=np.float32)
    book = np.array([[0, 0], [1, 1], [5, 5]], dtype=np.float32)
    code = np.array([0, 0, 1, 2])
    db = ReferenceDatabase(classes, z, book[code], code, np.array([0, 1, 1, 2]),
                           ["a", "b", "c", "d"], book)
    assert [lab for lab, _ in db.topk(np.array([0.09, 0.0]), 2)] == \
        ["stainless_cube", "wood_cube"]
    assert db.describe(["wood_cube", "stainless_cube"]) == (
        "a cube of hard wood that does not give at all, "
        "a cube of smooth steel, rigid and unyielding")
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
                   "a soft, sticky rice cake that flows under the fingers")
    assert db.labels[-1] == "boiled_kiri_mochi"
    after = load_model(model_dir)  # the manifest was re-hashed: it loads
    assert len(after.database) == len(before.database) + 2
    z, _ = after.encode(np.zeros((25, 96), dtype=np.float32))
    assert len(after.topk(z, 40)) == 33
    index = json.loads((model_dir / "database.json").read_text())
    assert index["classes"][-1]["split"] == "added"
    assert json.loads((model_dir / "manifest.json").read_text())["database"]["added"] == [
        "boiled_kiri_mochi"]
    # The added presses are retrievable: each one's nearest class is itself.
    from train.data import load_presses

    x = load_presses(cube_dir / "boiled_kiri_mochi").inputs(0)
    zs, _ = after.encode(x)
    assert all(after.topk(zi, 1)[0][0] == "boiled_kiri_mochi" for zi in zs)


def test_db_add_refuses_mixed_recordings(model_copy, cube_dir):
    model_dir = model_copy
    with pytest.raises(RecordingError, match="none is labelled"):
        add_class(model_dir, cube_dir, "mochi", "a rice cake")


def test_db_build_into_a_model_directory(released, reference_dir, tmp_path):
    model_dir = tmp_path / "m"
    model_dir.mkdir()
    shutil.copy(released / "encoder.onnx", model_dir)
    db = build_into(model_dir, reference_dir, space="z_q")
    assert db.space == "z_q" and len(db) == 64
    model = load_model(model_dir)
    assert model.database.space == "z_q"
    shipped = load_model(released).database
    np.testing.assert_array_equal(db.z, shipped.z)
