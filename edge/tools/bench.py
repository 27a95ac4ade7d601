"""``vt-edge bench``: the runtime's figures on the emulated robot, against their targets.

Writes ``OUT/results.json`` (one key per figure: p50, p99, max, n, unit, target, met; plus
``host`` and ``run``), ``OUT/results.md`` (the table and notes) and ``OUT/raw.json`` (every
press). Phases, each printed on stderr as it runs:

1. **Runtime under load.** The daemon's :class:`~edge.daemon.runtime.Runtime` (real drivers, HTTP
   API, episode store, VLM client) runs in this process against the emulated robot, which
   runs in its own process (:mod:`edge.tools.bench_sim`), as do a slow fake VLM and a poller of
   ``/healthz`` and ``/metrics``. A few presses first with no extra load (the software
   overhead, trigger to VLM request), then the load: the VLM client sends large camera
   stills to the slow VLM, the encoder runs over and over in the daemon's compute process
   (where its own presses are encoded and its images prepared), the API is polled. Under
   it, presses alternate between three controllers: the production one (threshold checked
   on every arriving frame), one that checks only on a 125 Hz tick, and one on a 100 Hz
   control loop (the usual ROS 2 arrangement); both comparison controllers
   live here, not in production code. The sampler's lateness is recorded throughout.
2. **The daemon as a process.** ``vt-edge run`` against ``vt-edge sim serve``: time from
   process start to ``READY=1`` on a ``NOTIFY_SOCKET`` bound here, resident memory at steady
   state after a recognition, and whether torch is mapped into the process.
3. **Encoder and retrieval.** onnxruntime (the robot's session options) against torch eager
   on the same weights and inputs; top-k on the shipped database and on 1,000,000 synthetic
   references against plain numpy brute force.
4. **Training.** The shipped encoder's training configuration on a freshly recorded
   simulated reference set.

Timing is on ``time.monotonic`` (CLOCK_MONOTONIC), shared by every process on the host.
torch and the ``train`` package are imported only in phases 3 and 4, never by the daemon.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import datetime
import importlib.metadata
import io
import json
import logging
import os
import platform
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from edge.core import preprocess
from edge.daemon.press import PressController, PressOutcome
from edge.tools.demo import http_json

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
SIM_CONFIG = ROOT / "configs" / "sim.toml"
MODELS = ROOT / "models"
CUBE = ["raw_kiri_mochi", "boiled_kiri_mochi", "raw_kabocha_squash", "boiled_kabocha_squash"]
OBJECTS = ("stainless_cube", "gelatin_soft")
CONTROLLERS = ("per_frame", "tick125", "loop100")
CONTROLLER_TEXT = {
    "per_frame": "threshold checked on every arriving frame (production)",
    "tick125": "threshold checked on a 125 Hz tick (the sampler's rate)",
    "loop100": "threshold checked by a 100 Hz control loop (ROS 2 style)",
}
HELPER_START_S = 30.0
# The emulated robot stands in for hardware, which never waits for a CPU: it runs favoured
# (nice -10, where allowed) so that a busy host starves the daemon, not the motors.
ROBOT_NICE = -10
# A press that fails (on a starved host the emulated bus can time out) is tried again, up
# to this many times, so that every controller gets its presses; failures are counted.
PRESS_ATTEMPTS = 3
PRESS_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class Settings:
    quick: bool
    load_min_s: float  # the loaded phase lasts at least this long (sampler figure)
    presses: int  # loaded presses per controller (alternating the two objects)
    quiet_presses: int  # presses with no extra load (the overhead figure)
    move_time_s: float  # arm moves between poses (time-based profile)
    vlm_latency_s: float  # the fake VLM's answer delay
    load_vlm_clients: int  # concurrent askers sending the large still
    image_px: tuple[int, int]
    encode_load_s: float  # encoder work per worker-thread call in the load
    encode_duty: float  # fraction of the time the encoder thread works (1: back to back)
    poll_hz: float
    daemon_runs: int
    rss_samples: int
    encode_n: int
    retrieval_queries: int
    brute_queries_1m: int
    retrieval_refs: int
    retrieval_classes: int
    train_presses: int  # recorded reference presses per class
    train_max_epochs: int | None  # None: the shipped configuration's


FULL = Settings(quick=False, load_min_s=60.0, presses=30, quiet_presses=8, move_time_s=0.2,
                vlm_latency_s=1.0, load_vlm_clients=2, image_px=(3000, 2000),
                encode_load_s=0.02, encode_duty=1.0, poll_hz=20.0, daemon_runs=3, rss_samples=6,
                encode_n=2000, retrieval_queries=200, brute_queries_1m=20,
                retrieval_refs=1_000_000, retrieval_classes=1000, train_presses=10,
                train_max_epochs=None)
QUICK = replace(FULL, quick=True, load_min_s=5.0, presses=3, quiet_presses=2, daemon_runs=1,
                rss_samples=3, encode_n=300, retrieval_queries=50, brute_queries_1m=5,
                train_presses=2, train_max_epochs=3)


def _progress(msg: str) -> None:
    print(f"[bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------------
# Figures


def stats(values: Sequence[float]) -> dict[str, Any]:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)),
            "max": float(v.max()), "n": int(v.size)}


def target(*conditions: tuple[str, str, float]) -> list[dict[str, Any]]:
    """Conditions on a figure's own keys, e.g. ``("p99", "<=", 2.0)``; all must hold."""
    return [{"stat": s, "op": op, "value": value} for s, op, value in conditions]


def _holds(value: Any, op: str, bound: float) -> bool:
    if value is None:
        return False
    return {"<=": value <= bound, ">=": value >= bound, "==": value == bound}[op]


def figure(values: Sequence[float], unit: str, goal: list[dict[str, Any]] | None = None,
           **extra: Any) -> dict[str, Any]:
    fig = {**stats(values), "unit": unit, **extra}
    return finish(fig, goal)


def finish(fig: dict[str, Any], goal: list[dict[str, Any]] | None) -> dict[str, Any]:
    fig["target"] = goal
    fig["met"] = None if not goal else all(_holds(fig.get(c["stat"]), c["op"], c["value"])
                                           for c in goal)
    return fig


def ratio_figure(num: dict[str, Any], den: dict[str, Any],
                 goal: list[dict[str, Any]] | None = None, **extra: Any) -> dict[str, Any]:
    """``num / den`` statistic by statistic (p50 of one over p50 of the other, ...)."""
    fig: dict[str, Any] = {"unit": "ratio"}
    for key in ("p50", "p99", "max"):
        a, b = num.get(key), den.get(key)
        fig[key] = a / b if a is not None and b else None
    fig["n"] = min(num.get("n", 0), den.get("n", 0))
    fig.update(extra)
    return finish(fig, goal)


def target_text(goal: list[dict[str, Any]] | None) -> str:
    if not goal:
        return "-"
    return " and ".join(f"{c['stat']} {c['op']} {c['value']:g}" for c in goal)


# --------------------------------------------------------------------------------------
# Host


def _cpu_model() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def host_info() -> dict[str, Any]:
    commit = None
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True,
                                capture_output=True, timeout=5).stdout.strip() or None
    return {
        "cpu_model": _cpu_model(),
        "cores": os.cpu_count(),
        "cores_usable": len(os.sched_getaffinity(0)),
        "python": platform.python_version(),
        "implementation": platform.python_implementation(),
        "kernel": platform.release(),
        "numpy": np.__version__,
        "onnxruntime": _version("onnxruntime"),
        "torch": _version("torch"),
        "aiohttp": _version("aiohttp"),
        "loadavg_start": list(os.getloadavg()),
        "switch_interval_s": sys.getswitchinterval(),
        "git_commit": commit,
    }


# --------------------------------------------------------------------------------------
# Helper processes


class Helper:
    """One :mod:`edge.tools.bench_sim` process: its announcement line, then SIGTERM to stop."""

    def __init__(self, *args: str) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, "-m", "edge.tools.bench_sim", *args],
                                     cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True)
        self.info = json.loads(self._line(HELPER_START_S, args[0]))

    def _line(self, timeout_s: float, what: str) -> str:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            self.proc.kill()
            raise RuntimeError(f"bench helper {what} did not start (exit {self.proc.poll()})")
        return line

    def stop(self) -> str:
        """SIGTERM; returns what it printed after its announcement."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        return out or ""


# --------------------------------------------------------------------------------------
# Press controllers: the production one and the two comparisons


class RecordingController(PressController):
    """The production controller, unchanged; its ``on_outcome`` hook hands each outcome to
    the bench."""

    name = "per_frame"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.outcomes: asyncio.Queue[PressOutcome] = asyncio.Queue()
        super().__init__(*args, on_outcome=self.outcomes.put_nowait, **kwargs)


class TickedController(RecordingController):
    """The threshold checked only on a periodic tick, with the latest frame.

    The sensor path only records the latest frame; a ticker on an absolute grid (period
    ``period_s``) runs the same check as the production controller (stop included) on it.
    The grid's phase against the frame stream is drawn afresh for every press: a 125 Hz tick
    against a 125 Hz stream would otherwise sit at one arbitrary phase for the whole run.
    """

    def __init__(self, *args: Any, name: str, period_s: float, rng: np.random.Generator,
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.name = name
        self.period_s = period_s
        self._rng = rng
        self._latest: tuple[np.ndarray, float] | None = None

    async def on_frame(self, raw: np.ndarray, recv_time: float) -> None:
        self._latest = (raw, recv_time)

    async def run(self) -> PressOutcome:
        ticker = asyncio.create_task(self._tick(), name=f"bench-{self.name}-ticker")
        try:
            return await super().run()
        finally:
            ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await ticker

    async def _tick(self) -> None:
        loop = asyncio.get_running_loop()
        period = self.period_s
        deadline = loop.time() + float(self._rng.uniform(0.0, period))
        while True:
            await asyncio.sleep(max(0.0, deadline - loop.time()))
            latest = self._latest
            if latest is not None and self.armed:
                await self.check(*latest)
            deadline += period
            behind = loop.time() - deadline
            if behind > period:
                deadline += (behind // period) * period


# --------------------------------------------------------------------------------------
# Phase 1: the runtime on the emulated robot, with and without load


def big_jpeg(size: tuple[int, int], seed: int = 0) -> bytes:
    """A camera-like still: gradients, texture and noise, JPEG quality 92."""
    from PIL import Image

    w, h = size
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 255, w, dtype=np.float32)
    y = np.linspace(0, 255, h, dtype=np.float32)[:, None]
    img = np.empty((h, w, 3), dtype=np.uint8)
    noise = rng.normal(0, 10, (h, w)).astype(np.float32)
    img[..., 0] = np.clip(0.6 * x + 0.3 * y + noise, 0, 255)
    img[..., 1] = np.clip(0.4 * y + 60 * np.sin(x / 40)[None, :] + 80 + noise, 0, 255)
    img[..., 2] = np.clip(255 - 0.5 * x - 0.2 * y + noise, 0, 255)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="JPEG", quality=92)
    return buf.getvalue()


@dataclass
class PressRecord:
    phase: str
    controller: str
    object: str
    marker: str
    result: str
    t_trigger: float
    t_first_cross: float | None = None
    t_stop: float | None = None
    stop_latency_ms: float | None = None
    controller_latency_ms: float | None = None  # as the controller itself logged it
    to_bus_ms: float | None = None  # first frame over x_th -> the stop's READ packet written
    from_send_ms: float | None = None  # the server sent that frame -> stop written
    force_at_cross_n: float | None = None
    peak_force_n: float | None = None
    overshoot_n: float | None = None
    press_s: float | None = None  # 'above' entered -> 'idle' entered
    pre_press_ms: float | None = None  # trigger -> 'above'
    t_vlm: float | None = None
    overhead_ms: float | None = None
    message: str = ""


def encode_for(ref: Any, seconds: float) -> int:
    """The encoder load, in the compute process: encode and top-k back to back."""
    from edge.daemon.compute import model_for

    model = model_for(ref)
    x = np.random.default_rng(1).normal(0, 2e-3, (25, 96)).astype(np.float32)
    n, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        model.topk(model.encode(x)[0], 3)
        n += 1
    return n


def first_crossing(ring: Any, outcome: PressOutcome,
                   x_th: float) -> tuple[float, int, float] | None:
    """Receive time, sequence number and sensor time (the server's wall clock) of the first
    frame over ``x_th`` after closing began (the controller's own norm), up to the stop."""
    states = dict(outcome.states)
    if outcome.tare is None or outcome.t_stop is None or "closing" not in states:
        return None
    win = ring.window(states["closing"] - 0.05, outcome.t_stop)
    if len(win.raw) == 0:
        return None
    level = np.linalg.norm(win.raw - outcome.tare, axis=1) / preprocess.UNITS_SCALE
    over = np.flatnonzero(level > x_th)
    if over.size == 0:
        return None
    i = int(over[0])
    return float(win.recv_time[i]), int(win.seq[i]), float(win.sensor_time[i])


READ_INSTRUCTION = 0x02


def _proc_cpu_s(pid: int, reaped_children: bool = False) -> float:
    """User + system CPU seconds of ``pid`` (and of its children it has waited for)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = fields[11:15] if reaped_children else fields[11:13]
    return sum(int(v) for v in ticks) / os.sysconf("SC_CLK_TCK")


def _host_cpu() -> tuple[float, float]:
    values = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = values[3] + values[4]
    return (sum(values) - idle) / os.sysconf("SC_CLK_TCK"), sum(values) / os.sysconf(
        "SC_CLK_TCK")


def _thread_sched(tid: int) -> tuple[float, float, int]:
    """CPU time, run-queue wait (s) and involuntary switches of thread ``tid`` here."""
    run_ns, wait_ns, _ = Path(f"/proc/self/task/{tid}/schedstat").read_text().split()
    forced = 0
    for line in Path(f"/proc/self/task/{tid}/status").read_text().splitlines():
        if line.startswith("nonvoluntary_ctxt_switches"):
            forced = int(line.split(":")[1])
    return int(run_ns) / 1e9, int(wait_ns) / 1e9, forced


def _bench_cpu_s() -> float:
    """CPU seconds of the bench and everything under it: its own, its reaped children's,
    and its live descendants' with their reaped children's (the compute worker is the
    forkserver's child, and the forkserver lives on)."""
    t = os.times()
    total = t.user + t.system + t.children_user + t.children_system
    for pid in process_tree(os.getpid())[1:]:
        with contextlib.suppress(OSError, ValueError, IndexError):
            total += _proc_cpu_s(pid, reaped_children=True)
    return total


def _cpu_mark() -> tuple[float, tuple[float, float], float]:
    return time.monotonic(), _host_cpu(), _bench_cpu_s()


def _cpu_since(mark: tuple[float, tuple[float, float], float]) -> dict[str, float]:
    """Cores busy on the host since ``mark``, and how many by processes not the bench's."""
    wall = time.monotonic() - mark[0]
    ours = (_bench_cpu_s() - mark[2]) / wall
    host = (_host_cpu()[0] - mark[1][0]) / wall
    return {"wall_s": round(wall, 1), "host_cores_busy": round(host, 2),
            "bench_cores": round(ours, 2), "other_cores": round(max(0.0, host - ours), 2)}


def cpu_snapshot(pids: dict[str, int]) -> dict[str, Any]:
    snap: dict[str, Any] = {"wall": time.monotonic(), "host": _host_cpu(), "pids": pids}
    with contextlib.suppress(OSError):
        snap["loop"] = _thread_sched(threading.get_native_id())
    for name, pid in pids.items():
        with contextlib.suppress(OSError):
            snap[name] = _proc_cpu_s(pid)
    return snap


def cpu_times_since(snap: dict[str, Any]) -> dict[str, float]:
    """Cores used on average since ``snap``: the whole host and each process."""
    wall = time.monotonic() - snap["wall"]
    busy, _ = _host_cpu()
    out = {"host_cores_busy": (busy - snap["host"][0]) / wall}
    for name, pid in snap["pids"].items():
        with contextlib.suppress(OSError, KeyError):
            out[name] = (_proc_cpu_s(pid) - snap[name]) / wall
    with contextlib.suppress(OSError, KeyError):
        run, wait, forced = _thread_sched(threading.get_native_id())
        # The event loop thread: its own CPU, and how long it sat runnable waiting for a core.
        out["loop_thread_cpu"] = (run - snap["loop"][0]) / wall
        out["loop_thread_runqueue_wait"] = (wait - snap["loop"][1]) / wall
        out["loop_thread_preempted_per_s"] = (forced - snap["loop"][2]) / wall
    return {k: round(v, 4) for k, v in out.items()}


def instrument_port(bus: Any) -> collections.deque[tuple[float, bytes]]:
    """The time and header of every packet the bus thread writes (the bus's ``on_write``
    hook).

    The stop is READ Present Position, then WRITE Goal Position (its write time is the stop
    latency's end); the READ's write time splits the latency into the software part (loop,
    hand-off to the bus thread, a transaction already on the wire) and the bus round trip.
    """
    writes: collections.deque[tuple[float, bytes]] = collections.deque(maxlen=8192)
    bus.on_write = lambda t, head: writes.append((t, head))
    return writes


def stop_read_time(writes: Sequence[tuple[float, bytes]], t_stop: float,
                   motor_id: int) -> float | None:
    """Write time of the last READ to ``motor_id`` before the stop's WRITE at ``t_stop``."""
    for t, head in reversed(list(writes)):
        if t < t_stop and len(head) >= 8 and head[4] == motor_id \
                and head[7] == READ_INSTRUCTION:
            return t
    return None


class SamplerWindow:
    """Records the runtime sampler from now until :meth:`close`: each wake-up's lateness
    (the sampler's own bench switch) and the time between samples (a stall shows whole,
    where the lateness is taken modulo the period after missed ticks)."""

    def __init__(self, sampler: Any) -> None:
        self.sampler = sampler
        self.before = asdict(sampler.stats)
        self.t0 = time.monotonic()
        self.intervals: list[float] = []
        self.lateness: list[float] = []
        last = [time.monotonic()]

        def on_tick(now: float, late: float) -> None:
            self.intervals.append(now - last[0])
            self.lateness.append(late)
            last[0] = now

        sampler.on_tick = on_tick

    def close(self) -> dict[str, Any]:
        sampler = self.sampler
        sampler.on_tick = None
        lateness = self.lateness
        after = asdict(sampler.stats)
        gaps = self.intervals[1:]
        return {
            "window_s": time.monotonic() - self.t0, "lateness_s": lateness,
            **{k: after[k] - self.before[k] for k in ("ticks", "missed_ticks", "gaps",
                                                      "extra_frames")},
            "max_interval_ms": 1e3 * max(gaps, default=0.0),
            "intervals_over_16ms": sum(v > 0.016 for v in gaps),
        }


class RuntimeBench:
    """The runtime in this process against the helper processes."""

    def __init__(self, settings: Settings, robot: Helper, vlm: Helper, state: Path) -> None:
        self.s = settings
        self.robot = robot.info
        self.vlm_info = vlm.info
        self.pids = {"daemon (this process)": os.getpid(), "sim robot": robot.proc.pid,
                     "fake VLM": vlm.proc.pid}
        self.state = state
        self.records: list[PressRecord] = []
        self.notes: list[str] = []
        self.load_stats: dict[str, Any] = {}
        self.quiet_stats: dict[str, Any] = {}
        self.compute: Any = None  # the ComputeWorker, while run() runs

    def config(self):
        from edge.core.config import load_config

        cfg = load_config(SIM_CONFIG)
        return replace(
            cfg,
            sensor=replace(cfg.sensor, url=self.robot["xela_url"]),
            bus=replace(cfg.bus, port=self.robot["dxl_port"]),
            camera=replace(cfg.camera, kind="http",
                           url=f"{self.robot['control_url']}/camera.jpg"),
            runtime=replace(cfg.runtime, models_dir=str(MODELS), state_dir=str(self.state),
                            move_time_s=self.s.move_time_s),
            api=replace(cfg.api, port=0),
            vlm=replace(cfg.vlm, base_url=self.vlm_info["base_url"], model="fake-vlm",
                        max_retries=0, total_timeout_s=60.0),
        )

    async def run(self) -> None:
        import aiohttp

        from edge.daemon.serve import assemble

        cfg = self.config()
        async with assemble(cfg) as daemon:
            runtime, compute = daemon.runtime, daemon.compute
            self.compute = compute
            worker = compute.pid()
            if worker is not None:
                self.pids["compute worker"] = worker
            self.port_writes = instrument_port(daemon.devices.bus)
            self.runtime = runtime
            rng = np.random.default_rng(0)
            self.controllers: dict[str, RecordingController] = {
                "per_frame": runtime.make_press_controller(RecordingController),
                "tick125": runtime.make_press_controller(
                    TickedController, name="tick125", period_s=1 / 125.0, rng=rng),
                "loop100": runtime.make_press_controller(
                    TickedController, name="loop100", period_s=1 / 100.0, rng=rng),
            }
            runtime.use_press_controller(self.controllers["per_frame"])
            task = asyncio.create_task(runtime.run(), name="bench-runtime")
            try:
                await asyncio.wait_for(runtime.ready.wait(), 30)
                self.api_url = f"http://127.0.0.1:{daemon.api.port}"
                async with aiohttp.ClientSession() as http:
                    self.http = http
                    await self._quiet_phase()
                    await self._loaded_phase(cfg, runtime.model)
                    await self._vlm_arrivals()
            finally:
                runtime.stop()
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(task, 30)

    # ----- one press

    async def _press(self, phase: str, name: str, obj: str) -> PressRecord:
        http, runtime = self.http, self.runtime
        ctl = self.controllers[name]
        async with http.post(f"{self.robot['control_url']}/object", json={"name": obj}) as r:
            r.raise_for_status()
        runtime.use_press_controller(ctl)
        marker = f"bench_{len(self.records):04d}"
        while True:
            t_trigger = time.monotonic()
            async with http.post(f"{self.api_url}/v1/recognize",
                                 json={"candidates": [*CUBE, marker]}) as r:
                if r.status == 202:
                    break
                if r.status != 409:
                    raise RuntimeError(f"recognize answered {r.status}: {await r.text()}")
            await asyncio.sleep(0.02)  # the previous press is still releasing its lock
        outcome = await asyncio.wait_for(ctl.outcomes.get(), PRESS_TIMEOUT_S)
        async with http.get(f"{self.robot['control_url']}/object") as r:
            world = await r.json()
        rec = PressRecord(phase, name, obj, marker, outcome.result, t_trigger,
                          message=outcome.message)
        states = dict(outcome.states)
        if "above" in states and "idle" in states:
            rec.press_s = states["idle"] - states["above"]
            rec.pre_press_ms = 1e3 * (states["above"] - t_trigger)
        if outcome.stop_latency_s is not None:
            rec.controller_latency_ms = 1e3 * outcome.stop_latency_s
        crossing = first_crossing(runtime.ring, outcome, runtime.cfg.press.x_th)
        if outcome.t_stop is not None and crossing is not None:
            # Counted whatever came after the stop (a late stop can still abort the hold).
            t_first, seq, sent_wall = crossing
            rec.t_first_cross, rec.t_stop = t_first, outcome.t_stop
            rec.stop_latency_ms = 1e3 * (outcome.t_stop - t_first)
            # The same stop seen from the XELA server: its frame time is its wall clock when
            # it sent the frame; the time the frame waited in the socket for the loop counts.
            wall_minus_mono = time.time() - time.monotonic()
            rec.from_send_ms = 1e3 * (outcome.t_stop + wall_minus_mono - sent_wall)
            t_read = stop_read_time(self.port_writes, outcome.t_stop,
                                    runtime.cfg.bus.gripper_id)
            if t_read is not None and t_read >= t_first:
                rec.to_bus_ms = 1e3 * (t_read - t_first)
            async with http.get(f"{self.robot['bench_url']}/force",
                                params={"seq": str(seq)}) as r:
                if r.status == 200:
                    rec.force_at_cross_n = (await r.json())["force_n"]
            rec.peak_force_n = world["peak_force_n"]
            if rec.force_at_cross_n is not None:
                rec.overshoot_n = rec.peak_force_n - rec.force_at_cross_n
        self.records.append(rec)
        return rec

    # ----- phases

    async def _press_ok(self, phase: str, name: str, obj: str) -> PressRecord:
        for _ in range(PRESS_ATTEMPTS):
            rec = await self._press(phase, name, obj)
            if rec.stop_latency_ms is not None:
                break
            _progress(f"  press failed ({name}, {obj}): {rec.result}: {rec.message}")
        return rec

    async def _quiet_phase(self) -> None:
        _progress(f"runtime: {self.s.quiet_presses} presses with no extra load (overhead)")
        window = SamplerWindow(self.runtime.sampler)
        try:
            for i in range(self.s.quiet_presses):
                rec = await self._press_ok("quiet", "per_frame", OBJECTS[i % len(OBJECTS)])
                _progress(f"  quiet press {i + 1}: {rec.result}, stop latency "
                          f"{_fmt(rec.stop_latency_ms)} ms, press {_fmt(rec.press_s)} s")
        finally:
            self.quiet_stats = window.close()

    async def _loaded_phase(self, cfg: Any, model: Any) -> None:
        from edge.core.errors import EdgeError
        from edge.core.vlm import OpenAIVLM
        from edge.daemon.serve import vlm_config

        s = self.s
        runtime = self.runtime
        image = await asyncio.to_thread(big_jpeg, s.image_px)
        _progress(f"runtime: load on: {s.load_vlm_clients} VLM clients sending a "
                  f"{s.image_px[0]}x{s.image_px[1]} JPEG ({len(image) / 1e6:.1f} MB) to a fake "
                  f"VLM answering after {s.vlm_latency_s} s; encoder looping in the compute "
                  f"process; /healthz and /metrics polled at {s.poll_hz:g} Hz")
        stop = asyncio.Event()
        counters = {"vlm_asks": 0, "vlm_errors": 0, "encodes": 0}
        # The load goes where the daemon's own work goes: images and the encoder to the
        # compute process.
        load_vlm = OpenAIVLM(vlm_config(cfg), offload=self.compute.run)

        async def vlm_load() -> None:
            while not stop.is_set():
                try:
                    await load_vlm.ask(image, "a load test", ["load_a", "load_b"])
                    counters["vlm_asks"] += 1
                except EdgeError:
                    counters["vlm_errors"] += 1
                    await asyncio.sleep(0.1)

        async def encode_load() -> None:
            if s.encode_duty <= 0:
                return
            pause = s.encode_load_s * (1.0 / s.encode_duty - 1.0)
            while not stop.is_set():
                counters["encodes"] += await self.compute.run(
                    encode_for, model, s.encode_load_s)
                if pause > 0:
                    await asyncio.sleep(pause)

        poller = await asyncio.to_thread(Helper, "poll", "--url", self.api_url,
                                         "--hz", str(s.poll_hz)) if s.poll_hz > 0 else None
        window = SamplerWindow(runtime.sampler)
        pids = dict(self.pids, **({"poller": poller.proc.pid} if poller else {}))
        cpu0 = cpu_snapshot(pids)
        t0 = time.monotonic()
        tasks = [asyncio.create_task(vlm_load(), name=f"bench-vlm-load-{i}")
                 for i in range(s.load_vlm_clients)]
        tasks.append(asyncio.create_task(encode_load(), name="bench-encode-load"))
        try:
            await asyncio.sleep(1.0)  # let the load settle in
            total = s.presses * len(CONTROLLERS)
            done = 0
            for i in range(s.presses):
                obj = OBJECTS[i % len(OBJECTS)]
                for name in CONTROLLERS:
                    rec = await self._press_ok("load", name, obj)
                    done += 1
                    _progress(f"  loaded press {done}/{total} ({name}, {obj}): {rec.result}, "
                              f"stop latency {_fmt(rec.stop_latency_ms)} ms, overshoot "
                              f"{_fmt(rec.overshoot_n, 3)} N")
            left = s.load_min_s - (time.monotonic() - t0)
            if left > 0:
                _progress(f"  load continues {left:.0f} s more (sampler window)")
                await asyncio.sleep(left)
        finally:
            cpu = cpu_times_since(cpu0)
            stop.set()
            duration = time.monotonic() - t0
            sampled = window.close()
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await load_vlm.close()
            poll_out = await asyncio.to_thread(poller.stop) if poller is not None else ""
        polled: dict[str, Any] = {}
        with contextlib.suppress(ValueError, IndexError):
            polled = json.loads(poll_out.strip().splitlines()[-1])
        self.load_stats = {
            "duration_s": duration, **sampled, "cpu_s": cpu,
            **counters, "poll": polled, "image_bytes": len(image),
        }
        _progress(f"runtime: load off after {duration:.0f} s: {counters['vlm_asks']} VLM asks "
                  f"({counters['vlm_errors']} failed), {counters['encodes']} encodes, "
                  f"{polled.get('requests', '?')} API polls ({polled.get('errors', '?')} "
                  "failed)")

    async def _vlm_arrivals(self) -> None:
        """Match each press's VLM request (by its marker candidate) to its arrival time."""
        deadline = time.monotonic() + 30.0
        wanted = {r.marker: r for r in self.records if r.result == "ok"}
        while True:
            async with self.http.get(f"{self.vlm_info['bench_url']}/received") as r:
                arrivals = await r.json()
            for a in arrivals:
                rec = wanted.get(a["candidates"][-1] if a["candidates"] else "")
                if rec is not None and rec.t_vlm is None:
                    rec.t_vlm = a["t"]
            if all(r.t_vlm is not None for r in wanted.values()) or time.monotonic() > deadline:
                break
            await asyncio.sleep(0.2)
        for rec in wanted.values():
            if rec.t_vlm is not None and rec.press_s is not None:
                rec.overhead_ms = 1e3 * (rec.t_vlm - rec.t_trigger - rec.press_s)
        missing = [m for m, r in wanted.items() if r.t_vlm is None]
        if missing:
            self.notes.append(f"{len(missing)} VLM requests never arrived: {missing[:5]}")

    # ----- figures

    def figures(self) -> dict[str, Any]:
        figs: dict[str, Any] = {}
        load = self.load_stats
        late_ms = [1e3 * v for v in load.get("lateness_s", [])]
        figs["sampler_period_error_ms"] = figure(
            late_ms, "ms", target(("p99", "<=", 1.0), ("missed_ticks", "==", 0)),
            missed_ticks=load.get("missed_ticks"), ticks=load.get("ticks"),
            gaps=load.get("gaps"), duration_s=load.get("duration_s"),
            max_gap_ms=load.get("max_interval_ms"),
            what="lateness of each 125 Hz sampler wake-up vs its ideal deadline, under load")
        calm = self.quiet_stats
        figs["sampler_period_error_ms_no_load"] = figure(
            [1e3 * v for v in calm.get("lateness_s", [])], "ms", None,
            missed_ticks=calm.get("missed_ticks"), ticks=calm.get("ticks"),
            duration_s=calm.get("window_s"), max_gap_ms=calm.get("max_interval_ms"),
            what="as sampler_period_error_ms, during the presses with no extra load")
        loaded = [r for r in self.records if r.phase == "load"]
        lat = {}
        for name in CONTROLLERS:
            recs = [r for r in loaded if r.controller == name]
            key = "stop_latency_ms" if name == "per_frame" else f"stop_latency_ms_{name}"
            failed = [f"{r.result}: {r.message}" for r in recs if r.stop_latency_ms is None]
            aborted = [r for r in recs if r.stop_latency_ms is not None and r.result != "ok"]
            # The controller's own crossing frame was a later one: it never saw the first
            # frame over x_th (a ticked check sees only the latest frame at each tick).
            later = [r for r in recs if r.stop_latency_ms is not None
                     and r.controller_latency_ms is not None
                     and r.stop_latency_ms - r.controller_latency_ms > 0.5]
            lat[name] = figs[key] = figure(
                [r.stop_latency_ms for r in recs], "ms",
                target(("p99", "<=", 2.0)) if name == "per_frame" else None,
                controller=CONTROLLER_TEXT[name], failed_presses=len(failed),
                aborted_after_stop=len(aborted), missed_first_crossing=len(later),
                to_bus_ms=stats([r.to_bus_ms for r in recs]),
                from_server_send_ms=stats([r.from_send_ms for r in recs]),
                what="first frame over x_th received -> stop packet written to the port, "
                     "under load")
            if failed:
                self.notes.append(f"{name}: {len(failed)} presses without a stop (tried again): "
                                  f"{failed[:3]}")
            if aborted:
                self.notes.append(
                    f"{name}: {len(aborted)} presses stopped, then aborted the hold: "
                    f"{[r.message for r in aborted][:3]} (their stop latencies are counted)")
            if later:
                self.notes.append(
                    f"{name}: in {len(later)} presses the controller stopped on a later frame "
                    f"than the first over x_th (by up to "
                    f"{max(r.stop_latency_ms - r.controller_latency_ms for r in later):.0f} "
                    "ms): the level crossed x_th and fell back between two checks")
        quiet = [r for r in self.records if r.phase == "quiet"]
        figs["stop_latency_ms_no_load"] = figure(
            [r.stop_latency_ms for r in quiet], "ms", None, controller=CONTROLLER_TEXT["per_frame"],
            to_bus_ms=stats([r.to_bus_ms for r in quiet]),
            from_server_send_ms=stats([r.from_send_ms for r in quiet]),
            what="as stop_latency_ms, with no extra load (the overhead presses)")
        figs["stop_latency_ratio_loop100"] = ratio_figure(
            lat["loop100"], lat["per_frame"], target(("p50", ">=", 5.0)),
            what="100 Hz loop stop latency / per-frame stop latency (statistic by statistic)")
        figs["stop_latency_ratio_tick125"] = ratio_figure(
            lat["tick125"], lat["per_frame"],
            what="125 Hz tick stop latency / per-frame stop latency (statistic by statistic)")
        for obj in OBJECTS:
            for name in CONTROLLERS:
                recs = [r for r in loaded if r.controller == name and r.object == obj]
                figs[f"force_overshoot_n_{obj}_{name}"] = figure(
                    [r.overshoot_n for r in recs], "N", None, controller=CONTROLLER_TEXT[name],
                    what=f"peak normal force minus the force at the first frame over x_th "
                         f"(SimWorld), {obj}")
        for phase, key, goal in (("quiet", "overhead_ms", target(("p99", "<=", 20.0))),
                                 ("load", "overhead_ms_under_load", None)):
            recs = [r for r in self.records if r.phase == phase]
            figs[key] = figure(
                [r.overhead_ms for r in recs], "ms", goal,
                pre_press_ms_p50=stats([r.pre_press_ms for r in recs])["p50"],
                what="POST /v1/recognize -> VLM request received, minus the press itself "
                     "('above' entered -> 'idle' entered)" +
                     (", no extra load" if phase == "quiet" else ", under the load"))
        return figs


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def runtime_phase(s: Settings, tmp: Path) -> tuple[dict[str, Any], list[str], list[dict],
                                                   dict[str, Any]]:
    from edge.daemon.serve import new_event_loop

    _progress("starting the emulated robot and the fake VLM (own processes)")
    robot = Helper("robot", "--config", str(SIM_CONFIG), "--object", OBJECTS[0],
                   "--nice", str(ROBOT_NICE))
    if robot.info.get("nice") is None:
        _progress(f"  (the emulated robot could not be reniced to {ROBOT_NICE})")
    vlm = None
    try:
        vlm = Helper("vlm", "--latency-s", str(s.vlm_latency_s))
        bench = RuntimeBench(s, robot, vlm, tmp / "state")
        quiet_loggers = [logging.getLogger(n) for n in ("edge", "aiohttp")]
        levels = [lg.level for lg in quiet_loggers]
        for lg in quiet_loggers:
            lg.setLevel(logging.WARNING)
        try:
            # The daemon's own event loop (edge.daemon.serve.new_event_loop), as `vt-edge run` has.
            with asyncio.Runner(loop_factory=new_event_loop) as runner:
                runner.run(bench.run())
        finally:
            for lg, level in zip(quiet_loggers, levels, strict=True):
                lg.setLevel(level)
    finally:
        if vlm is not None:
            vlm.stop()
        robot.stop()
    load = {k: v for k, v in bench.load_stats.items() if k != "lateness_s"}
    return bench.figures(), bench.notes, [asdict(r) for r in bench.records], load


# --------------------------------------------------------------------------------------
# Phase 2: the daemon as a process


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants (the daemon, its forkserver and compute worker)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            # The command name may hold spaces and parentheses: the fields follow the last ')'.
            ppid = int(stat.read_text().rpartition(")")[2].split()[1])
            children.setdefault(ppid, []).append(int(stat.parent.name))
    tree, todo = [], [pid]
    while todo:
        p = todo.pop()
        tree.append(p)
        todo.extend(children.get(p, []))
    return tree


def _rss_mb(pid: int) -> tuple[float, float, float, float]:
    """Over ``pid``'s process tree, in MiB: the sum of VmRSS (pages shared between the
    processes counted in each: an upper bound), of VmHWM (peaks), of Pss (shared pages
    split between their processes: the memory the tree really takes), and ``pid``'s own
    VmRSS."""
    rss = hwm = pss = own = 0.0
    for p in process_tree(pid):
        with contextlib.suppress(OSError):
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                key, _, value = line.partition(":")
                if key == "VmRSS":
                    rss += int(value.split()[0]) / 1024.0
                    if p == pid:
                        own = int(value.split()[0]) / 1024.0
                elif key == "VmHWM":
                    hwm += int(value.split()[0]) / 1024.0
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    pss += int(line.split()[1]) / 1024.0
    return rss, hwm, pss, own


def torch_mappings(pid: int) -> list[str]:
    """Mapped files of ``pid`` that belong to torch (libtorch*, .../torch/...)."""
    found = set()
    for line in Path(f"/proc/{pid}/maps").read_text().splitlines():
        parts = line.split(maxsplit=5)
        path = parts[5] if len(parts) == 6 else ""
        if "libtorch" in path or "/torch/" in path or "libc10" in path:
            found.add(path)
    return sorted(found)


def daemon_phase(s: Settings, tmp: Path) -> tuple[dict[str, Any], list[str]]:
    from edge.core import tomledit
    from edge.core.config import load_config

    notes: list[str] = []
    env = dict(os.environ, VTZERO_STATE_DIR=str(tmp / "daemon-state"), PYTHONUNBUFFERED="1",
               VTZERO_LOG_LEVEL="WARNING")
    for key in ("VTZERO_VLM_URL", "VTZERO_VLM_MODEL", "NOTIFY_SOCKET", "WATCHDOG_USEC",
                "WATCHDOG_PID"):
        env.pop(key, None)
    run_cfg = tmp / "daemon.toml"
    _progress("daemon process: starting `vt-edge sim serve`")
    sim = subprocess.Popen([sys.executable, "-m", "edge", "sim", "serve", "--config",
                            str(SIM_CONFIG), "--object", OBJECTS[0], "--write-config",
                            str(run_cfg)], cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
    startup, rss, hwm, pss, main_rss, torch_found = [], [], [], [], [], []
    try:
        deadline = time.monotonic() + HELPER_START_S
        while not run_cfg.exists():
            if sim.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("vt-edge sim serve did not write its configuration")
            time.sleep(0.05)
        port = _free_port()
        tomledit.update(run_cfg, run_cfg, {"api": {"port": port}})
        api = f"http://127.0.0.1:{port}"
        control = load_config(run_cfg).camera.url.rsplit("/", 1)[0]
        for i in range(s.daemon_runs):
            sock_path = tmp / f"notify-{i}.sock"
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
                sock.bind(str(sock_path))
                log_path = tmp / f"daemon-{i}.log"
                with log_path.open("w") as err:
                    t0 = time.monotonic()
                    proc = subprocess.Popen(
                        [sys.executable, "-m", "edge", "run", "--config", str(run_cfg)],
                        cwd=ROOT, env={**env, "NOTIFY_SOCKET": str(sock_path)},
                        stdout=subprocess.DEVNULL, stderr=err)
                    try:
                        t_ready = _wait_ready(sock, proc, 60.0)
                        startup.append(t_ready - t0)
                        _progress(f"daemon process {i + 1}/{s.daemon_runs}: READY=1 after "
                                  f"{t_ready - t0:.2f} s; one recognition, then RSS")
                        http_json("POST", f"{control}/object", {"name": OBJECTS[i % 2]})
                        ep = http_json("POST", f"{api}/v1/recognize",
                                       {"candidates": CUBE, "wait": True, "timeout_s": 50},
                                       timeout=60)
                        if ep.get("status") not in ("not_configured", "done"):
                            notes.append(f"daemon process recognition: {ep.get('status')} "
                                         f"{ep.get('error', '')}")
                        for _ in range(s.rss_samples):
                            time.sleep(0.5)
                            http_json("GET", f"{api}/healthz", timeout=5)
                            now, peak, proportional, own = _rss_mb(proc.pid)
                            rss.append(now)
                            hwm.append(peak)
                            pss.append(proportional)
                            main_rss.append(own)
                        torch_found.append([m for p in process_tree(proc.pid)
                                            for m in torch_mappings(p)])
                    finally:
                        if proc.poll() is None:
                            proc.send_signal(signal.SIGTERM)
                        try:
                            rc = proc.wait(30)
                        except subprocess.TimeoutExpired:
                            proc.kill()
                            rc = proc.wait()
                    if rc != 0:
                        notes.append(f"daemon run {i + 1} exited with {rc}; log: "
                                     f"{log_path.read_text()[-500:]}")
    finally:
        sim.send_signal(signal.SIGTERM)
        try:
            sim.wait(20)
        except subprocess.TimeoutExpired:
            sim.kill()
    mapped = sorted({p for found in torch_found for p in found})
    figs = {
        "startup_to_ready_s": figure(startup, "s", target(("max", "<=", 3.0)),
                                     what="`vt-edge run` process start -> READY=1 received on "
                                          "NOTIFY_SOCKET"),
        "daemon_rss_mb": figure(pss, "MiB", target(("max", "<=", 150.0)),
                                rss_sum_mb=stats(rss), main_rss_mb=stats(main_rss),
                                peak_hwm_sum_mb=max(hwm) if hwm else None,
                                what="memory of the daemon's processes (the daemon, its "
                                     "forkserver, compute worker and resource tracker) at "
                                     "steady state after one recognition: their Pss summed "
                                     "(pages shared between them split, not counted in each; "
                                     "rss_sum_mb counts them in each, main_rss_mb is the "
                                     "event-loop process alone)"),
        "daemon_torch_mapped": figure([len(f) for f in torch_found], "files",
                                      target(("max", "==", 0)), mapped=mapped,
                                      what="torch libraries mapped into any of the daemon's "
                                           "processes (/proc/PID/maps) after a recognition"),
    }
    if mapped:
        notes.append(f"TORCH IS LOADED BY THE DAEMON: {mapped[:3]}")
    return figs, notes


def _wait_ready(sock: socket.socket, proc: subprocess.Popen, timeout_s: float) -> float:
    deadline = time.monotonic() + timeout_s
    while True:
        left = deadline - time.monotonic()
        if left <= 0 or proc.poll() is not None:
            raise RuntimeError(f"daemon sent no READY=1 (exit {proc.poll()})")
        sock.settimeout(min(left, 0.5))
        try:
            data = sock.recv(4096)
        except TimeoutError:
            continue
        t = time.monotonic()
        if b"READY=1" in data.split(b"\n"):
            return t


# --------------------------------------------------------------------------------------
# Phase 3: encoder and retrieval


def _timed(fn: Callable[[int], Any], n: int, warmup: int = 20) -> list[float]:
    for i in range(warmup):
        fn(i)
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out.append(1e3 * (time.perf_counter() - t0))
    return out


def torch_encoder_from_onnx(path: Path, manifest: dict[str, Any]):
    """The shipped encoder as a torch module, weights read back from ``encoder.onnx``.

    ONNX GRU gates are ordered (z, r, h) and torch's (r, z, n); biases are [Wb | Rb]. The
    caller checks parity with onnxruntime before trusting it.
    """
    import onnx
    import torch
    from onnx import numpy_helper

    from train.model import ExportEncoder, ModelConfig, TactileAutoencoder

    proto = onnx.load(str(path))
    init = {t.name: numpy_helper.to_array(t).copy() for t in proto.graph.initializer}
    cfg = ModelConfig(**manifest["training"]["vq"]["config"]["model"])
    model = TactileAutoencoder(cfg).eval()
    h = cfg.hidden

    def reorder(m: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.concatenate([m[h:2 * h], m[:h], m[2 * h:]]))

    grus = [n for n in proto.graph.node if n.op_type == "GRU"]
    if len(grus) != cfg.layers:
        raise ValueError(f"{len(grus)} GRU nodes in {path}, the model has {cfg.layers} layers")
    gru = model.encoder.gru
    with torch.no_grad():
        for layer, node in enumerate(grus):
            w, r, b = (init[name] for name in node.input[1:4])
            for d, suffix in enumerate(("", "_reverse")):
                getattr(gru, f"weight_ih_l{layer}{suffix}").copy_(reorder(w[d]))
                getattr(gru, f"weight_hh_l{layer}{suffix}").copy_(reorder(r[d]))
                getattr(gru, f"bias_ih_l{layer}{suffix}").copy_(reorder(b[d][:3 * h]))
                getattr(gru, f"bias_hh_l{layer}{suffix}").copy_(reorder(b[d][3 * h:]))
        model.encoder.head.weight.copy_(torch.from_numpy(init["encoder.head.weight"]))
        model.encoder.head.bias.copy_(torch.from_numpy(init["encoder.head.bias"]))
        meta = {p.key: p.value for p in proto.metadata_props}
        book = np.asarray(json.loads(meta["vtzero.codebook"]), dtype=np.float32)
        assert model.quantiser is not None
        model.quantiser.codebook.copy_(torch.from_numpy(book))
    return ExportEncoder(model, init["mean"], init["std"]).eval()


# Encoder calls alternate in blocks: both runtimes see the same (shared, noisy) host, and
# each runs warm (alternating single calls evicts onnxruntime's small working set: its
# median doubled in a trial).
ENCODE_BLOCK = 50


def encode_phase(s: Settings) -> tuple[dict[str, Any], list[str]]:
    """onnxruntime through edge.core.model against torch eager on the same weights and inputs."""
    from edge.core.model import load_model

    notes: list[str] = []
    model = load_model(MODELS)
    manifest = model.manifest
    mean = np.asarray(manifest["encoder"]["mean"], dtype=np.float32)
    std = np.asarray(manifest["encoder"]["std"], dtype=np.float32)
    rng = np.random.default_rng(0)
    xs = (mean + std * rng.standard_normal((64, 25, 96))).astype(np.float32)
    calls: dict[str, Callable[[np.ndarray], Any]] = {"ort": model.encode}
    worst = None
    torch = None
    if _version("torch") is None:
        notes.append("torch is not installed: no torch eager comparison")
    else:
        import torch

        torch.set_num_threads(1)
        wrapper = torch_encoder_from_onnx(MODELS / "encoder.onnx", manifest)

        def torch_encode(x: np.ndarray) -> tuple[np.ndarray, int]:
            with torch.inference_mode():
                z, code = wrapper(torch.from_numpy(x[None]))
                return z.numpy()[0], int(code[0])

        calls["torch"] = torch_encode
        worst = max(float(np.abs(torch_encode(x)[0] - model.encode(x)[0]).max()) for x in xs)
    _progress(f"encoder: {s.encode_n} single-sequence encodes each: onnxruntime (1 thread, "
              f"the robot's options)" + (f", torch {torch.__version__} eager (1 thread, same "
                                         f"weights and inputs, parity max |dz| {worst:.2g})"
                                         if torch else ""))
    times: dict[str, list[float]] = {name: [] for name in calls}
    for start in range(-ENCODE_BLOCK, s.encode_n, ENCODE_BLOCK):  # the first block warms up
        for name, fn in calls.items():
            for i in range(start, start + ENCODE_BLOCK):
                x = xs[i % len(xs)]
                t0 = time.perf_counter()
                fn(x)
                if i >= 0:
                    times[name].append(1e3 * (time.perf_counter() - t0))
    figs = {"encode_ms": figure(times["ort"], "ms", target(("p50", "<=", 0.3)),
                                what="edge.core.model Model.encode of one (25, 96) sequence, "
                                     "onnxruntime CPU, 1 intra-op thread")}
    if "torch" in times:
        figs["encode_ms_torch"] = figure(
            times["torch"], "ms", None, parity_max_abs_dz=worst,
            what="the same encoder in torch eager (weights read back from encoder.onnx), "
                 "1 thread, inference_mode, same inputs, in blocks alternating with onnxruntime's")
        figs["encode_speedup_vs_torch"] = ratio_figure(
            figs["encode_ms_torch"], figs["encode_ms"], target(("p50", ">=", 10.0)),
            what="torch eager time / onnxruntime time (statistic by statistic)")
        if worst is None or not worst < 1e-4:
            notes.append(f"torch reconstruction differs from onnxruntime (max |dz| {worst}): "
                         "the torch timing is of a different function")
    return figs, notes


def numpy_topk(refs: np.ndarray, labels: np.ndarray, q: np.ndarray, k: int) -> list[int]:
    """Plain numpy: every distance, argsort, first k distinct classes."""
    d = np.sqrt(((refs - q) ** 2).sum(axis=1))
    order = np.argsort(d)
    _, first = np.unique(labels[order], return_index=True)
    return [int(labels[order[i]]) for i in np.sort(first)[:k]]


def retrieval_phase(s: Settings) -> tuple[dict[str, Any], list[str]]:
    from edge.core.model import load_model, synthetic_database

    notes: list[str] = []
    figs: dict[str, Any] = {}
    shipped = load_model(MODELS).database
    dbs = [("shipped", shipped)]
    _progress(f"retrieval: building a synthetic database of {s.retrieval_refs:,} "
              f"references, {s.retrieval_classes} classes")
    dbs.append(("1m", synthetic_database(s.retrieval_refs, s.retrieval_classes)))
    rng = np.random.default_rng(1)
    for name, db in dbs:
        # The embeddings topk compares (its space), grouped by class like label_index.
        refs, labels = (db.z if db.space == "z" else db.z_q), db.label_index
        if name == "shipped":
            qs = refs[rng.integers(0, len(refs), s.retrieval_queries)] + \
                rng.normal(0, 0.05 * refs.std(), (s.retrieval_queries, db.dim))
        else:
            qs = rng.standard_normal((s.retrieval_queries, db.dim))
        qs = qs.astype(np.float32)
        n_brute = s.retrieval_queries if name == "shipped" else s.brute_queries_1m
        _progress(f"retrieval ({name}, {len(db):,} refs): {s.retrieval_queries} top-k "
                  f"queries, {n_brute} numpy brute-force queries")
        fast = _timed(lambda i, db=db, qs=qs: db.topk(qs[i % len(qs)], 3),
                      s.retrieval_queries, warmup=3)
        brute = _timed(lambda i, r=refs, lb=labels, qs=qs: numpy_topk(r, lb, qs[i % len(qs)], 3),
                       n_brute, warmup=1)
        names = db.labels
        mismatch = sum(
            [label for label, _ in db.topk(q, 3)] != [names[c] for c in numpy_topk(
                refs, labels, q, 3)] for q in qs[:n_brute])
        ships = name == "1m"
        key = "retrieval_ms_1m" if ships else "retrieval_ms_shipped"
        figs[key] = figure(fast, "ms", target(("p50", "<=", 5.0)) if ships else None,
                           references=len(db), classes=len(db.classes),
                           what="ReferenceDatabase.topk (k = 3 distinct classes), one query")
        figs[f"retrieval_numpy_ms_{name}"] = figure(
            brute, "ms", None, references=len(db), answer_mismatches=mismatch,
            what="plain numpy: all L2 distances, argsort, first 3 distinct classes")
        figs[f"retrieval_speedup_{name}"] = ratio_figure(
            figs[f"retrieval_numpy_ms_{name}"], figs[key],
            what="numpy brute force time / topk time (statistic by statistic)")
        if mismatch:
            notes.append(f"retrieval ({name}): top-3 differs from numpy brute force on "
                         f"{mismatch} of {n_brute} queries (ties?)")
    return figs, notes


# --------------------------------------------------------------------------------------
# Phase 4: training


def train_phase(s: Settings, tmp: Path) -> tuple[dict[str, Any], list[str]]:
    notes: list[str] = []
    if _version("torch") is None:
        notes.append("torch is not installed: no training figure")
        return {}, notes
    from edge.core.model import read_manifest
    from edge.sim.record import record_dataset
    from train.data import training_data
    from train.trainer import Progress, TrainConfig, train

    manifest = read_manifest(MODELS)
    shipped = manifest["training"]["vq"]
    config = TrainConfig.from_dict(shipped["config"])
    if s.train_max_epochs is not None:
        config = replace(config, max_epochs=s.train_max_epochs)
    rec_dir = tmp / "recordings"
    _progress(f"training: recording {s.train_presses} simulated presses per reference class")
    t0 = time.perf_counter()
    record_dataset("reference", s.train_presses, rec_dir, seed=0)
    record_s = time.perf_counter() - t0
    data = training_data(rec_dir)
    _progress(f"training: recorded in {record_s:.1f} s; training the VQ encoder "
              f"(shipped config, max {config.max_epochs} epochs, patience {config.patience}, "
              f"{config.threads} thread(s))")
    result = train(data, config, None, Progress(every=10))
    epochs_note = ("shipped configuration" if s.train_max_epochs is None
                   else f"QUICK: capped at {s.train_max_epochs} epochs, not the shipped run")
    fig = figure([result.seconds], "s", None, epochs=result.epochs,
                 best_epoch=result.best_epoch, stopped=result.stopped,
                 train_samples=len(data.train), record_s=record_s,
                 shipped_epochs=shipped["result"]["epochs"],
                 shipped_train_s=manifest.get("timings", {}).get("train_vq_s"),
                 what=f"train.trainer.train of the VQ-VAE on {s.train_presses} fresh simulated "
                      f"presses per reference class ({epochs_note})")
    return {"train_s": fig}, notes


# --------------------------------------------------------------------------------------
# Output


# Every figure a full run writes (the train and torch figures need torch), in table order.
FIGURES = (
    "sampler_period_error_ms", "sampler_period_error_ms_no_load",
    "stop_latency_ms", "stop_latency_ms_tick125",
    "stop_latency_ms_loop100", "stop_latency_ratio_loop100", "stop_latency_ratio_tick125",
    "stop_latency_ms_no_load",
    *(f"force_overshoot_n_{o}_{c}" for o in OBJECTS for c in CONTROLLERS),
    "overhead_ms", "overhead_ms_under_load",
    "startup_to_ready_s", "daemon_rss_mb", "daemon_torch_mapped",
    "encode_ms", "encode_ms_torch", "encode_speedup_vs_torch",
    "retrieval_ms_shipped", "retrieval_numpy_ms_shipped", "retrieval_speedup_shipped",
    "retrieval_ms_1m", "retrieval_numpy_ms_1m", "retrieval_speedup_1m",
    "train_s",
)
TORCH_FIGURES = ("encode_ms_torch", "encode_speedup_vs_torch", "train_s")


def _cell(value: Any, unit: str) -> str:
    if value is None:
        return "-"
    if unit == "ratio":
        return f"{value:.1f}x"
    if isinstance(value, int) or (float(value).is_integer() and abs(value) > 10):
        return f"{value:g}"
    return f"{value:.3g}" if abs(value) < 100 else f"{value:.0f}"


def markdown(results: dict[str, Any], notes: list[str]) -> str:
    host, run = results["host"], results["run"]
    figs = {k: v for k, v in results.items() if isinstance(v, dict) and "unit" in v}
    keys = [k for k in FIGURES if k in figs] + [k for k in figs if k not in FIGURES]
    lines = [
        "# vt-edge bench",
        "",
        f"{'QUICK run (smoke test: figures are not representative). ' if run['quick'] else ''}"
        f"{run['started_at']}, {run['duration_s']:.0f} s. Host: {host['cpu_model']}, "
        f"{host['cores']} cores, Python {host['python']}, onnxruntime {host['onnxruntime']}, "
        f"numpy {host['numpy']}, torch {host['torch']}; load average at start "
        f"{', '.join(f'{v:.2f}' for v in host['loadavg_start'])}, at end "
        f"{', '.join(f'{v:.2f}' for v in run['loadavg_end'])}. Commit {host['git_commit']}.",
        "",
        "CPU during each phase (cores busy on the host / of them by processes outside the "
        "bench): " + "; ".join(f"{name} {c['host_cores_busy']:.2f} / {c['other_cores']:.2f}"
                               for name, c in run.get("phase_cpu", {}).items()) + ".",
        "",
        "| figure | p50 | p99 | max | n | unit | target | met |",
        "| --- | ---: | ---: | ---: | ---: | --- | --- | --- |",
    ]
    for key in keys:
        f = figs[key]
        met = {True: "yes", False: "**NO**", None: "-"}[f["met"]]
        lines.append(f"| `{key}` | {_cell(f['p50'], f['unit'])} | {_cell(f['p99'], f['unit'])} "
                     f"| {_cell(f['max'], f['unit'])} | {f['n']} | {f['unit']} | "
                     f"{target_text(f['target'])} | {met} |")
    load = run.get("load")
    if load:
        cpu = load.get("cpu_s", {})
        lines += ["", "## The load", "",
                  f"{load.get('duration_s', 0):.0f} s; {load.get('vlm_asks')} VLM requests with a "
                  f"{load.get('image_bytes', 0) / 1e6:.1f} MB still ({load.get('vlm_errors')} "
                  f"failed), {load.get('encodes')} encoder runs (each an encode and a top-k), "
                  f"{(load.get('poll') or {}).get('requests', '?')} API polls. Sampler: "
                  f"{load.get('ticks')} ticks, {load.get('missed_ticks')} missed, longest gap "
                  f"between two samples {load.get('max_interval_ms', 0):.1f} ms "
                  f"({load.get('intervals_over_16ms')} gaps over two periods). CPU, in cores: "
                  + ", ".join(f"{k} {v:g}" for k, v in cpu.items()) + "."]
    lines += ["", "## Reading the figures", "",
              "- Stop latency is measured from the same frame for every controller: the first "
              "frame whose norm crosses x_th, found afterwards in the frame ring; the end is the "
              "stop's WRITE packet at the port. A ticked controller checks only the latest "
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
              "", "## What each figure is", ""]
    for key in keys:
        extra = {k: v for k, v in figs[key].items()
                 if k not in ("p50", "p99", "max", "n", "unit", "target", "met", "what",
                              "host_cores_busy")}
        detail = ", ".join(f"{k} {_short(v)}" for k, v in extra.items())
        lines.append(f"- `{key}`: {figs[key].get('what', '')}" + (f" ({detail})" if detail
                                                                 else ""))
    if notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in notes]
    return "\n".join(lines) + "\n"


def _short(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, list | dict):
        text = json.dumps(v)
        return text if len(text) < 120 else text[:117] + "..."
    return str(v)


def run_bench(args: argparse.Namespace) -> int:
    s = QUICK if getattr(args, "quick", False) else FULL
    return bench(Path(getattr(args, "out", "bench")), s)


def bench(out: Path, s: Settings, phases: Sequence[str] = ("runtime", "daemon", "encode",
                                                             "retrieval", "train"),
          extra_notes: Sequence[str] = ()) -> int:
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    host = host_info()
    run: dict[str, Any] = {
        "quick": s.quick, "settings": asdict(s), "phases": list(phases),
        "started_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": "vt-edge bench" + (" --quick" if s.quick else ""),
    }
    _progress(f"{'quick' if s.quick else 'full'} run on {host['cpu_model']} "
              f"({host['cores']} cores), load average {host['loadavg_start']}")
    figures: dict[str, Any] = {}
    notes: list[str] = list(extra_notes)
    raw: dict[str, Any] = {}
    runners: dict[str, Callable[[Path], tuple]] = {
        "runtime": lambda tmp: runtime_phase(s, tmp),
        "daemon": lambda tmp: daemon_phase(s, tmp),
        "encode": lambda tmp: encode_phase(s),
        "retrieval": lambda tmp: retrieval_phase(s),
        "train": lambda tmp: train_phase(s, tmp),
    }
    run["phase_cpu"] = {}
    with tempfile.TemporaryDirectory(prefix="vtzero-bench-") as tmp_name:
        tmp = Path(tmp_name)
        for phase in phases:
            before = _cpu_mark()
            out_ = runners[phase](tmp)
            cpu = _cpu_since(before)
            run["phase_cpu"][phase] = cpu
            figs, more = out_[0], out_[1]
            if phase == "runtime":
                raw["presses"], run["load"] = out_[2], out_[3]
            for fig in figs.values():
                fig["host_cores_busy"] = cpu["host_cores_busy"]
            figures.update(figs)
            notes += more
            _progress(f"{phase}: host {cpu['host_cores_busy']:.2f} of {host['cores']} cores "
                      f"busy, {cpu['other_cores']:.2f} of them by other processes")
    run["duration_s"] = time.monotonic() - started
    run["loadavg_end"] = list(os.getloadavg())
    notes += explain(figures, host)
    results = {"host": host, "run": run, **figures, "notes": notes}
    (out / "results.json").write_text(json.dumps(results, indent=1, default=_plain) + "\n")
    (out / "raw.json").write_text(json.dumps(raw, indent=1, default=_plain) + "\n")
    md = markdown(results, notes)
    (out / "results.md").write_text(md)
    print(md)
    _progress(f"wrote {out / 'results.json'}, {out / 'results.md'}, {out / 'raw.json'} "
              f"in {run['duration_s']:.0f} s")
    return 0


def _plain(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def explain(figures: dict[str, Any], host: dict[str, Any]) -> list[str]:
    """One line per missed target: why, and what would close it."""
    out = []
    for key, fig in figures.items():
        if fig.get("met") is False:
            out.append(f"MISSED `{key}` ({target_text(fig['target'])}): p50 "
                       f"{_short(fig['p50'])}, p99 {_short(fig['p99'])}, max "
                       f"{_short(fig['max'])} {fig['unit']}. {WHY.get(key, '')}".rstrip())
    return out


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
        "The median is near the unloaded figure (stop_latency_ms_no_load); the tail is the "
        "loop held up as for the sampler: in the slow presses the time goes before the "
        "stop's READ reaches the port (to_bus_ms: the frame waiting for the loop, the stop "
        "waiting for the bus thread), not on the bus. To close it: as for the sampler. On "
        "the real arm add a USB round trip: the stop reads Present Position before writing "
        "the goal (at least the adapter's 1 ms latency timer)."),
    "stop_latency_ratio_loop100": (
        "The load's stalls inflate the per-frame median far more, relatively, than the "
        "100 Hz loop's, whose own wait for its next tick is 0-10 ms (5 ms on average); "
        "idle, the per-frame path is at stop_latency_ms_no_load. The ratio also flatters "
        "the loop: see missed_first_crossing and aborted_after_stop of "
        "stop_latency_ms_loop100. Closing the per-frame tail (above) closes this."),
    "overhead_ms": (
        "What remains: the API request and the pre-press motor check (pre_press_ms), the "
        "crop, encoder and serialisation in the compute process and the pickling both ways "
        "(about 5 ms), image preparation there, JSON and the POST; the episode's durable "
        "write overlaps the VLM request. The p99 of 8 presses is their slowest, on a host "
        "shared with the emulated robot. To close it: the host as for the sampler; one "
        "round trip to the compute process for the analysis and the image together, "
        "started as soon as the window after the stop is complete."),
    "encode_ms": (
        "onnxruntime itself needs about 0.1 ms per sequence on a quiet core (0.094 ms p50 "
        "in a separate run of this code); see host_cores_busy and the other tenants' share "
        "in the CPU line above for this phase. To close it: a quiet core."),
    "encode_speedup_vs_torch": (
        "The ratio moves with onnxruntime's time on a busy host (torch's ~1-2 ms per call "
        "hides the noise better); 11.5-12.8x was measured on a calmer moment with the same "
        "block method. To close it: a quiet core."),
    "retrieval_ms_1m": (
        "One query scans 1M x 4 float32 with numpy (16 MB of memory traffic) and is "
        "memory-bound; on a busy host it slows with the other tenants' traffic. To close "
        "it: a quiet core, or an index (the query only needs the per-class minimum)."),
    "startup_to_ready_s": "Start-up imports numpy, onnxruntime and aiohttp and connects the "
                          "bus: on a busy host each takes longer.",
}
