"""Other sensors' labelled presses: the format, its refusals, the PHAC-2 converter, and the
same preprocessing as the robot's presses."""

import io

import numpy as np
import pytest
import scipy.io

from edge.core import preprocess
from edge.core.errors import RecordingError
from edge.core.preprocess import DEFAULT_WINDOW as W
from train.learn import phac2, sequences
from train.learn.data import Normaliser, Splits, load_presses, training_data_of
from train.learn.model import ModelConfig
from train.learn.trainer import Progress, TrainConfig, train
from train.ship import database

from .synthetic import squeeze, write_set


def test_a_set_of_sequences_is_cut_by_the_robots_preprocessing_at_its_own_rate(tmp_path):
    write_set(tmp_path, presses=2)
    presses = load_presses(tmp_path)
    # 100 Hz: the window's 100 samples in 25 steps, 4 offsets; 6 channels.
    assert presses.x.shape == presses.x_bar.shape == (10, 4, 25, 6)
    assert presses.classes == ["hard_a", "hard_b", "odd", "soft_a", "soft_b"]
    first = sequences.load(presses.paths[0])
    w = W.at_rate(100.0)
    times = np.arange(len(first.samples)) / 100.0
    x, x_bar = preprocess.training_pairs(times, first.samples, w.before_s, w, edge="hold")
    np.testing.assert_allclose(presses.x[0], x, rtol=1e-6)
    np.testing.assert_allclose(presses.x_bar[0], x_bar, rtol=1e-6)
    np.testing.assert_array_equal(presses.x[0, 1], first.samples[1:100:4])  # no stream before
    # The database holds every offset the window's subsampling gives (4 here, not 5).
    assert database.offsets_of(presses) == (0, 1, 2, 3)
    assert database.reference_inputs(presses).shape == (40, 25, 6)


def test_the_stop_places_the_window(tmp_path):
    data = squeeze("soft_a", 0, seconds=3.0)
    path = sequences.save(tmp_path / "a.seq.npz", data, 100.0, "soft_a", stop_s=1.0)
    seq = sequences.load(path)
    x, _ = seq.pairs()
    np.testing.assert_array_equal(x[0], data[60:160:4])  # 0.4 s before the stop, 0.6 after
    late = sequences.save(tmp_path / "b.seq.npz", data, 100.0, "soft_a", stop_s=2.7)
    with pytest.raises(RecordingError, match=r"b.seq.npz: field stop_s: the window .* leaves"):
        sequences.load(late).pairs()


def _npz(path, **arrays):
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())
    return path


@pytest.mark.parametrize("arrays, message", [
    ({"samples": np.zeros((50, 3)), "rate_hz": 100.0}, "missing field label"),
    ({"samples": np.zeros(50), "rate_hz": 100.0, "label": "a"}, "field samples must be"),
    ({"samples": np.full((50, 3), np.nan), "rate_hz": 100.0, "label": "a"},
     r"field samples holds a non-finite value \(sample 0, channel 0\)"),
    ({"samples": np.zeros((50, 3)), "rate_hz": -5.0, "label": "a"}, "field rate_hz must be"),
    ({"samples": np.zeros((50, 3)), "rate_hz": [1.0, 2.0], "label": "a"},
     "field rate_hz must be one finite number"),
    ({"samples": np.zeros((50, 3)), "rate_hz": 100.0, "label": "../etc"}, "field label"),
    ({"samples": np.zeros((50, 3)), "rate_hz": 100.0, "label": 7}, "field label"),
    ({"samples": np.zeros((50, 3)), "rate_hz": 100.0, "label": "a", "stop_s": -1.0},
     "field stop_s must be at or after"),
    ({"samples": np.array([None, 1], dtype=object), "rate_hz": 100.0, "label": "a"},
     "unreadable field"),
])
def test_hostile_sequences_are_refused_naming_the_file_and_field(tmp_path, arrays, message):
    path = _npz(tmp_path / "x.seq.npz", **arrays)
    with pytest.raises(RecordingError, match=message) as err:
        sequences.load(path)
    assert "x.seq.npz" in str(err.value)


def test_not_an_archive_is_refused(tmp_path):
    garbage = tmp_path / "g.seq.npz"
    garbage.write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(RecordingError, match=r"g\.seq\.npz: not an \.npz archive"):
        sequences.load(garbage)
    bare = tmp_path / "b.seq.npz"
    np.save(bare.open("wb"), np.zeros(3))
    with pytest.raises(RecordingError, match=r"bare \.npy"):
        sequences.load(bare)


def test_one_set_is_one_sensor(tmp_path):
    write_set(tmp_path / "six", objects=("hard_a",), presses=1, channels=6)
    write_set(tmp_path / "six", objects=("soft_a",), presses=1, channels=8)
    with pytest.raises(RecordingError, match=r"25 steps of 8 channels.*25 of 6"):
        load_presses(tmp_path / "six")


def _phac2_file(path, samples=1000, drop=None):
    rng = np.random.default_rng(0)
    fields = {"F0Electrodes": rng.integers(1000, 3000, (19, samples)).astype(np.uint16),
              "F1Electrodes": rng.integers(1000, 3000, (19, samples)).astype(np.uint16),
              "F0pdc": rng.integers(1000, 3000, (1, samples)).astype(np.uint16),
              "F1pdc": rng.integers(1000, 3000, (1, samples)).astype(np.uint16),
              "F0pac": np.zeros((22, samples), np.uint16), "JPos": np.zeros((1, samples))}
    fields.pop(drop, None)
    scipy.io.savemat(path, fields)
    return fields


def test_phac2_files_convert_to_sequences_of_both_fingers_electrodes_and_pressure(tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    fields = _phac2_file(raw / "car_sponge_101_03_HOLD.mat")
    _phac2_file(raw / "steel_vase_702_01_HOLD.mat")
    written = phac2.convert(raw, tmp_path / "seq")
    assert [p.relative_to(tmp_path / "seq").as_posix() for p in written] == [
        "car_sponge/car_sponge_101_03_HOLD.seq.npz", "steel_vase/steel_vase_702_01_HOLD.seq.npz"]
    seq = sequences.load(written[0])
    assert seq.label == "car_sponge" and seq.rate_hz == 100.0 and seq.samples.shape == (1000, 40)
    np.testing.assert_array_equal(seq.samples[:, 19:38], fields["F1Electrodes"].T)
    np.testing.assert_array_equal(seq.samples[:, 39], fields["F1pdc"][0])
    assert load_presses(tmp_path / "seq").x.shape == (2, 4, 25, 40)


def test_phac2_file_without_a_channel_is_refused(tmp_path):
    _phac2_file(tmp_path / "acrylic_211_01_HOLD.mat", drop="F1pdc")
    with pytest.raises(RecordingError, match=r"acrylic_211_01_HOLD\.mat: field F1pdc missing"):
        phac2.read(tmp_path / "acrylic_211_01_HOLD.mat")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="no PHAC-2 files"):
        phac2.find(tmp_path / "empty")


def test_the_std_floor_is_a_setting():
    rng = np.random.default_rng(0)
    x = rng.normal(0, 1, (50, 25, 3)).astype(np.float32) * np.array([1e-3, 1.0, 5.0])
    own = Normaliser.fit(x, 0.0)
    np.testing.assert_allclose(own.std, x.reshape(-1, 3).std(0), rtol=1e-5)
    floored = Normaliser.fit(x, 1.0)
    assert floored.std[0] == floored.std[1] > 2.0  # the two quiet channels share one spread
    with pytest.raises(ValueError, match="std floor must be >= 0"):
        Normaliser.fit(x, -0.5)


@pytest.mark.integration  # trains two small models
def test_one_validation_class_keeps_a_metric_term_against_the_training_presses(tmp_path):
    """One validation class has no other class to be told apart from in its own samples: its
    metric term is measured against the training presses, so early stopping still sees it."""
    write_set(tmp_path, presses=2)
    presses = load_presses(tmp_path)
    splits = Splits(("hard_a", "hard_b", "soft_a"), ("soft_b",), {})
    config = TrainConfig(model=ModelConfig(channels=6), max_epochs=2, patience=5)
    result = train(training_data_of(presses, splits), config, None, Progress(enabled=False))
    val = result.history[0]["val"]
    print("one-class validation metric term:", val["metric"])
    assert val["metric"] > 0
    assert val["loss"] == pytest.approx(val["recon"] + val["codebook"] + 0.25 * val["commit"]
                                        + val["metric"], rel=1e-5)
    # Two validation classes: their own metric term, as before.
    two = Splits(("hard_a", "hard_b", "odd"), ("soft_a", "soft_b"), {})
    result = train(training_data_of(presses, two), config, None, Progress(enabled=False))
    assert "metric" in result.history[0]["val"]
