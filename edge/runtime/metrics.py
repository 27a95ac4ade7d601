"""Prometheus text metrics of the daemon (no dependency: the format is a few lines)."""

from __future__ import annotations

import bisect
from typing import TYPE_CHECKING, Any

from edge.hw.contracts import BusStatus
from edge.runtime.domain import PressResult

if TYPE_CHECKING:
    from edge.runtime.press import PressOutcome
    from edge.runtime.store import EpisodeStore
    from edge.vlm.client import VLMClient


class Histogram:
    def __init__(self, buckets: tuple[float, ...]) -> None:
        self.buckets = buckets
        self.counts = [0] * (len(buckets) + 1)
        self.total = 0.0
        self.n = 0

    def observe(self, value: float) -> None:
        self.counts[bisect.bisect_left(self.buckets, value)] += 1
        self.total += value
        self.n += 1

    def render(self, name: str, help_text: str) -> list[str]:
        lines = [f"# HELP {name} {help_text}", f"# TYPE {name} histogram"]
        cumulative = 0
        for bound, count in zip(self.buckets, self.counts, strict=False):
            cumulative += count
            lines.append(f'{name}_bucket{{le="{bound:g}"}} {cumulative}')
        lines.append(f'{name}_bucket{{le="+Inf"}} {self.n}')
        lines.append(f"{name}_sum {self.total:.6f}")
        lines.append(f"{name}_count {self.n}")
        return lines


class Metrics:
    def __init__(self) -> None:
        self.vlm_errors = 0
        self.discarded_partial = 0
        self.presses: dict[PressResult, int] = {}
        self.stop_latency = Histogram((0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05))
        self.vlm_latency = Histogram((0.25, 0.5, 1, 2, 5, 10, 30, 60))
        # Answers by the structured-output mode that answered.
        self.vlm_answers: dict[str, int] = {}
        # Analysed presses' familiarity (a percentile: edge.core.model.Familiarity), and
        # those at or past [runtime] unfamiliar_percentile.
        self.familiarity = Histogram((5, 25, 50, 75, 90, 95, 99, 100))
        self.unfamiliar = 0

    def observe_press(self, outcome: PressOutcome) -> None:
        self.presses[outcome.result] = self.presses.get(outcome.result, 0) + 1
        if outcome.stop_latency_s is not None:
            self.stop_latency.observe(outcome.stop_latency_s)

    def observe_familiarity(self, familiarity: float | None, unfamiliar: bool) -> None:
        if familiarity is not None:
            self.familiarity.observe(familiarity)
        self.unfamiliar += unfamiliar

    def observe_vlm(self, latency_s: float, structured_output: str | None = None) -> None:
        self.vlm_latency.observe(latency_s)
        if structured_output is not None:
            self.vlm_answers[structured_output] = self.vlm_answers.get(structured_output, 0) + 1

    def render(self, st: Any, sensor: Any, bus: BusStatus | None = None,
               vlm: VLMClient | None = None, store: EpisodeStore | None = None) -> str:
        """Prometheus text: these counters, the sampler's stats ``st``, the sensor task's
        frame and stale counts, with a motor ``bus`` its stops, whether the ``vlm`` client
        reaches its server, and whether the episode ``store`` writes."""
        lines = [
            "# HELP vtzero_presses_total Presses by result.",
            "# TYPE vtzero_presses_total counter",
        ]
        for result in sorted(self.presses) or [PressResult.OK]:
            lines.append(f'vtzero_presses_total{{result="{result}"}} '
                         f"{self.presses.get(result, 0)}")
        lines += self.stop_latency.render(
            "vtzero_stop_latency_seconds", "Frame over x_th received to stop packet written.")
        lines += self.vlm_latency.render("vtzero_vlm_latency_seconds",
                                         "Duration of successful VLM calls.")
        lines += self.familiarity.render(
            "vtzero_familiarity_percentile", "Analysed presses' familiarity: how clearly each "
            "lies in its nearest class, a percentile of the database's own leave-one-out figures.")
        lines += [
            "# HELP vtzero_unfamiliar_presses_total Analysed presses at or past [runtime] "
            "unfamiliar_percentile (like no reference).",
            "# TYPE vtzero_unfamiliar_presses_total counter",
            f"vtzero_unfamiliar_presses_total {self.unfamiliar}",
        ]
        lines += [
            "# HELP vtzero_vlm_errors_total VLM calls that failed and were left pending.",
            "# TYPE vtzero_vlm_errors_total counter",
            f"vtzero_vlm_errors_total {self.vlm_errors}",
            "# HELP vtzero_vlm_answers_total VLM answers by the structured-output mode that "
            "answered.",
            "# TYPE vtzero_vlm_answers_total counter",
            *(f'vtzero_vlm_answers_total{{structured_output="{mode}"}} {n}'
              for mode, n in sorted(self.vlm_answers.items())),
            "# HELP vtzero_vlm_reachable 0 after attempts in a row got no answer from the VLM "
            "server (see /healthz), else 1.",
            "# TYPE vtzero_vlm_reachable gauge",
            f"vtzero_vlm_reachable {0 if vlm is not None and vlm.unreachable else 1}",
            "# HELP vtzero_store_discarded_partial_total Episodes found half-written at start "
            "(a crash while writing) and discarded.",
            "# TYPE vtzero_store_discarded_partial_total counter",
            f"vtzero_store_discarded_partial_total {self.discarded_partial}",
            "# HELP vtzero_tactile_frames_total Tactile frames received.",
            "# TYPE vtzero_tactile_frames_total counter",
            f"vtzero_tactile_frames_total {sensor.frames}",
            "# HELP vtzero_tactile_stale_total Times the tactile stream went stale.",
            "# TYPE vtzero_tactile_stale_total counter",
            f"vtzero_tactile_stale_total {sensor.stale_events}",
            "# HELP vtzero_sampler_gaps_total 125 Hz ticks without a new frame.",
            "# TYPE vtzero_sampler_gaps_total counter",
            f"vtzero_sampler_gaps_total {st.gaps}",
            "# HELP vtzero_sampler_missed_ticks_total Ticks skipped because the loop lagged.",
            "# TYPE vtzero_sampler_missed_ticks_total counter",
            f"vtzero_sampler_missed_ticks_total {st.missed_ticks}",
            "# HELP vtzero_loop_lag_max_seconds Largest lateness of the 125 Hz sampler.",
            "# TYPE vtzero_loop_lag_max_seconds gauge",
            f"vtzero_loop_lag_max_seconds {st.max_late_s:.6f}",
        ]
        if store is not None:
            lines += [
                "# HELP vtzero_store_ok 1 while the episode store writes (and has space), "
                "else 0 (see /healthz store_error; presses are refused).",
                "# TYPE vtzero_store_ok gauge",
                f"vtzero_store_ok {0 if store.error() else 1}",
                "# HELP vtzero_store_write_failures_total Writes of the episode store that "
                "failed.",
                "# TYPE vtzero_store_write_failures_total counter",
                f"vtzero_store_write_failures_total {store.write_failures}",
                "# HELP vtzero_store_held_episodes Episodes held in memory until the store "
                "writes again.",
                "# TYPE vtzero_store_held_episodes gauge",
                f"vtzero_store_held_episodes {store.held}",
                "# HELP vtzero_store_lost_total Episodes neither written nor held (the "
                "memory's bound reached).",
                "# TYPE vtzero_store_lost_total counter",
                f"vtzero_store_lost_total {store.lost}",
                "# HELP vtzero_store_removed_total Finished episodes and recording segments "
                "removed by retention (store_max_mb, keep_free_mb).",
                "# TYPE vtzero_store_removed_total counter",
                f'vtzero_store_removed_total{{kind="episode"}} {store.removed_episodes}',
                f'vtzero_store_removed_total{{kind="segment"}} {store.removed_segments}',
                "# HELP vtzero_store_removed_bytes_total Bytes retention removed.",
                "# TYPE vtzero_store_removed_bytes_total counter",
                f"vtzero_store_removed_bytes_total {store.removed_bytes}",
            ]
        if bus is not None:
            lines += [
                "# HELP vtzero_stops_total Stops sent to the gripper.",
                "# TYPE vtzero_stops_total counter",
                f"vtzero_stops_total {bus.stops}",
                "# HELP vtzero_stop_fallbacks_total Stops that read Present Position first "
                "(no gripper state fresh enough to write from).",
                "# TYPE vtzero_stop_fallbacks_total counter",
                f"vtzero_stop_fallbacks_total {bus.stop_fallbacks}",
            ]
        return "\n".join(lines) + "\n"
