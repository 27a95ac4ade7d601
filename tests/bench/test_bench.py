"""``make bench`` end to end with tiny durations: ``vt-edge bench`` writes every figure of the
runtime side, ``vt-train bench --merge-into`` adds the torch and training figures to the same
results files.

Structure and generous sanity bounds only: the targets are what the bench reports, never
what this test asserts (the box running the tests is shared and noisy).
"""

import importlib.util
import json
import math
from dataclasses import replace

import pytest

from edge import bench
from edge.bench.figures import figure, ratio_figure, target
from edge.bench.results import markdown
from edge.bench.settings import CONTROLLERS
from train.eval import bench as train_bench

TINY = replace(bench.QUICK, presses=2, quiet_presses=1, load_min_s=2.0, label_presses=1,
               label_warmup=False, rt_presses=1, rt_min_s=2.0, daemon_runs=1,
               rss_samples=1, encode_n=30, retrieval_queries=10, brute_queries_1m=2)
TINY_TRAIN = replace(train_bench.QUICK, encode_n=30, train_presses=1, train_max_epochs=1)


def check_figure(key, fig):
    assert isinstance(fig["n"], int) and fig["n"] >= 1, (key, fig)
    for stat in ("p50", "p99", "max"):
        assert isinstance(fig[stat], float | int) and math.isfinite(fig[stat]), (key, fig)
    assert fig["p50"] <= fig["p99"] + 1e-9 or fig["unit"] == "ratio", (key, fig)
    assert isinstance(fig["unit"], str) and fig["unit"]
    assert (fig["target"] is None) == (fig["met"] is None), (key, fig)
    assert fig["met"] in (True, False, None)
    assert 0 <= fig["host_cores_busy"] <= 64, (key, fig)


# Slow: a whole (tiny) bench run, with its load generators busy on every core.
@pytest.mark.slow
def test_both_sides_write_every_figure_into_one_results_file(tmp_path):
    results_json = tmp_path / "results.json"
    assert bench.bench(tmp_path, TINY) == 0
    results = json.loads(results_json.read_text())
    missing = [k for k in bench.FIGURES if k not in results]
    assert not missing, missing
    assert not [k for k in train_bench.FIGURES if k in results]  # the edge side has no torch
    for key in bench.FIGURES:
        check_figure(key, results[key])
    host = results["host"]
    assert host["cores"] >= 1 and len(host["loadavg_start"]) == 3 and host["python"]
    assert results["run"]["quick"] is True
    assert results["run"]["phases"] == list(bench.PHASES)

    # Sanity, far from the targets: the stop follows the crossing within a second, the
    # overshoot is a few newtons at most, the daemon starts and stays a plausible size.
    assert 0 < results["stop_latency_ms"]["p50"] < 1000
    assert 0 < results["stop_latency_ms_loop100"]["p50"] < 1000
    # The hot path's thread CPU: every armed frame of the production presses, each stop in two
    # threads; a fraction of a core's millisecond, and no more with the load beside it than
    # the wall clock gives.
    frame, stop = results["frame_check_cpu_us"], results["stop_cpu_us"]
    print(f"frame {frame['p50']:.0f} us ({frame['no_load']['p50']:.0f} no load), stop "
          f"{stop['p50']:.0f} us ({stop['no_load']['p50']:.0f} no load)")
    assert frame["n"] > 20 and frame["no_load"]["n"] > 10 and 0 < frame["p50"] < 5000
    assert stop["n"] + stop["in_flight_stops"] >= 1
    assert stop["loop_us"]["p50"] > 0 and stop["bus_us"]["p50"] > 0
    assert stop["p50"] < 1e3 * results["stop_latency_ms"]["max"]
    assert all(-1 < results[k]["max"] < 50 for k in results if k.startswith("force_overshoot"))
    assert 0 < results["startup_to_ready_s"]["max"] < 60
    assert 20 < results["daemon_rss_mb"]["p50"] < 2000
    assert results["sampler_period_error_ms"]["ticks"] > 100
    assert 0 <= results["overhead_ms"]["p50"] < 5000
    # The VLM request leaves after the window is complete, well before the arm is back.
    assert 0 < results["label_after_window_ms"]["p50"] < 500
    # Part of it: the wait for the frame that completes the window (one press, so its p50
    # is that press's, which the request can only follow).
    after = results["label_after_window_ms"]
    assert 0 <= after["frame_wait_ms"] <= after["p50"], after
    label = results["trigger_to_label_s"]
    assert label["move_time_s"] > 0
    # The label waits for the later of the VLM's answer and the arm back above the object
    # (the episode's order of states); one press, so each p50 is that press's.
    assert label["label_after_stop_s"] >= max(label["answer_after_stop_s"],
                                              label["arm_back_after_stop_s"]) - 0.005, label
    assert results["retrieval_ms_1m"]["references"] == 1_000_000
    raw_before = (tmp_path / "raw.json").read_bytes()
    raw = json.loads(raw_before)
    assert len(raw["presses"]) >= TINY.quiet_presses + TINY.presses * len(CONTROLLERS)

    # The training side adds its phases to the same files; raw.json is the edge side's.
    assert train_bench.bench(TINY_TRAIN, merge_into=results_json) == 0
    merged = json.loads(results_json.read_text())
    has_torch = importlib.util.find_spec("torch") is not None
    added = list(train_bench.FIGURES) if has_torch else []
    for key in [*bench.FIGURES, *added]:
        check_figure(key, merged[key])
    assert {k: merged[k] for k in bench.FIGURES} == {k: results[k] for k in bench.FIGURES}
    assert merged["run"]["phases"] == [*bench.PHASES, *train_bench.PHASES]
    assert "vt-edge bench" in merged["run"]["command"]
    assert "vt-train bench" in merged["run"]["command"]
    assert merged["notes"][:len(results["notes"])] == results["notes"]
    assert (tmp_path / "raw.json").read_bytes() == raw_before
    if has_torch:
        assert merged["encode_ms_torch"]["parity_max_abs_dz"] < 1e-4
        assert merged["encode_speedup_vs_torch"]["onnxruntime_ms"]["n"] >= TINY_TRAIN.encode_n

    # results.md is rendered from results.json alone: every figure, the sections, in order.
    md = (tmp_path / "results.md").read_text()
    assert md == markdown(merged)
    assert "| figure | p50 | p99 | max |" in md and "## The load" in md
    rows = [line.split("`")[1] for line in md.splitlines() if line.startswith("| `")]
    assert rows == [*bench.FIGURES, *added]

    # A merge that would mix runs is refused before measuring anything.
    with pytest.raises(ValueError, match="already holds the phases"):
        train_bench.bench(TINY_TRAIN, merge_into=results_json)
    with pytest.raises(ValueError, match="quick"):
        train_bench.bench(train_bench.FULL, merge_into=results_json)


def test_figure_targets_and_ratios():
    fig = figure([1.0, 2.0, 3.0], "ms", target(("p99", "<=", 2.0)))
    assert fig["n"] == 3 and fig["max"] == 3.0 and fig["met"] is False
    fast = figure([1.0] * 10, "ms")
    slow = figure([8.0] * 10, "ms")
    ratio = ratio_figure(slow, fast, target(("p50", ">=", 5.0)))
    assert ratio["p50"] == 8.0 and ratio["met"] is True and ratio["unit"] == "ratio"
    assert figure([], "ms", target(("p50", "<=", 1.0)))["met"] is False
    assert figure([1.0], "N")["met"] is None
