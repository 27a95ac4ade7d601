"""``vt-edge bench`` end to end with tiny durations: every figure is written, with numbers.

Structure and generous sanity bounds only: the targets are what the bench reports, never
what this test asserts (the box running the tests is shared and noisy).
"""

import importlib.util
import json
import math
from dataclasses import replace

from edge.tools import bench

TINY = replace(bench.QUICK, presses=2, quiet_presses=1, load_min_s=2.0, daemon_runs=1,
               rss_samples=1, encode_n=30, retrieval_queries=10, brute_queries_1m=2,
               train_presses=1, train_max_epochs=1)


def test_bench_writes_every_figure(tmp_path):
    assert bench.bench(tmp_path, TINY) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    has_torch = importlib.util.find_spec("torch") is not None
    expected = [k for k in bench.FIGURES if has_torch or k not in bench.TORCH_FIGURES]
    missing = [k for k in expected if k not in results]
    assert not missing, missing
    for key in expected:
        fig = results[key]
        assert isinstance(fig["n"], int) and fig["n"] >= 1, (key, fig)
        for stat in ("p50", "p99", "max"):
            assert isinstance(fig[stat], float | int) and math.isfinite(fig[stat]), (key, fig)
        assert fig["p50"] <= fig["p99"] + 1e-9 or fig["unit"] == "ratio", (key, fig)
        assert isinstance(fig["unit"], str) and fig["unit"]
        assert (fig["target"] is None) == (fig["met"] is None), (key, fig)
        assert fig["met"] in (True, False, None)
    host = results["host"]
    assert host["cores"] >= 1 and len(host["loadavg_start"]) == 3 and host["python"]
    assert results["run"]["quick"] is True

    # Sanity, far from the targets: the stop follows the crossing within a second, the
    # overshoot is a few newtons at most, the daemon starts and stays a plausible size.
    assert 0 < results["stop_latency_ms"]["p50"] < 1000
    assert 0 < results["stop_latency_ms_loop100"]["p50"] < 1000
    assert all(-1 < results[k]["max"] < 50 for k in results if k.startswith("force_overshoot"))
    assert 0 < results["startup_to_ready_s"]["max"] < 60
    assert 20 < results["daemon_rss_mb"]["p50"] < 2000
    assert results["sampler_period_error_ms"]["ticks"] > 100
    assert 0 <= results["overhead_ms"]["p50"] < 5000
    assert results["retrieval_ms_1m"]["references"] == 1_000_000

    md = (tmp_path / "results.md").read_text()
    assert "| figure | p50 | p99 | max |" in md
    assert all(f"`{k}`" in md for k in expected)
    raw = json.loads((tmp_path / "raw.json").read_text())
    assert len(raw["presses"]) >= TINY.quiet_presses + TINY.presses * len(bench.CONTROLLERS)


def test_figure_targets_and_ratios():
    fig = bench.figure([1.0, 2.0, 3.0], "ms", bench.target(("p99", "<=", 2.0)))
    assert fig["n"] == 3 and fig["max"] == 3.0 and fig["met"] is False
    fast = bench.figure([1.0] * 10, "ms")
    slow = bench.figure([8.0] * 10, "ms")
    ratio = bench.ratio_figure(slow, fast, bench.target(("p50", ">=", 5.0)))
    assert ratio["p50"] == 8.0 and ratio["met"] is True and ratio["unit"] == "ratio"
    assert bench.figure([], "ms", bench.target(("p50", "<=", 1.0)))["met"] is False
    assert bench.figure([1.0], "N")["met"] is None
