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


def test_target_is_smoothed_before_the_crop_without_edge_effects():
    # A stream with a step right at the window's first sample: smoothing the crop alone
    # would see a flat padded edge there; smoothing the stream first sees the step.
    t_stop = 10.0
    times = W.grid(t_stop, margin=40)  # frames on the 125 Hz grid, 40 beyond each end
    units = (np.arange(len(times)) < 40).astype(np.float32)[:, None]  # 1 before the window
    target = preprocess.smoothed_crop(times, units, t_stop)
    cropped_then_smoothed = preprocess.smooth(preprocess.crop(times, units, t_stop))
    assert cropped_then_smoothed[0, 0] == 0.0  # the edge effect the paper's order avoids
    # The window's first sample gets the kernel's weight on the 12 samples before it.
    k = np.arange(-12, 13)
    w = np.exp(-0.5 * (k / 3.0) ** 2)
    assert target[0, 0] == pytest.approx(w[k < 0].sum() / w.sum(), rel=1e-5)
    assert target[0, 0] == pytest.approx(0.434, abs=1e-3)
    assert target[60, 0] == 0.0  # far from the step: untouched
    # X is the raw crop; X_bar the smoothed stream, cropped and subsampled the same way.
    xs, x_bar = preprocess.training_pairs(times, units, t_stop)
    np.testing.assert_array_equal(xs[2], preprocess.crop(times, units, t_stop)[2::5])
    np.testing.assert_array_equal(x_bar[2], target[2::5])


def test_target_needs_the_filters_reach_beyond_the_window():
    t_stop = 10.0
    margin_s = (W.smooth_margin - 1) / 125.0  # one sample short on each side
    times = np.arange(W.grid(t_stop)[0] - margin_s, W.grid(t_stop)[-1] + margin_s, 1 / 125.0)
    units = np.zeros((len(times), 96), dtype=np.float32)
    assert W.smooth_margin == 12
    preprocess.crop(times, units, t_stop)  # the input itself is fine
    with pytest.raises(PreprocessError, match=r"12 samples \(96 ms\) of stream beyond"):
        preprocess.training_pairs(times, units, t_stop)


def test_tared_norms_tare_the_first_frames_as_the_press_does():
    times = np.arange(10) * 0.1
    raw = np.full((10, 96), 30000, dtype=np.uint16)
    raw[3:, 0] += 262  # one channel 262 counts up after the tare: 0.004 tactile units
    raw[:3, 1] = [29990, 30000, 30010]  # tared to its mean: no change after
    norms = preprocess.tared_norms(times, raw, 0.25)
    np.testing.assert_allclose(norms, 262 / 65536, rtol=1e-6)
    assert norms.shape == (7,)
    with pytest.raises(PreprocessError, match=r"none left after a 1.0 s tare"):
        preprocess.tared_norms(times, raw, 1.0)


def _stream(rate_hz: float, seconds: float = 3.0, seed: int = 0):
    """A stream sent at ``rate_hz`` and received with up to 2 ms of delay: receive times,
    values of a known signal at them (a 1.3 Hz sine in every channel, scaled per channel),
    send times, sequence numbers."""
    rng = np.random.default_rng(seed)
    sent = np.arange(0, seconds, 1 / rate_hz)
    t = np.sort(sent + rng.uniform(0, 0.002, len(sent)))
    values = np.sin(2 * np.pi * 1.3 * t)[:, None] * np.linspace(0.5, 1.0, 6)[None, :]
    return t, values.astype(np.float32), sent, np.arange(len(t))


def test_a_100_hz_stream_crops_onto_the_same_grid_as_a_125_hz_one():
    # docs/method.md 'A stream that is not 125 Hz': the crop places its samples by time, so
    # a 100 Hz stream gives the same 125 samples and 25 steps of the same signal, each
    # interpolated from fewer frames.
    t_stop = 1.5
    x125 = preprocess.model_input(*_stream(125.0)[:2], t_stop)
    t100, v100, sent100, seq100 = _stream(100.0, seed=1)
    x100 = preprocess.model_input(t100, v100, t_stop)
    assert x100.shape == x125.shape == (25, 6)
    gap = float(np.abs(x100 - x125).max())
    print(f"largest difference of the 100 and 125 Hz crops: {gap:.5f} (signal amplitude 1)")
    assert gap < 0.01
    rate = preprocess.stream_rate(t100, sent100, seq100, t_stop)
    print(f"100 Hz stream measured at {rate}")
    assert rate.window_hz == pytest.approx(100, abs=1) and rate.press_hz == pytest.approx(
        100, abs=1)


def test_the_rate_is_the_servers_whatever_the_load_on_either_side():
    t, _, sent, seq = _stream(125.0)
    assert preprocess.fresh_rate(t, sent, seq) == pytest.approx(125, abs=0.5)
    # Every frame sent twice (a server repeating its last frame): still 125 new frames/s.
    assert preprocess.fresh_rate(*(np.repeat(a, 2) for a in (t, sent, seq))) == \
        pytest.approx(125, abs=0.5)
    # A busy sender skips one tick in ten, one frame in twenty is lost on the way, and a busy
    # receiver takes them in bursts (50 ms late every 200 ms): the server is still set to 125.
    kept = (np.arange(len(sent)) % 10 != 9)
    sent = sent[kept]
    seq = np.arange(len(sent))
    arrived = np.maximum(sent, np.ceil(sent / 0.2) * 0.2 - 0.15) + 0.0005
    lost = np.arange(len(sent)) % 20 == 7
    received = preprocess.fresh_rate(arrived[~lost], sent[~lost], seq[~lost])
    counted = (np.sum(~lost) - 1) / (arrived[~lost][-1] - arrived[~lost][0])
    print(f"server at 125 Hz, busy on both sides: {received:.1f} frames/s measured, "
          f"{counted:.1f} counted")
    assert received == pytest.approx(125, abs=0.5) and counted < 110
    # Without a server clock (all sent times equal), the receive times give the rate.
    assert preprocess.fresh_rate(t, np.zeros_like(t), np.arange(len(t))) == pytest.approx(
        125, rel=0.05)
    assert preprocess.fresh_rate(t[:1], sent[:1], seq[:1]) is None
    assert preprocess.fresh_rate(t, t, np.arange(len(t)), 10.0, 11.0) is None  # no frame


def test_a_rate_more_than_10_percent_off_is_a_problem_naming_both():
    assert preprocess.rate_problem(104.4, 125.0) == (
        "104.4 frames/s is 16 % off 125 Hz (more than 10 %)")
    assert preprocess.rate_problem(115.0, 125.0) is None  # 8 % off
    assert preprocess.rate_problem(None, 125.0) is None  # not measured


def test_the_peak_norm_runs_from_closing_to_opening():
    t = np.array([0.0, 0.1, 0.2, 0.3])
    units = np.array([[0.001, 0], [0.003, 0.004], [0.002, 0], [0.0, 0.009]])
    assert preprocess.peak_norm(t, units, t_open=0.3) == pytest.approx(0.005)
    assert preprocess.peak_norm(t, units) == pytest.approx(0.009)


def test_a_window_at_another_rate_keeps_its_seconds_and_steps():
    assert W.at_rate(125.0) == W  # the robot's window is its own rate's
    w100 = W.at_rate(100.0)
    assert (w100.n_window, w100.subsample, w100.n_steps) == (100, 4, 25)
    assert w100.sigma_samples * w100.period_s == pytest.approx(W.sigma_samples * W.period_s)
    assert W.at_rate(1000.0).n_steps == 25
    with pytest.raises(PreprocessError, match="below the model's step rate"):
        W.at_rate(10.0)


def test_held_edges_change_only_the_targets_samples_within_the_filters_reach():
    """A sequence that ends with the window: "hold" smooths against its end sample held; the
    target is the whole stream's away from the ends, and a ramp's last sample lies about
    0.4 sigma short of the ramp (what the docstring says)."""
    w = W.at_rate(100.0)
    long_times = np.arange(-50, 150) * w.period_s
    ramp = np.stack([long_times, np.sin(7 * long_times)], axis=1).astype(np.float32)
    t_stop = w.before_s  # the window starts at time 0
    whole = preprocess.smoothed_crop(long_times, ramp, t_stop, w)
    inside = (long_times >= 0) & (long_times < w.n_window * w.period_s - 1e-9)
    times, units = long_times[inside], ramp[inside]  # no stream beyond either end
    with pytest.raises(PreprocessError, match="of stream beyond each end"):
        preprocess.smoothed_crop(times, units, t_stop, w)
    held = preprocess.smoothed_crop(times, units, t_stop, w, edge="hold")
    m = w.smooth_margin
    assert held.shape == whole.shape == (100, 2)
    np.testing.assert_allclose(held[m:-m], whole[m:-m], atol=1e-6)
    lag = (whole[-1, 0] - held[-1, 0]) / (w.sigma_samples * w.period_s)
    print(f"ramp's last target sample short by {lag:.3f} sigma")
    assert 0.3 < lag < 0.5
    # A stream long enough: "hold" is "require", to the bit.
    np.testing.assert_array_equal(
        preprocess.smoothed_crop(long_times, ramp, t_stop, w, edge="hold"), whole)
    # The window itself still has to lie in the stream.
    with pytest.raises(PreprocessError, match="leaves the stream"):
        preprocess.smoothed_crop(times[5:], units[5:], t_stop, w, edge="hold")
