import numpy as np
import pytest

from edge.core import preprocess, recording
from edge.core.errors import PreprocessError
from edge.core.preprocess import DEFAULT_WINDOW as W
from tests.support.presses import recording_of


def test_window_sizes_are_the_papers():
    assert W.n_window == 125 and W.n_steps == 25 and W.subsample == 5
    grid = W.grid(10.0)
    assert grid[0] == pytest.approx(9.6) and grid[-1] == pytest.approx(10.592)


def test_crop_and_subsample_shapes():
    rec = recording_of("stainless_cube", 0)
    units = preprocess.recording_units(rec)
    window = preprocess.crop(rec.recv_time, units, rec.t_stop)
    assert window.shape == (125, 96)
    x = preprocess.model_input(rec.recv_time, units, rec.t_stop)
    assert x.shape == (25, 96) and x.dtype == np.float32
    xs, targets = preprocess.recording_pairs(rec)
    assert xs.shape == targets.shape == (5, 25, 96)
    np.testing.assert_array_equal(xs[0], x)
    np.testing.assert_array_equal(xs[3], window[3::5])


def test_linear_resampling_is_exact_on_a_ramp_with_irregular_times():
    rng = np.random.default_rng(1)
    times = np.cumsum(rng.uniform(0.004, 0.012, 400))
    values = np.stack([3.0 * times, -times], axis=1)
    grid = np.linspace(times[10], times[-10], 125)
    out = preprocess.resample(times, values, grid)
    np.testing.assert_allclose(out[:, 0], 3.0 * grid, rtol=1e-6)
    hold = preprocess.resample(times, values, grid, method="hold")
    assert np.all(hold[:, 0] <= 3.0 * grid + 1e-6)


def test_window_outside_the_stream_is_refused():
    times = np.arange(100) * 0.008
    with pytest.raises(PreprocessError, match="leaves the stream"):
        preprocess.crop(times, np.zeros((100, 96)), t_stop=0.1)


def test_units_and_tare():
    raw = np.full((4, 96), 32768 + 655, dtype=np.uint16)
    tare = preprocess.tare(np.full((10, 96), 32768, dtype=np.uint16))
    units = preprocess.to_units(raw, tare)
    np.testing.assert_allclose(units, 655 / 65536, rtol=1e-6)
    assert preprocess.norm(units[0]) == pytest.approx(np.sqrt(96) * 655 / 65536, rel=1e-6)


def test_smoothing_is_gaussian_sigma_3():
    impulse = np.zeros((125, 1), dtype=np.float32)
    impulse[60] = 1.0
    out = preprocess.smooth(impulse)[:, 0]
    assert out.sum() == pytest.approx(1.0, rel=1e-4)
    assert out[60 + 3] / out[60] == pytest.approx(np.exp(-0.5), rel=1e-3)


def test_preprocessing_round_trips_through_the_file_bit_exactly(tmp_path):
    rec = recording_of("boiled_kiri_mochi", 3)
    path = recording.save(rec, tmp_path / "p.press.npz")
    back = recording.load(path)
    for a, b in zip(preprocess.recording_pairs(rec), preprocess.recording_pairs(back), strict=True):
        np.testing.assert_array_equal(a, b)
    assert back.meta() == rec.meta()
