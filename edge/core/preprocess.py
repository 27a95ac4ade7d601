"""Preprocessing of tactile streams: the single implementation used by the robot and by
training, so what the model is trained on and what the robot feeds it cannot drift apart.

Tactile units are ``(raw - tare) / 65536`` per channel. The model sees a window of
``[t_stop - 0.4 s, t_stop + 0.6 s)`` on an ideal 125 Hz grid placed from frame timestamps
(so a late sampler wake-up never shifts the data), subsampled to 25 Hz at an offset 0..4:
the model input ``X``, never smoothed. The training target ``X_bar`` is the observed 125 Hz
stream smoothed with a Gaussian (sigma 3 samples) *before* the crop, then cropped and
subsampled the same way: the stream is resampled on the same 125 Hz grid extended by the
filter's reach on both sides, smoothed, and the window cut out of the middle, so its first and
last samples average real neighbours instead of a padded edge.

A stream at another rate than the grid's (some xela_server installs send about 100 frames/s)
is interpolated onto the same 125 Hz grid: the window keeps its length in time, its 125
samples and its 25 steps, but each step is made of fewer real frames, and the stop that
starts it comes later after the crossing. Presses at 100 Hz are therefore comparable with
one another, not with presses at 125 Hz: :func:`stream_rate` measures a press's rate and
:func:`rate_problem` says when it is more than ``RATE_TOLERANCE`` off a grid or a reference.

Another sensor's evenly sampled sequence (train.learn.sequences) is cut by the same functions
at its own rate instead (:meth:`WindowSpec.at_rate`), and may end with its window: its
smoothed target then holds the end samples (``edge="hold"``, :func:`smoothed_crop`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from edge.core.errors import PreprocessError

UNITS_SCALE = 65536.0
# scipy's gaussian_filter1d reaches this many sigmas either side (its ``truncate``).
GAUSSIAN_TRUNCATE = 4.0


@dataclass(frozen=True)
class WindowSpec:
    """Where and how the model's input is cut from the stream (docs/method.md,
    'Crop and preprocessing')."""

    rate_hz: float = 125.0
    before_s: float = 0.4
    after_s: float = 0.6
    subsample: int = 5
    sigma_samples: float = 3.0

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def n_window(self) -> int:
        return round((self.before_s + self.after_s) * self.rate_hz)

    @property
    def n_steps(self) -> int:
        return self.n_window // self.subsample

    @property
    def smooth_margin(self) -> int:
        """Samples the Gaussian reaches on each side: the stream the target needs beyond the
        window (12 at sigma 3, 96 ms at 125 Hz)."""
        return int(GAUSSIAN_TRUNCATE * self.sigma_samples + 0.5)

    @property
    def last_sample_s(self) -> float:
        """The window's last sample time from the stop (``after_s`` less one period): the
        crop is complete with the first frame at or past it."""
        return (self.n_window - 1) * self.period_s - self.before_s

    @property
    def step_hz(self) -> float:
        """The model's steps per second (25 Hz by default)."""
        return self.rate_hz / self.subsample

    def at_rate(self, rate_hz: float) -> WindowSpec:
        """The same window at another sample rate (a sequence recorded at ``rate_hz``, taken
        at its own rate): the same seconds before and after the stop, steps as near this
        window's step rate as a whole number of samples allows, and the same smoothing in
        time. At this window's own rate it is this window."""
        if not rate_hz >= self.step_hz:
            raise PreprocessError(f"rate {rate_hz:g} Hz is below the model's step rate "
                                  f"{self.step_hz:g} Hz: nothing to subsample")
        return replace(self, rate_hz=float(rate_hz),
                       subsample=max(1, round(rate_hz / self.step_hz)),
                       sigma_samples=self.sigma_samples * rate_hz / self.rate_hz)

    def grid(self, t_stop: float, margin: int = 0) -> np.ndarray:
        """The ideal sample times of the window around ``t_stop``, with ``margin`` more
        samples of the same grid on each side."""
        steps = np.arange(-margin, self.n_window + margin)
        return t_stop - self.before_s + steps * self.period_s


DEFAULT_WINDOW = WindowSpec()

# Rates further apart than this (relative) are two rates: the crop of a press at one is
# interpolated from a different number of frames than at the other.
RATE_TOLERANCE = 0.10
# What the smoothed target does where the stream ends within the filter's reach: "require"
# refuses (a press recording keeps 0.2 s beyond the window, so a short one is a defect);
# "hold" smooths against the stream's first and last samples held beyond its ends (a
# sequence from another sensor may end where the grasp ends).
Edge = Literal["require", "hold"]
# Where a stream's rate is set, for whoever is told it is off.
RATE_SETTING = ("the pads' rate is set in xela_server's configuration ([sim] sensor_rate_hz "
                "on the emulated robot)")


@dataclass(frozen=True)
class StreamRate:
    """The stream's measured rate around one press (:func:`fresh_rate`), frames per second
    (None: fewer than two fresh frames)."""

    window_hz: float | None  # over the model's crop window
    press_hz: float | None  # over the whole press recording


def fresh_rate(times: np.ndarray, sent: np.ndarray, seq: np.ndarray, t0: float = -np.inf,
               t1: float = np.inf) -> float | None:
    """The rate the server sends at, frames/s, from the frames received (``times``) in
    ``[t0, t1)``: one over the median interval between consecutive fresh frames (a repeated
    sequence number brings nothing new), each divided by the sequence numbers it spans (a
    frame lost on the way), on the server's clock ``sent``. A busy receiving host bunches the
    arrivals and a busy sender skips a tick now and then: neither moves the median, so the
    figure is the rate xela_server is set to. On the receive clock where the server's gives
    no interval; None with fewer than two fresh frames."""
    times, sent, seq = (np.asarray(a, dtype=np.float64) for a in (times, sent, seq))
    fresh = np.ones(len(seq), dtype=bool)
    fresh[1:] = seq[1:] != seq[:-1]
    keep = fresh & (times >= t0) & (times < t1)
    if keep.sum() < 2:
        return None
    steps = np.diff(seq[keep])
    steps = np.where(steps > 0, steps, 1.0)  # (a server restarted: its numbers start again)
    for clock in (sent[keep], times[keep]):
        period = float(np.median(np.diff(clock) / steps))
        if period > 0:
            return 1.0 / period
    return None


def stream_rate(times: np.ndarray, sent: np.ndarray, seq: np.ndarray, t_stop: float,
                spec: WindowSpec = DEFAULT_WINDOW) -> StreamRate:
    """The rate (:func:`fresh_rate`) over the crop window around ``t_stop`` and over all the
    frames given."""
    return StreamRate(fresh_rate(times, sent, seq, t_stop - spec.before_s,
                                 t_stop + spec.after_s),
                      fresh_rate(times, sent, seq))


def rate_problem(rate_hz: float | None, expected_hz: float) -> str | None:
    """Why ``rate_hz`` is not ``expected_hz`` (more than ``RATE_TOLERANCE`` apart), else
    None (also where no rate was measured)."""
    if rate_hz is None or abs(rate_hz / expected_hz - 1) <= RATE_TOLERANCE:
        return None
    return (f"{rate_hz:.1f} frames/s is {abs(rate_hz / expected_hz - 1) * 100:.0f} % off "
            f"{expected_hz:g} Hz (more than {RATE_TOLERANCE * 100:.0f} %)")


def tare(raw: np.ndarray) -> np.ndarray:
    """Per-channel mean of unloaded raw samples, shape (C,)."""
    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] == 0:
        raise PreprocessError("tare needs at least one unloaded frame (shape (N, C))")
    return raw.astype(np.float64).mean(axis=0)


def to_units(raw: np.ndarray, tare_counts: np.ndarray) -> np.ndarray:
    """Raw counts to tactile units, float32."""
    return ((np.asarray(raw, dtype=np.float64) - tare_counts) / UNITS_SCALE).astype(np.float32)


def norm(units: np.ndarray) -> np.ndarray | float:
    """L2 norm over channels: the quantity compared with x_th."""
    return np.linalg.norm(units, axis=-1)


def peak_norm(times: np.ndarray, units: np.ndarray, t_open: float | None = None) -> float:
    """A press's peak norm, the one figure collect, ``dataset summary``, episodes and the
    operator page show as "peak": the highest tactile norm over the press's tare from the
    gripper closing to its opening (``t_open``; None: every frame), the hold's squeeze
    included. The press controller keeps the same maximum over the frames it checks while
    it watches the threshold; the frames before closing (the tare) stay below x_th."""
    times = np.asarray(times, dtype=np.float64)
    level = np.asarray(norm(units))
    if t_open is not None:
        level = level[times < t_open]
    return float(level.max()) if level.size else 0.0


def tared_norms(times: np.ndarray, raw: np.ndarray, tare_s: float) -> np.ndarray:
    """The norm a press compares with x_th, frame by frame: tared over the first ``tare_s``
    of the frames as the press tares, the frames after it in tactile units. On idle frames:
    the pads' noise as the press sees it."""
    times = np.asarray(times, dtype=np.float64)
    raw = np.asarray(raw)
    tared = times < times[0] + tare_s
    if tared.all():
        raise PreprocessError(f"{times.shape[0]} frames over {times[-1] - times[0]:.2f} s: "
                              f"none left after a {tare_s} s tare")
    return np.asarray(norm(to_units(raw[~tared], tare(raw[tared]))))


def resample(times: np.ndarray, values: np.ndarray, grid: np.ndarray,
             method: Literal["linear", "hold"] = "linear") -> np.ndarray:
    """Values of an irregular stream at ``grid`` times.

    ``linear`` interpolates between the frames around each grid time; ``hold`` takes the
    latest frame at or before it (what a sample-and-hold sampler sees). The grid must lie
    within the stream: extrapolation would invent data.
    """
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values)
    if times.ndim != 1 or values.shape[0] != times.shape[0] or times.shape[0] < 2:
        raise PreprocessError("resample needs >= 2 frames with one time each")
    if grid[0] < times[0] or grid[-1] > times[-1]:
        raise PreprocessError(
            f"window [{grid[0]:.3f}, {grid[-1]:.3f}] s leaves the stream "
            f"[{times[0]:.3f}, {times[-1]:.3f}] s: record longer around the stop")
    right = np.searchsorted(times, grid, side="right")
    if method == "hold":
        return values[right - 1].astype(np.float32)
    right = np.clip(right, 1, times.shape[0] - 1)
    left = right - 1
    span = times[right] - times[left]
    w = np.where(span > 0, (grid - times[left]) / np.where(span > 0, span, 1.0), 1.0)
    w = np.clip(w, 0.0, 1.0)[:, None]
    lo = values[left].astype(np.float64)
    hi = values[right].astype(np.float64)
    return (lo + w * (hi - lo)).astype(np.float32)


def crop(times: np.ndarray, units: np.ndarray, t_stop: float,
         spec: WindowSpec = DEFAULT_WINDOW) -> np.ndarray:
    """The 125 Hz window around ``t_stop``, shape (n_window, C)."""
    return resample(times, units, spec.grid(t_stop))


def subsample(window: np.ndarray, offset: int, spec: WindowSpec = DEFAULT_WINDOW) -> np.ndarray:
    """Every ``subsample``-th row starting at ``offset``: shape (n_steps, C)."""
    if not 0 <= offset < spec.subsample:
        raise PreprocessError(f"offset {offset} must be in 0..{spec.subsample - 1}")
    if window.shape[0] != spec.n_window:
        raise PreprocessError(f"window has {window.shape[0]} rows, expected {spec.n_window}")
    return window[offset::spec.subsample]


def smooth(window: np.ndarray, spec: WindowSpec = DEFAULT_WINDOW) -> np.ndarray:
    """Gaussian smoothing along time (edges padded with their nearest sample)."""
    # Imported here: scipy.ndimage takes a third of a second to import, and only training
    # smooths (the model input never is), so the daemon's processes need not pay for it.
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(window, spec.sigma_samples, axis=0, mode="nearest",
                             truncate=GAUSSIAN_TRUNCATE)


def smoothed_crop(times: np.ndarray, units: np.ndarray, t_stop: float,
                  spec: WindowSpec = DEFAULT_WINDOW, edge: Edge = "require") -> np.ndarray:
    """The target's window: the stream on the window's grid extended by the filter's reach
    (``spec.smooth_margin`` samples each side), smoothed, then cropped to the window.

    The result equals smoothing an unbounded stream: no sample of the window is filtered
    against a padded edge. With ``edge="require"`` the recording must reach that far
    (recordings keep 0.2 s beyond the window; the filter needs 0.096 s at 125 Hz). With
    ``edge="hold"`` a stream that ends within the reach (the window itself must lie in it)
    is smoothed as far as it goes with its end sample held beyond it: the target's samples
    within ``smooth_margin`` of that end are pulled toward the end's value, so a stream still
    rising or falling there is flattened (on a ramp the last sample lies about 0.4 sigma of
    the ramp short of the stream); samples further in are as with the whole stream.
    """
    margin = spec.smooth_margin
    wide = spec.grid(t_stop, margin)
    lost_before = lost_after = 0
    if edge == "hold":
        times = np.asarray(times, dtype=np.float64)
        lost_before = min(margin, int(np.searchsorted(wide, times[0], side="left")))
        lost_after = min(margin, len(wide) - int(np.searchsorted(wide, times[-1],
                                                                 side="right")))
        wide = wide[lost_before:len(wide) - lost_after]
    try:
        wide_units = resample(times, units, wide)
    except PreprocessError as exc:
        raise PreprocessError(
            f"{exc}; the smoothed target also needs {margin} samples "
            f"({margin * spec.period_s * 1e3:.0f} ms) of stream beyond each end of the "
            "window") from None
    start = margin - lost_before
    return smooth(wide_units, spec)[start:start + spec.n_window]


def model_input(times: np.ndarray, units: np.ndarray, t_stop: float,
                spec: WindowSpec = DEFAULT_WINDOW, offset: int = 0) -> np.ndarray:
    """Recognition-time input X: one subsampled window, shape (n_steps, C), float32."""
    return subsample(crop(times, units, t_stop, spec), offset, spec)


def training_pairs(times: np.ndarray, units: np.ndarray, t_stop: float,
                   spec: WindowSpec = DEFAULT_WINDOW, edge: Edge = "require"
                   ) -> tuple[np.ndarray, np.ndarray]:
    """All offsets of one press: inputs X (the raw crop) and targets X_bar (smoothed before
    the crop, ``edge`` as :func:`smoothed_crop`), each (subsample, n_steps, C)."""
    window = crop(times, units, t_stop, spec)
    target = smoothed_crop(times, units, t_stop, spec, edge)
    xs = np.stack([subsample(window, o, spec) for o in range(spec.subsample)])
    ts = np.stack([subsample(target, o, spec) for o in range(spec.subsample)])
    return xs.astype(np.float32), ts.astype(np.float32)


def recording_units(rec) -> np.ndarray:
    """A recording's frames in tactile units against its own tare, (N, C) float32."""
    return to_units(rec.frames, rec.tare)


def recording_peak(rec) -> float:
    """:func:`peak_norm` of a :class:`edge.core.recording.Recording` (up to its ``t_open``)."""
    t_open = rec.extra.get("t_open")
    return peak_norm(rec.recv_time, recording_units(rec),
                     t_open if isinstance(t_open, int | float) else None)


def recording_rate(rec, spec: WindowSpec = DEFAULT_WINDOW) -> StreamRate:
    """The stream's rate in a :class:`edge.core.recording.Recording`."""
    return stream_rate(rec.recv_time, rec.sensor_time, rec.seq, rec.t_stop, spec)


def recording_pairs(rec, spec: WindowSpec = DEFAULT_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """Training pairs (X, X_bar) of a :class:`edge.core.recording.Recording`."""
    return training_pairs(rec.recv_time, recording_units(rec), rec.t_stop, spec)
