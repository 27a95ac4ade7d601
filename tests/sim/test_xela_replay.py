"""``vt-edge sim serve --replay``: the xela_server emulator serving a real recording.

The real client (edge/hw/xela.py), the daemon's sensor path (ring, sampler, sensor task) and
collect mode run against real XR1944 frames (tests/fixtures/xela/real-xr1944/). Timing bounds
are generous (a loaded two-core host); the measured figures are printed (-s).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from edge.core import recording
from edge.core.config import SensorConfig
from edge.core.errors import RecordingError, StaleSensorError
from edge.hw.contracts import TactileFrame
from edge.hw.xela import XelaClient
from edge.lab.collect import collect
from edge.runtime.ring import FrameRing
from edge.runtime.sensor import Sampler, SensorTask
from edge.sim.robot import SimRobot
from edge.sim.xela_replay import load_replay
from edge.sim.xela_server import XelaServerEmulator
from tests.support.daemon import ROOT, base_config

FIXTURE = ROOT / "tests" / "fixtures" / "xela" / "real-xr1944"
FULL = FIXTURE / "data_sample_2022-02-22-15-15-00"  # 259 frames, 4.3 s
SHORT = FIXTURE / "data_sample_2022-02-21-09-58-49"  # 70 frames, 1.2 s
STARTUP_TIMEOUT_S = 5.0
# The client's staleness timeout here (base_config's; the shipped 0.1 s is tested apart in
# tests/hw/test_xela_client.py) and a bound a loaded host always meets for the stale report.
STALE_TIMEOUT_S = 0.25
STALE_BOUND_S = 1.0
# Frames are sent at their recorded times; a loaded host delays some. Median and worst
# allowed error of a frame's arrival against the recording's schedule.
TIMING_MEDIAN_BOUND_S = 0.005
TIMING_MAX_BOUND_S = 0.1


def csv_rows(directory: Path) -> np.ndarray:
    """The sensor files read independently of the loader: (N, 96) counts."""
    pads = [np.loadtxt(directory / f"xela_sensor{i}.csv", delimiter=",", skiprows=1)
            for i in (1, 2)]
    return np.concatenate(pads, axis=1)


def test_the_loader_reads_a_real_recording_intact():
    rep = load_replay(FULL)
    assert (rep.sensors, rep.taxels, rep.frames.shape) == (2, 16, (259, 96))
    assert rep.frames.dtype == np.uint16
    np.testing.assert_array_equal(rep.frames, csv_rows(FULL))
    # Timed by robot_state.csv's time column: uneven, ~60 frames/s.
    assert rep.times_s[0] == 0.0 and rep.duration_s == pytest.approx(4.314)
    assert 0.015 < rep.period_s < 0.019
    # One of its files names the same recording; without robot_state.csv the rows are
    # evenly spaced at meta_data.csv's frequency_hz.
    assert load_replay(FULL / "xela_sensor2.csv").frames.shape == (259, 96)


def test_without_row_times_the_rate_in_the_metadata_is_used(tmp_path):
    for name in ("xela_sensor1.csv", "xela_sensor2.csv", "meta_data.csv"):
        (tmp_path / name).write_bytes((SHORT / name).read_bytes())
    rep = load_replay(tmp_path)
    np.testing.assert_allclose(np.diff(rep.times_s), 1 / 59.7544117)


def _broken(tmp_path: Path, edit) -> Path:
    """A copy of the short recording with one file changed by ``edit(directory)``."""
    directory = tmp_path / "rec"
    directory.mkdir()
    for f in SHORT.iterdir():
        (directory / f.name).write_bytes(f.read_bytes())
    edit(directory)
    return directory


def _rewrite(path: Path, fn) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(fn(lines)) + "\n")


def _set_field(line: str, index: int, value: str) -> str:
    fields = line.split(",")
    fields[index] = value
    return ",".join(fields)


BAD_FILES = {
    "missing": (lambda d: None, "no such file", "nowhere"),
    "no sensor files": (lambda d: [p.unlink() for p in d.glob("xela_sensor*.csv")],
                        "no xela_sensor1.csv there", ""),
    "bad header": (lambda d: _rewrite(d / "xela_sensor1.csv",
                                      lambda ls: [ls[0].replace("txl2_y", "txl2_q"), *ls[1:]]),
                   "column 5 is 'txl2_q', expected 'txl2_y'", "xela_sensor1.csv"),
    "not a number": (lambda d: _rewrite(d / "xela_sensor2.csv",
                                        lambda ls: [*ls[:3], _set_field(ls[3], 7, "abc"),
                                                    *ls[4:]]),
                     "line 4: 'abc' is not a number", "xela_sensor2.csv"),
    "out of range": (lambda d: _rewrite(d / "xela_sensor1.csv",
                                        lambda ls: [ls[0], _set_field(ls[1], 0, "70000.0"),
                                                    *ls[2:]]),
                     "line 2: '70000.0' is not a 16-bit count", "xela_sensor1.csv"),
    "fractional": (lambda d: _rewrite(d / "xela_sensor1.csv",
                                      lambda ls: [ls[0], _set_field(ls[1], 2, "38000.5"),
                                                  *ls[2:]]),
                   "is not a 16-bit count", "xela_sensor1.csv"),
    "short row": (lambda d: _rewrite(d / "xela_sensor1.csv",
                                     lambda ls: [*ls[:5], ls[5].rsplit(",", 1)[0], *ls[6:]]),
                  "line 6: 47 values, the header has 48", "xela_sensor1.csv"),
    "row counts differ": (lambda d: _rewrite(d / "xela_sensor2.csv", lambda ls: ls[:-3]),
                          "different numbers of rows (xela_sensor1.csv 70, xela_sensor2.csv 67)",
                          ""),
    "times wrong length": (lambda d: _rewrite(d / "robot_state.csv", lambda ls: ls[:-1]),
                           "69 rows of 'time' for 70 frames", "robot_state.csv"),
    "times go back": (lambda d: _rewrite(d / "robot_state.csv",
                                         lambda ls: [*ls[:10], "0.0", *ls[11:]]),
                      "line 11: 'time' goes backwards", "robot_state.csv"),
    "no timing": (lambda d: [(d / "robot_state.csv").unlink(), (d / "meta_data.csv").unlink()],
                  "no timing", ""),
    "binary": (lambda d: (d / "xela_sensor1.csv").write_bytes(b"\x00\xff\xfe" * 100),
               "not a CSV text file", "xela_sensor1.csv"),
    "one row": (lambda d: [_rewrite(d / f"xela_sensor{i}.csv", lambda ls: ls[:2])
                           for i in (1, 2)],
                "1 data row(s); a replay needs 2 or more", "xela_sensor1.csv"),
}


@pytest.mark.parametrize("case", BAD_FILES)
def test_a_bad_file_is_refused_naming_the_file_and_the_problem(tmp_path, case):
    edit, problem, file_name = BAD_FILES[case]
    path = tmp_path / "nowhere" if case == "missing" else _broken(tmp_path, edit)
    with pytest.raises(RecordingError) as err:
        load_replay(path)
    message = str(err.value)
    print(f"\n  {case}: {message}")
    assert str(path) in message and problem in message and file_name in message


def test_other_files_are_refused(tmp_path):
    npy = tmp_path / "frames.npy"
    np.save(npy, np.zeros((3, 96), dtype=np.uint16))
    with pytest.raises(RecordingError, match="not a recording to replay"):
        load_replay(npy)
    fake = tmp_path / "x.press.npz"
    fake.write_bytes(b"PK not really")
    with pytest.raises(RecordingError, match="truncated or corrupt"):
        load_replay(fake)


def test_a_press_recording_replays_at_its_receive_times(tmp_path):
    from tests.support.presses import recording_of

    rec = recording_of("konjac", 3)
    path = recording.save(rec, tmp_path / f"konjac{recording.SUFFIX}")
    rep = load_replay(path)
    np.testing.assert_array_equal(rep.frames, rec.frames)
    np.testing.assert_allclose(rep.times_s, rec.recv_time - rec.recv_time[0])
    assert (rep.sensors, rep.taxels) == (2, 16)


def config_for(srv: XelaServerEmulator) -> SensorConfig:
    return SensorConfig(url=srv.url, stale_timeout_s=STALE_TIMEOUT_S, reconnect_max_backoff_s=0.2)


def timing_errors(frames: list[TactileFrame], times_s: np.ndarray) -> np.ndarray:
    """|arrival - recorded time| per frame, the schedule anchored on its best fit."""
    recv = np.array([f.recv_time for f in frames])
    offset = np.median(recv - times_s)
    return np.abs(recv - times_s - offset)


@pytest.mark.asyncio
async def test_the_client_gets_every_frame_intact_at_its_time_then_stale():
    rep = load_replay(FULL)
    async with XelaServerEmulator(port=0, replay=rep, loop=False) as server:
        async with XelaClient(config_for(server)) as client:
            frames: list[TactileFrame] = []
            with pytest.raises(StaleSensorError) as err:
                async for frame in client.frames(first_timeout_s=STARTUP_TIMEOUT_S):
                    frames.append(frame)
            after_last_s = time.monotonic() - frames[-1].recv_time
            fresh = client.is_fresh()
            stats = client.stats
    got = np.array([f.raw for f in frames])
    errors = timing_errors(frames, rep.times_s)
    span = frames[-1].recv_time - frames[0].recv_time
    print(f"\n  {len(frames)} frames over {span:.3f} s (recorded {rep.duration_s:.3f} s); "
          f"timing error median {np.median(errors) * 1e3:.2f} ms, max {errors.max() * 1e3:.1f} ms; "
          f"stale {after_last_s * 1e3:.0f} ms after the last frame; {stats}\n  {err.value}")
    assert len(frames) == len(rep.frames) == 259
    np.testing.assert_array_equal(got, rep.frames)  # the recorded counts, in order
    assert [f.seq for f in frames] == list(range(frames[0].seq, frames[0].seq + 259))
    assert (stats.repeats, stats.skipped, stats.lost, stats.overruns) == (0, 0, 0, 0)
    assert np.median(errors) < TIMING_MEDIAN_BOUND_S and errors.max() < TIMING_MAX_BOUND_S
    # The recording's end reads as a server gone quiet: stale, never "no contact".
    assert not fresh
    assert STALE_TIMEOUT_S * 0.9 < after_last_s < STALE_BOUND_S
    assert server.replay_laps == 1


class Watch:
    """Stands in for the press controller: what the sensor task tells it."""

    def __init__(self) -> None:
        self.sensor_is_stale = False
        self.stale: list[BaseException] = []
        self.fresh_again = 0
        self.frames = 0
        self.went_stale = asyncio.Event()

    async def check(self, raw: np.ndarray, recv_time: float) -> None:
        self.frames += 1

    def sensor_stale(self, exc: BaseException) -> None:
        self.sensor_is_stale = True
        self.stale.append(exc)
        self.went_stale.set()

    def sensor_fresh(self) -> None:
        self.sensor_is_stale = False
        self.fresh_again += 1


@pytest.mark.asyncio
async def test_the_sensor_path_on_a_looping_replay():
    """Ring, sampler and sensor task on a real 60 frames/s stream, two laps and a half:
    every frame in the ring is the recording's, in order across the wrap; the 125 Hz
    sampler counts the ticks without a new frame; the stream never goes stale."""
    rep = load_replay(SHORT)
    n = len(rep.frames)
    lap_s = rep.duration_s + rep.period_s
    watch = Watch()
    async with XelaServerEmulator(port=0, replay=rep, loop=True) as server:
        async with XelaClient(config_for(server)) as client:
            ring = FrameRing(96, 1000)
            sampler = Sampler(ring, 125.0)
            task = SensorTask(client, ring, watch)  # type: ignore[arg-type]
            runs = [asyncio.create_task(task.run()), asyncio.create_task(sampler.run())]
            try:
                await asyncio.sleep(2.5 * lap_s)
            finally:
                for run in runs:
                    run.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await run
            laps = server.replay_laps
    got = ring.raw[: ring.count]
    # Each frame is a recorded row; consecutive frames are consecutive rows, lap after lap.
    first = int(np.flatnonzero((rep.frames == got[0]).all(axis=1))[0])
    expected = rep.frames[(first + np.arange(len(got))) % n]
    st = sampler.stats
    print(f"\n  {len(got)} frames ({laps} laps of {n}); sampler {st.ticks} ticks, "
          f"{st.gaps} without a new frame ({st.gaps / st.ticks:.0%}), {st.extra_frames} "
          f"extra; stale reports {len(watch.stale)}")
    np.testing.assert_array_equal(got, expected)
    assert laps >= 2 and len(got) >= 2 * n
    assert not watch.stale and not watch.sensor_is_stale
    # ~60 frames/s sampled at 125 Hz: about half the ticks see no new frame.
    assert 0.3 < st.gaps / st.ticks < 0.7


@pytest.mark.asyncio
async def test_the_sensor_task_reports_stale_when_the_replay_ends():
    rep = load_replay(SHORT)
    watch = Watch()
    async with XelaServerEmulator(port=0, replay=rep, loop=False) as server:
        async with XelaClient(config_for(server)) as client:
            task = SensorTask(client, FrameRing(96, 1000), watch)  # type: ignore[arg-type]
            run = asyncio.create_task(task.run())
            try:
                async with asyncio.timeout(rep.duration_s + STARTUP_TIMEOUT_S):
                    await watch.went_stale.wait()
            finally:
                run.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await run
    print(f"\n  {watch.frames} frames, then: {watch.stale[0] if watch.stale else None}")
    assert watch.frames == len(rep.frames)
    assert watch.sensor_is_stale and isinstance(watch.stale[0], StaleSensorError)


@pytest.mark.asyncio
async def test_collect_mode_on_a_real_recording(tmp_path):
    """The emulated arm presses while the pads replay the real recording: the press
    controller tares on it, stops on its change (the object carried by the arm, ~16 x x_th)
    and collect mode writes a recording whose frames are the real ones."""
    rep = load_replay(FULL)
    cfg = base_config()
    async with SimRobot("wood_cube", seed=4, cfg=cfg, replay=rep) as robot:
        files = await collect(robot.runtime_config(cfg), "replayed", 1, tmp_path, prompt=None)
    rec = recording.load(files[0])
    rows = [np.flatnonzero((rep.frames == f).all(axis=1)) for f in rec.frames]
    print(f"\n  {len(rec.frames)} frames written, stop latency "
          f"{rec.extra['stop_latency_s'] * 1e3:.1f} ms, t_stop - first frame "
          f"{rec.t_stop - rec.recv_time[0]:.2f} s")
    assert all(len(r) for r in rows)  # every frame written is a recorded row
    assert rec.label == "replayed" and rec.extra["stop_latency_s"] > 0
    # The tare is the mean of recorded rows: within the recording's range per channel.
    assert np.all(rec.tare >= rep.frames.min(0)) and np.all(rec.tare <= rep.frames.max(0))


def test_cli_refuses_a_bad_replay_file(tmp_path):
    bad = _broken(tmp_path, lambda d: _rewrite(d / "xela_sensor1.csv",
                                               lambda ls: [ls[0], _set_field(ls[1], 0, "x"),
                                                           *ls[2:]]))
    out = subprocess.run([sys.executable, "-m", "edge", "sim", "serve", "--replay", str(bad)],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    print(f"\n  exit {out.returncode}: {out.stderr.strip().splitlines()[-1]}")
    assert out.returncode == 2
    assert str(bad / "xela_sensor1.csv") in out.stderr and "is not a number" in out.stderr


@pytest.mark.asyncio
async def test_cli_serves_the_replay(tmp_path):
    """``vt-edge sim serve --replay FILE --replay-once`` as a process: the real client reads
    the recording's frames from it."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "edge", "sim", "serve", "--config", str(ROOT / "configs/sim.toml"),
        "--replay", str(SHORT), "--replay-once", cwd=ROOT, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.DEVNULL, env={**os.environ, "VTZERO_LOG_LEVEL": "WARNING"})
    try:
        assert proc.stdout is not None
        lines = []
        async with asyncio.timeout(30):
            while not any(line.startswith("xela_server emulator:") for line in lines):
                lines.append((await proc.stdout.readline()).decode())
            lines.append((await proc.stdout.readline()).decode())
        url = next(line.split(": ", 1)[1].strip() for line in lines
                   if line.startswith("xela_server emulator:"))
        print("\n  " + "  ".join(lines))
        assert "replaying" in lines[-1] and "70 frames" in lines[-1] and "once" in lines[-1]
        cfg = SensorConfig(url=url, stale_timeout_s=STALE_TIMEOUT_S)
        got: list[TactileFrame] = []
        async with XelaClient(cfg) as client:
            async for frame in client.frames(first_timeout_s=STARTUP_TIMEOUT_S):
                got.append(frame)
                break
        rep = load_replay(SHORT)
        assert any((rep.frames == got[0].raw).all(axis=1))
    finally:
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(10):
            assert await proc.wait() == 0
