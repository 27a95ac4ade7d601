"""Real tactile recordings for the ``xela_server`` emulator to replay.

``vt-edge sim serve --replay FILE`` serves the frames of a recording at their recorded
timing, so the client, the ring, the health checks and collect mode run on real data. Two
formats are read:

- XELA CSV, as in the public slip-control dataset (``tests/fixtures/xela/real-xr1944/``): a
  directory with ``xela_sensor1.csv``, ``xela_sensor2.csv``, ... (one row per frame, columns
  ``txl1_x, txl1_y, txl1_z, ...``, raw counts), timed by the ``time`` column of
  ``robot_state.csv`` (seconds, one row per frame) or, without it, evenly at
  ``meta_data.csv``'s ``frequency_hz``. ``FILE`` may be the directory or one of its files.
- a vtzero press recording (``.press.npz``, from collect mode or the simulator), timed by its
  receive times; its pads as its metadata names them (two of 16 taxels when it names none).

Anything else, or a file that does not hold what its format says, is refused with a
:class:`~edge.core.errors.RecordingError` naming the file and the problem.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from edge.core import recording
from edge.core.errors import RecordingError
from edge.core.layout import PadLayout

SENSOR_FILE = "xela_sensor{}.csv"
TIME_FILE = "robot_state.csv"
TIME_COLUMN = "time"
META_FILE = "meta_data.csv"
RATE_COLUMN = "frequency_hz"
# Anything longer is not a recording to replay (an hour at 125 Hz is 450k frames).
MAX_FRAMES = recording.MAX_FRAMES
# More pads than this on one server is a misread directory, not a robot.
MAX_SENSORS = 16
_AXES = "xyz"


@dataclass(frozen=True, eq=False)
class Replay:
    """A recording to replay: raw frames and when each came, from the first frame."""

    frames: np.ndarray  # (N, sensors * taxels * 3) uint16, channel order of edge.hw.contracts
    times_s: np.ndarray  # (N,) float64, 0 for the first frame, never decreasing
    sensors: int
    taxels: int
    source: str  # the file(s), for messages

    @property
    def duration_s(self) -> float:
        return float(self.times_s[-1])

    @property
    def period_s(self) -> float:
        """The typical frame interval: the pause before the first frame comes again."""
        return float(np.median(np.diff(self.times_s)))

    def describe(self) -> str:
        return (
            f"{self.source}: {len(self.frames)} frames of {self.sensors} x "
            f"{self.taxels} taxels over {self.duration_s:.2f} s "
            f"(~{(len(self.frames) - 1) / max(self.duration_s, 1e-9):.0f} frames/s)"
        )


def load_replay(path: str | Path) -> Replay:
    """Read a recording to replay (see the module's formats); RecordingError on any defect."""
    path = Path(path)
    if not path.exists():
        raise RecordingError(f"replay {path}: no such file or directory")
    if path.is_dir():
        return _load_csv_dir(path)
    if path.name.endswith(recording.SUFFIX):
        return _load_press(path)
    if path.suffix == ".csv":
        return _load_csv_dir(path.parent)
    raise RecordingError(
        f"replay {path}: not a recording to replay; give a directory of XELA CSV files "
        f"({SENSOR_FILE.format(1)}, ...), one of its files, or a {recording.SUFFIX} file"
    )


def _load_press(path: Path) -> Replay:
    rec = recording.load(path)
    # A press file names its pads when they are not two XR1944 (16 taxels); CSV files say theirs.
    layout = PadLayout.of_recording(rec.extra, rec.channels)
    times = rec.recv_time - rec.recv_time[0]
    return Replay(rec.frames, times, layout.pads, layout.taxels, str(path))


def _load_csv_dir(directory: Path) -> Replay:
    files = []
    for i in range(1, MAX_SENSORS + 2):
        f = directory / SENSOR_FILE.format(i)
        if not f.is_file():
            break
        files.append(f)
    if not files:
        raise RecordingError(
            f"replay {directory}: no {SENSOR_FILE.format(1)} there; a XELA CSV recording "
            f"has one {SENSOR_FILE.format('N')} per sensor, numbered from 1"
        )
    if len(files) > MAX_SENSORS:
        raise RecordingError(f"replay {directory}: more than {MAX_SENSORS} sensor files")
    pads = [_read_sensor(f) for f in files]
    taxels = {p.shape[1] // 3 for p in pads}
    if len(taxels) != 1:
        sizes = ", ".join(f"{f.name} {p.shape[1] // 3}" for f, p in zip(files, pads, strict=True))
        raise RecordingError(f"replay {directory}: sensors differ in taxels ({sizes})")
    rows = {len(p) for p in pads}
    if len(rows) != 1:
        sizes = ", ".join(f"{f.name} {len(p)}" for f, p in zip(files, pads, strict=True))
        raise RecordingError(
            f"replay {directory}: the sensor files have different numbers of rows ({sizes}); "
            "each row is one frame of every sensor"
        )
    n = rows.pop()
    times = _read_times(directory, n)
    frames = np.concatenate(pads, axis=1)
    source = f"{directory} ({', '.join(f.name for f in files)})"
    return Replay(frames, times, len(files), taxels.pop(), source)


def _read_sensor(path: Path) -> np.ndarray:
    """One sensor's CSV as (rows, taxels * 3) uint16, every field checked."""
    try:
        return _parse_sensor(path)
    except (UnicodeDecodeError, csv.Error) as exc:
        raise RecordingError(f"replay {path}: not a CSV text file ({exc})") from None


def _parse_sensor(path: Path) -> np.ndarray:
    with _open_csv(path) as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if not header:
            raise RecordingError(f"replay {path}: empty file")
        header = [h.strip() for h in header]
        if len(header) % 3 or len(header) == 0:
            raise RecordingError(f"replay {path}: {len(header)} columns is not x, y, z per taxel")
        expected = [f"txl{k}_{a}" for k in range(1, len(header) // 3 + 1) for a in _AXES]
        if header != expected:
            bad = next(i for i, (h, e) in enumerate(zip(header, expected, strict=True)) if h != e)
            raise RecordingError(
                f"replay {path}: column {bad + 1} is {header[bad]!r:.30}, expected "
                f"{expected[bad]!r} (columns txl1_x, txl1_y, txl1_z, txl2_x, ...)"
            )
        values: list[list[float]] = []
        for line, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) != len(header):
                raise RecordingError(
                    f"replay {path}, line {line}: {len(row)} values, the header has {len(header)}"
                )
            values.append([_count(v, path, line) for v in row])
            if len(values) > MAX_FRAMES:
                raise RecordingError(f"replay {path}: more than {MAX_FRAMES} rows")
    if len(values) < 2:
        raise RecordingError(f"replay {path}: {len(values)} data row(s); a replay needs 2 or more")
    return np.asarray(values).astype(np.uint16)


def _count(text: str, path: Path, line: int) -> float:
    try:
        value = float(text)
    except ValueError:
        raise RecordingError(
            f"replay {path}, line {line}: {text.strip()!r:.20} is not a number"
        ) from None
    if not (math.isfinite(value) and value == int(value) and 0 <= value <= 0xFFFF):
        raise RecordingError(
            f"replay {path}, line {line}: {text.strip()!r:.20} is not a 16-bit count "
            "(an integer 0..65535)"
        )
    return value


def _read_times(directory: Path, n: int) -> np.ndarray:
    """Frame times from robot_state.csv, else evenly at meta_data.csv's rate."""
    path = directory / TIME_FILE
    if path.is_file():
        column = _column(path, TIME_COLUMN)
        if len(column) != n:
            raise RecordingError(
                f"replay {path}: {len(column)} rows of {TIME_COLUMN!r} for {n} frames; it "
                "must have one row per frame"
            )
        times = np.asarray(column)
        if np.any(np.diff(times) < 0):
            i = int(np.argmax(np.diff(times) < 0))
            raise RecordingError(
                f"replay {path}, line {i + 3}: {TIME_COLUMN!r} goes backwards "
                f"({times[i]} -> {times[i + 1]})"
            )
        return times - times[0]
    meta = directory / META_FILE
    if meta.is_file():
        rates = _column(meta, RATE_COLUMN)
        if len(rates) != 1 or not 0 < rates[0] <= 10_000:
            raise RecordingError(
                f"replay {meta}: {RATE_COLUMN!r} must be one rate in (0, 10000] Hz, got {rates[:3]}"
            )
        return np.arange(n) / rates[0]
    raise RecordingError(
        f"replay {directory}: no timing; it needs {TIME_FILE} (a {TIME_COLUMN!r} column, one "
        f"row per frame) or {META_FILE} (a {RATE_COLUMN!r} column)"
    )


def _column(path: Path, name: str) -> list[float]:
    try:
        return _parse_column(path, name)
    except (UnicodeDecodeError, csv.Error) as exc:
        raise RecordingError(f"replay {path}: not a CSV text file ({exc})") from None


def _parse_column(path: Path, name: str) -> list[float]:
    with _open_csv(path) as fh:
        reader = csv.reader(fh)
        header = [h.strip() for h in next(reader, [])]
        if name not in header:
            raise RecordingError(f"replay {path}: no {name!r} column")
        index = header.index(name)
        out = []
        for line, row in enumerate(reader, start=2):
            if not row:
                continue
            try:
                value = float(row[index])
            except (IndexError, ValueError):
                raise RecordingError(
                    f"replay {path}, line {line}: {name!r} is missing or not a number"
                ) from None
            if not math.isfinite(value):
                raise RecordingError(f"replay {path}, line {line}: {name!r} is {value}")
            out.append(value)
            if len(out) > MAX_FRAMES:
                raise RecordingError(f"replay {path}: more than {MAX_FRAMES} rows")
    return out


def _open_csv(path: Path) -> TextIO:
    try:
        # newline="": the csv module handles line endings itself.
        return path.open(newline="", encoding="utf-8")
    except OSError as exc:
        raise RecordingError(f"replay {path}: cannot read: {exc.strerror or exc}") from None
