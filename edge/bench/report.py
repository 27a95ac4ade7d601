"""How the runtime side's figures read: their order in the table, how to read them, the
load they ran under, and why a target is missed on this kind of host (``results.md``;
:mod:`edge.bench.results` renders it)."""

from __future__ import annotations

from typing import Any

from edge.bench.settings import CONTROLLERS, OBJECTS

# Every figure `vt-edge bench` writes, in table order (`vt-train bench --merge-into` adds
# the torch and training figures after them).
FIGURES = (
    "sampler_period_error_ms", "sampler_period_error_ms_no_load",
    "sampler_period_error_ms_realtime",
    "stop_latency_ms", "stop_floor_ms", "stop_latency_ratio_floor", "stop_latency_ms_realtime",
    "stop_latency_ms_tick125",
    "stop_latency_ms_loop100", "stop_latency_ratio_loop100", "stop_latency_ratio_tick125",
    "stop_latency_ms_no_load", "stop_floor_ms_no_load", "stop_latency_ratio_floor_no_load",
    "frame_check_cpu_us", "stop_cpu_us",
    "sampler_period_error_ms_two_pages", "stop_latency_ms_two_pages", "operator_page_feed_fps",
    *(f"force_overshoot_n_{o}_{c}" for o in OBJECTS for c in CONTROLLERS),
    "overhead_ms", "overhead_ms_under_load", "label_after_window_ms", "trigger_to_label_s",
    "startup_to_ready_s", "daemon_rss_mb", "daemon_torch_mapped",
    "encode_ms",
    "retrieval_ms_shipped", "retrieval_numpy_ms_shipped", "retrieval_speedup_shipped",
    "retrieval_ms_1m", "retrieval_numpy_ms_1m", "retrieval_speedup_1m",
)


def load_text(load: dict[str, Any]) -> str:
    """The load the runtime phase ran under, in one paragraph."""
    cpu = load.get("cpu_s", {})
    return (f"{load.get('duration_s', 0):.0f} s; {load.get('vlm_asks')} VLM requests with a "
            f"{load.get('image_bytes', 0) / 1e6:.1f} MB still ({load.get('vlm_errors')} "
            f"failed), {load.get('encodes')} encoder runs (each an encode and a top-k), "
            f"{(load.get('poll') or {}).get('requests', '?')} API polls. Sampler: "
            f"{load.get('ticks')} ticks, {load.get('missed_ticks')} missed, longest gap "
            f"between two samples {load.get('max_interval_ms', 0):.1f} ms "
            f"({load.get('intervals_over_16ms')} gaps over two periods). CPU, in cores: "
            + ", ".join(f"{k} {v:g}" for k, v in cpu.items()) + ".")


READING = "\n".join([
    "- Stop latency is measured from the same frame for every controller: the first "
    "frame whose norm crosses x_th (its receive time), found afterwards in the frame ring; "
    "the end is the write call of the stop's one WRITE packet (the packet goes to the "
    "kernel from there; the call returning can wait for a CPU or the GIL after the packet "
    "is out, write_return_ms). The production stop is split into parse_ms (the frame's "
    "JSON into counts, checked), queue_ms (to the threshold check), check_ms (the norm, "
    "the threshold, down to the hand-over), handover_ms (to the bus thread running the "
    "stop), in_flight_ms (the rest of a transaction already on the wire; in_flight_stops "
    "counts them) and write_ms (the goal and its packet, to the write call); they add up "
    "to the latency. fallback_stops: stops that had to read Present Position first.",
    "- frame_check_cpu_us and stop_cpu_us are what the hot path costs in thread CPU time "
    "(time.thread_time_ns), which another process's load does not inflate: per frame "
    "while the threshold is armed, the loop thread from the XELA message's arrival to the "
    "end of its threshold check; "
    "per stop, the loop thread from the frame's arrival to the hand-over to the bus "
    "thread, plus the bus thread from there to its stop packet's write call (loop_us, "
    "bus_us). Each gives the same with no load beside it (no_load): a change to the "
    "stop's path shows in them on any host, where the wall-clock figures move with the "
    "host's load.",
    "- stop_floor_ms is the same path written the shortest way, measured on the same "
    "frames, host and load in a process of its own: an aiohttp client that parses each "
    "frame with json and numpy, takes the norm and writes a 16-byte packet to a pty from "
    "its loop thread (receive -> the write call; every frame is a sample). It validates "
    "nothing, keeps no ring, stamps nothing and owns no bus.",
    "- The *_realtime figures: the same load, with the loop and bus threads SCHED_FIFO on "
    "a CPU of their own (Daemon.realtime, the [runtime] realtime option).",
    "- A ticked controller checks only the latest "
    "frame at each tick, so it can miss a crossing that falls back before the tick "
    "(missed_first_crossing). from_server_send_ms is the same stop timed from the "
    "XELA server's frame time (wall clock, same host): it also counts the time the "
    "frame waited in the socket before the loop read it, which the receive time "
    "cannot see.",
    "- On the rigid stainless_cube much of the overshoot is there even with the "
    "fastest stop: the stop goal lies a few counts past the present position (the "
    "squeeze that keeps contact) and the motor pushes to it, up to Goal Current; the "
    "latency adds on top (compare the controllers). gelatin_soft yields, so its force "
    "grows little in a few milliseconds.",
    "- The emulated robot shares the host: its bus replies are slower under load than "
    "a motor's, and it runs favoured (nice -10) to stand in for hardware.",
])


# Why a target is missed on this kind of host, and what would close it: from what the bench
# and the trials behind its commits showed (the figure's own numbers come with it).
WHY: dict[str, str] = {
    "sampler_period_error_ms": (
        "No thread of the daemon holds its GIL for milliseconds any more: image preparation "
        "and the encoder run in the compute process, niced +10 (before that, p99 was 5.35 "
        "ms with 343 missed ticks under this load). What is left is the CPU: the compute "
        "worker keeps one of the two cores busy with the back-to-back encoder load, the "
        "emulated robot, fake VLM and poller share the other, and the loop thread still "
        "waits for a core ('The load': run-queue wait, preemptions); the missed ticks come "
        "from a few single stalls (max_gap_ms). Without the load the sampler is at "
        "sampler_period_error_ms_no_load. To close it: a core of its own for the loop and "
        "bus threads (CPUAffinity=, isolcpus) at real-time priority "
        "(CPUSchedulingPolicy=fifo). A late tick never shifts the recorded data: the crop is "
        "placed from receive timestamps."),
    "stop_latency_ms": (
        "The stop is one WRITE; its parts are in the figure. Under the load the slow "
        "stops are the bus thread waiting for a core after the hand-over (handover_ms) and "
        "a transaction already on the wire that the emulated robot, starved by the load, "
        "answers late (in_flight_ms): not the path itself. With the loop and bus threads at "
        "real-time priority on a CPU of their own the hand-over stays short "
        "(stop_latency_ms_realtime). What is left in the tail there is the emulated bus."),
    "stop_latency_ms_realtime": (
        "With real-time scheduling the parts of the path stay short even in the tail; the "
        "slow stops wait for a transaction already on the wire (in_flight_ms), which the "
        "emulated robot, a process of the loaded host, answers late. On the real arm that "
        "transaction is the gripper trace's read, which ends before the next frame."),
    "stop_latency_ratio_floor": (
        "The floor does a third of the work: vtzero's parse alone (json plus the checks "
        "that refuse a malformed or repeated frame, parse_ms) costs about what the floor's "
        "whole path does; then the frame goes to the check (queue_ms, check_ms), the stop "
        "is handed to the bus thread that owns the port (handover_ms: the SDK is blocking "
        "and not thread-safe, so it never runs on the loop) and the goal goes into the "
        "packet built ahead (write_ms). The parts are in stop_latency_ms."),
    "sampler_period_error_ms_realtime": (
        "At real-time priority on a CPU of its own the loop thread hardly waits for a core "
        "any more (loop_thread: run-queue wait, preemptions), so the ticks it still misses "
        "are the loop itself held up: it shares the interpreter's lock with the daemon's "
        "other threads (the compute pool's move the load's megabyte images), and a holder "
        "that is waiting for a core keeps it. Which one held it in the long gaps "
        "(max_gap_ms) is not measured. p99 is the figure to compare with "
        "sampler_period_error_ms."),
    "stop_latency_ratio_loop100": (
        "The load's stalls inflate the per-frame median far more, relatively, than the "
        "100 Hz loop's, whose own wait for its next tick is 0-10 ms (5 ms on average); "
        "idle, the per-frame path is at stop_latency_ms_no_load. The ratio also flatters "
        "the loop: see missed_first_crossing and aborted_after_stop of "
        "stop_latency_ms_loop100. Closing the per-frame tail (above) closes this."),
    "overhead_ms": (
        "What remains: the API request and the pre-press motor check (pre_press_ms: a SYNC "
        "READ of torque and one of the watchdogs, round trips to the emulated robot, a "
        "process of this host; the photo waits for it); the wait for the first frame at or "
        "past the crop's last sample (label_after_window_ms's frame_wait_ms, up to one frame "
        "period and usually most of one: that sample lies 74 frame periods after the stop, "
        "which follows the crossing frame's arrival by a fraction of a millisecond, so the "
        "frame 74 periods on arrives just before it and the crop needs the next); one round "
        "trip to the compute process (the crop, encoder and top-k); JSON and the POST. The "
        "p99 of 8 presses is their slowest, on a host shared with the emulated robot (and "
        "with other jobs when the CPU line above says so). To close it: the host as for the "
        "sampler, or a crop whose last sample needs no further frame, which changes the "
        "method's preprocessing (a new release)."),
    "encode_ms": (
        "onnxruntime itself needs about 0.1 ms per sequence on a quiet core (0.094 ms p50 "
        "in a separate run of this code); see host_cores_busy and the other tenants' share "
        "in the CPU line above for this phase. To close it: a quiet core."),
    "retrieval_ms_1m": (
        "One query scans 1M x 4 float32 with numpy (16 MB of memory traffic) and is "
        "memory-bound; on a busy host it slows with the other tenants' traffic. To close "
        "it: a quiet core, or an index (the query only needs the per-class minimum)."),
    "startup_to_ready_s": "Start-up imports numpy, onnxruntime and aiohttp and connects the "
                          "bus: on a busy host each takes longer.",
}
