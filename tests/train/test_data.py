import json

import numpy as np
import pytest

from edge.core import preprocess, recording
from edge.core.errors import RecordingError
from train.learn.data import (
    STD_FLOOR_FRACTION,
    Normaliser,
    Splits,
    load_presses,
    samples,
    training_data,
)

from .conftest import PRESSES
from .synthetic import write_set


def test_samples_follow_design_section_1(data, reference_dir):
    # 27 training classes x presses x 5 offsets; 5 validation classes the same way.
    assert len(data.splits.train) == 27 and len(data.splits.val) == 5
    assert data.train.x.shape == (27 * PRESSES * 5, 25, 96)
    assert data.val.x.shape == (5 * PRESSES * 5, 25, 96)
    assert data.train.x.dtype == np.float32
    # The first sample is offset 0 of the first press of the first class, normalised;
    # built by edge.core.preprocess, not by a copy of it.
    first = sorted((reference_dir / data.splits.train[0]).glob("*.press.npz"))[0]
    x, x_bar = preprocess.recording_pairs(recording.load(first))
    np.testing.assert_array_equal(data.train.x[0], data.norm(x[0]))
    np.testing.assert_array_equal(data.train.x_bar[4], data.norm(x_bar[4]))
    assert data.train.offset[:5].tolist() == [0, 1, 2, 3, 4]
    assert data.train.classes == data.splits.train


def test_ordering_is_deterministic(reference_dir):
    a = training_data(reference_dir)
    b = training_data(reference_dir)
    np.testing.assert_array_equal(a.train.x, b.train.x)
    assert a.presses.paths == b.presses.paths


def test_normaliser_floors_noise_channels_and_round_trips():
    rng = np.random.default_rng(0)
    x = rng.normal(0, 1, (50, 25, 4)).astype(np.float32)
    x[..., 0] *= 1e-4  # a channel that is only noise
    norm = Normaliser.fit(x)
    rms = np.sqrt(np.mean(x.reshape(-1, 4).std(0) ** 2))
    assert norm.std[0] == pytest.approx(STD_FLOOR_FRACTION * rms, rel=1e-5)
    assert abs(float(norm(x)[..., 0].std())) < 1e-3  # not blown up to unit variance
    back = Normaliser.from_dict(json.loads(json.dumps(norm.to_dict())))
    np.testing.assert_array_equal(back.std, norm.std)


def test_splits_file_overrides_dataset_json(tmp_path, reference_dir):
    f = tmp_path / "splits.json"
    f.write_text(json.dumps({"train": ["wood_cube", "sponge_cube"], "val": ["yokan"]}))
    splits = Splits.from_file(f)
    d = training_data(reference_dir, splits)
    assert d.train.classes == ("wood_cube", "sponge_cube")
    assert len(d.val) == PRESSES * 5
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"train": ["a"], "val": ["a"]}))
    with pytest.raises(RecordingError, match="both train and val"):
        Splits.from_file(bad)


def test_offset_selection_and_missing_class(reference_dir, data):
    presses = load_presses(reference_dir, ["yokan"])
    s0 = samples(presses, data.norm, offsets=[0])
    assert len(s0) == PRESSES and set(s0.offset.tolist()) == {0}
    with pytest.raises(RecordingError, match="no recordings of nothing"):
        presses.select(["nothing"])


def test_sequences_without_a_dataset_json_split_by_name(tmp_path):
    # Ten classes: the last fifth by name validate; each label is its own description.
    write_set(tmp_path, objects=[f"obj_{i}" for i in range(10)], presses=1)
    splits = Splits.of_dataset(tmp_path)
    assert splits.train == tuple(f"obj_{i}" for i in range(8))
    assert splits.val == ("obj_8", "obj_9") and splits.descriptions["obj_8"] == "obj 8"
    one = tmp_path / "one"
    write_set(one, objects=["hard_a"], presses=1)
    with pytest.raises(RecordingError, match="1 class: training needs two or more"):
        Splits.of_dataset(one)
    # A dataset.json beside the sequences decides instead.
    (tmp_path / "dataset.json").write_text(json.dumps({"classes": [
        {"label": "obj_0", "split": "train"}, {"label": "obj_1", "split": "val"}]}))
    assert Splits.of_dataset(tmp_path).val == ("obj_1",)
