"""The tactile contract: TactileFrame, StreamStats and the in-memory FakeTactileSource."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from edge.core.errors import SensorError, StaleSensorError
from edge.hw.contracts import StreamStats, TactileFrame, TactileSource
from tests.support.fakes import FakeTactileSource


def idle(n: int = 1) -> np.ndarray:
    return np.full((n, 96), 32768, dtype=np.uint16)


def test_frame_is_read_only_and_checked() -> None:
    frame = TactileFrame(1, 0.0, time.monotonic(), idle()[0], ("XR1944", "XR1944"))
    with pytest.raises(ValueError):
        frame.raw[0] = 1
    with pytest.raises(ValueError, match="uint16"):
        TactileFrame(1, 0.0, 0.0, np.zeros(96), ("XR1944",))


def test_stats_count_gaps_repeats_and_resets() -> None:
    stats = StreamStats()
    fresh = [
        stats.observe(seq, t)
        for seq, t in [(1, 1.0), (2, 2.0), (2, 2.0), (3, 2.0), (7, 7.0), (1, 8.0)]
    ]
    assert fresh == [True, True, False, False, True, True]
    assert (stats.frames, stats.repeats, stats.gaps, stats.lost, stats.resets) == (4, 2, 1, 3, 1)
    # After a reconnect a restarted server may reuse the last seq with a new time: that is data.
    stats.new_connection()
    assert stats.observe(1, 9.0)
    stats.new_connection()
    assert not stats.observe(1, 9.0)  # the very same frame again is still a repeat
    # A server without a clock (time NaN) is judged by its seq alone.
    assert stats.observe(2, float("nan")) and stats.observe(3, float("nan"))
    assert not stats.observe(3, float("nan"))


@pytest.mark.asyncio
async def test_fake_replays_an_array_at_its_rate() -> None:
    raw = np.arange(20 * 96, dtype=np.uint16).reshape(20, 96)
    async with FakeTactileSource(raw, rate_hz=200.0) as src:
        assert isinstance(src, TactileSource)
        frames = [f async for f in src.frames()]
    assert [f.seq for f in frames] == list(range(1, 21))
    np.testing.assert_array_equal(frames[5].raw, raw[5])
    span_s = frames[-1].recv_time - frames[0].recv_time
    print(f"\n  19 periods of 5 ms took {span_s * 1e3:.1f} ms")
    assert 0.08 < span_s < 0.5
    assert src.stats.frames == 20 and src.stats.gaps == 0


@pytest.mark.asyncio
async def test_fake_fed_by_put_counts_repeats_and_ends_on_finish() -> None:
    src = FakeTactileSource()
    src.put(idle()[0])
    src.put(idle()[0], seq=1, sensor_time=0.0)  # a repeated seq: dropped and counted
    src.put(idle()[0], seq=5)
    src.finish()
    seqs = [f.seq async for f in src.frames()]
    assert seqs == [1, 5]
    assert (src.stats.repeats, src.stats.gaps, src.stats.lost) == (1, 1, 3)


@pytest.mark.asyncio
async def test_fake_raises_stale_and_injected_errors() -> None:
    src = FakeTactileSource(stale_timeout_s=0.05)
    src.put(idle()[0])
    got = []
    with pytest.raises(StaleSensorError):
        async for frame in src.frames():
            got.append(frame)
            assert src.is_fresh()
    assert len(got) == 1
    await asyncio.sleep(0.06)
    assert not src.is_fresh()
    src.fail(SensorError("broken"))
    with pytest.raises(SensorError, match="broken"):
        async for _ in src.frames():
            pass
    await src.close()
    assert [f async for f in src.frames()] == []


def test_fake_refuses_bad_rows() -> None:
    with pytest.raises(ValueError):
        FakeTactileSource(np.full((1, 96), 70000))
    with pytest.raises(ValueError):
        FakeTactileSource(np.zeros((1, 96), dtype=float))
