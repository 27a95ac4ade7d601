"""The runtime phase: the daemon's runtime in this process against the emulated robot, with
and without load.

The daemon as ``vt-edge run`` assembles it (:func:`edge.app.assemble`: real drivers,
HTTP API, episode store, VLM client, compute process) runs on the daemon's own event loop in
this process, against the emulated robot, which runs in its own process, as do a slow fake
VLM and a poller of ``/healthz`` and ``/metrics`` (:mod:`edge.bench.load`). A few
presses first with no extra load (the software overhead, trigger to VLM request), then the
load: the VLM client sends large camera stills to the slow VLM, the encoder runs over and
over in the daemon's compute process (where its own presses are encoded and its images
prepared), the API is polled. Under it, presses alternate between the three controllers of
:mod:`edge.bench.controllers`; then, still under it, production presses with the
loop and bus threads at real-time priority on a CPU of their own (``Daemon.realtime``).
The sampler's lateness is recorded throughout.

The floor of the stop latency runs beside it all, in a process of its own: the minimal loop
a new user would write (``load`` role ``floor``) on the same frames, host and load; each
phase's figure takes its samples from the phase's time window. Each production stop is
split into its parts (:class:`StopParts`).

Every press is triggered over the HTTP API; the bench reads the daemon only through its
public hooks (:mod:`edge.bench.probes`); its press controller is the bench's
(``assemble(..., controller_factory=BenchController)``), switched between presses.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from edge.bench.controllers import BenchController
from edge.bench.figures import figure, finish, ratio_figure, stats, target
from edge.bench.host import cpu_snapshot, cpu_times_since
from edge.bench.load import Helper, big_jpeg, encode_for
from edge.bench.probes import (
    HotPathCPU,
    SamplerWindow,
    StopParts,
    first_crossing,
    instrument_parse,
    instrument_port,
    stop_parts,
)
from edge.bench.report import READING, load_text
from edge.bench.results import PhaseResult, progress
from edge.bench.settings import (
    CONTROLLER_TEXT,
    CONTROLLERS,
    CUBE,
    MODELS,
    OBJECTS,
    SIM_CONFIG,
    Settings,
)
from edge.core.progress import Progress
from edge.runtime.domain import PressState

# The emulated robot stands in for hardware, which never waits for a CPU: it runs favoured
# (nice -10, where allowed) so that a busy host starves the daemon, not the motors.
ROBOT_NICE = -10
# A press that fails (on a starved host the emulated bus can time out) is tried again, up
# to this many times, so that every controller gets its presses; failures are counted.
PRESS_ATTEMPTS = 3
PRESS_TIMEOUT_S = 60.0
READY_TIMEOUT_S = 30.0
# Operator pages kept open during the pages phase.
PAGES = 2
# Targets of the stop (issue: the stop at the floor): p99 under the load, and the median
# at most this many times the floor's.
STOP_P99_MS = 1.0
FLOOR_RATIO_P50 = 2.0
FLOOR_TEXT = ("the floor: a minimal asyncio client (aiohttp) receiving the same xela_server "
              "frames, parsing each (json, numpy), taking the norm and writing a 16-byte "
              "packet to a pty from the loop thread; receive -> the write call, every frame")


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
    parts: StopParts | None = None  # the production stop split into its parts
    fast: bool | None = None  # one WRITE (False: it read Present Position first)
    realtime: bool = False  # loop and bus threads at real-time priority
    from_send_ms: float | None = None  # the server sent that frame -> stop written
    force_at_cross_n: float | None = None
    peak_force_n: float | None = None
    overshoot_n: float | None = None
    press_s: float | None = None  # 'above' entered -> 'idle' entered
    pre_press_ms: float | None = None  # trigger -> 'above'
    # 'above' entered -> the model's crop window complete (the stop + its last sample's
    # time): the press's own part of the way to the VLM question.
    to_window_s: float | None = None
    t_vlm: float | None = None
    overhead_ms: float | None = None
    message: str = ""


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
        self.pages_stats: dict[str, Any] = {}
        self.page_stats: list[dict[str, Any]] = []
        self.rt_stats: dict[str, Any] = {}
        self.rt_applied = False
        # Each phase's time window (monotonic), to take the floor's samples from.
        self.windows: dict[str, tuple[float, float]] = {}
        self.floor_samples: list[tuple[float, float, float]] = []
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

        from edge.app import assemble, running

        cfg = self.config()
        async with assemble(cfg, controller_factory=BenchController) as daemon:
            runtime, compute = daemon.runtime, daemon.compute
            self.compute = compute
            worker = compute.pid()
            if worker is not None:
                self.pids["compute worker"] = worker
            self.port_writes = instrument_port(daemon.devices.bus)
            self.parsed = instrument_parse(daemon.devices.tactile)
            self.cpu = HotPathCPU(daemon.devices.bus)
            daemon.devices.tactile.on_received = self.cpu.arrived
            self.bus = daemon.devices.bus
            self.realtime = daemon.realtime
            self.runtime = runtime
            assert isinstance(runtime.press, BenchController)
            self.controller = runtime.press
            self.controller.measure_cpu(self.cpu)
            async with running(daemon, READY_TIMEOUT_S):
                self.api_url = f"http://127.0.0.1:{daemon.api.port}"
                floor = await asyncio.to_thread(Helper, "floor", "--url",
                                                self.robot["xela_url"])
                try:
                    async with aiohttp.ClientSession() as http:
                        self.http = http
                        await self._quiet_phase()
                        await self._pages_phase()
                        await self._loaded_phase(cfg, runtime.model)
                        await self._vlm_arrivals()
                finally:
                    out = await asyncio.to_thread(floor.stop)
                    with contextlib.suppress(ValueError, IndexError, KeyError):
                        self.floor_samples = json.loads(out.strip().splitlines()[-1])["samples"]

    # ----- one press

    async def _press(self, phase: str, name: str, obj: str) -> PressRecord:
        http, runtime = self.http, self.runtime
        ctl = self.controller
        async with http.post(f"{self.robot['control_url']}/object", json={"name": obj}) as r:
            r.raise_for_status()
        ctl.use(name)
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
                          message=outcome.message, realtime=self.realtime.active)
        states = dict(outcome.states)
        if PressState.ABOVE in states and PressState.IDLE in states:
            rec.press_s = states[PressState.IDLE] - states[PressState.ABOVE]
            rec.pre_press_ms = 1e3 * (states[PressState.ABOVE] - t_trigger)
            if outcome.t_stop is not None:
                rec.to_window_s = (outcome.t_stop + ctl.window.last_sample_s
                                   - states[PressState.ABOVE])
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
            stop = self.bus.last_stop
            if stop is not None and stop.t_write_call == outcome.t_stop:
                rec.fast = stop.fast
                # The parts of a stop made on the first frame over x_th (a ticked
                # controller's frame waited for its tick: not a part of the path).
                stopped_on = outcome.t_stop - (outcome.stop_latency_s or 0.0)
                if (name == "per_frame" and outcome.t_check is not None
                        and abs(stopped_on - t_first) < 1e-6):
                    rec.parts = stop_parts(stop, t_first, outcome.t_check,
                                           self.parsed.get(seq))
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
            progress(f"  press failed ({name}, {obj}): {rec.result}: {rec.message}")
        return rec

    async def _quiet_phase(self) -> None:
        progress(f"runtime: {self.s.quiet_presses} presses with no extra load (overhead)")
        window = SamplerWindow(self.runtime.sampler)
        t0 = time.monotonic()
        try:
            with Progress("bench quiet", self.s.quiet_presses, "presses") as bar:
                for i in range(self.s.quiet_presses):
                    rec = await self._press_ok("quiet", "per_frame", OBJECTS[i % len(OBJECTS)])
                    bar.update(1, f"{rec.result}, stop latency {_fmt(rec.stop_latency_ms)} ms, "
                                  f"press {_fmt(rec.press_s)} s")
        finally:
            self.quiet_stats = window.close()
            self.windows["quiet"] = (t0, time.monotonic())

    async def _pages_phase(self) -> None:
        """The quiet presses again, with two operator pages open (each its own process, as
        a browser is): what watching the robot costs the 125 Hz path."""
        progress(f"runtime: {self.s.quiet_presses} presses with {PAGES} operator pages open")
        pages = [await asyncio.to_thread(Helper, "page", "--url", self.api_url)
                 for _ in range(PAGES)]
        window = SamplerWindow(self.runtime.sampler)
        try:
            await asyncio.sleep(1.0)  # the pages load and their streams start
            with Progress("bench two pages", self.s.quiet_presses, "presses") as bar:
                for i in range(self.s.quiet_presses):
                    rec = await self._press_ok("pages", "per_frame", OBJECTS[i % len(OBJECTS)])
                    bar.update(1, f"{rec.result}, stop latency {_fmt(rec.stop_latency_ms)} ms")
        finally:
            self.pages_stats = window.close()
            outs = await asyncio.gather(*(asyncio.to_thread(p.stop) for p in pages))
            self.page_stats = [json.loads(out.strip().splitlines()[-1]) for out in outs
                               if out.strip()]

    async def _loaded_phase(self, cfg: Any, model: Any) -> None:
        from edge.app import vlm_config
        from edge.core.errors import EdgeError
        from edge.vlm.client import OpenAIVLM

        s = self.s
        runtime = self.runtime
        image = await asyncio.to_thread(big_jpeg, s.image_px)
        progress(f"runtime: load on: {s.load_vlm_clients} VLM clients sending a "
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
        window: SamplerWindow | None = SamplerWindow(runtime.sampler)
        pids = dict(self.pids, **({"poller": poller.proc.pid} if poller else {}))
        cpu0 = cpu_snapshot(pids)
        t0 = time.monotonic()
        cpu: dict[str, float] = {}
        sampled: dict[str, Any] = {}
        tasks = [asyncio.create_task(vlm_load(), name=f"bench-vlm-load-{i}")
                 for i in range(s.load_vlm_clients)]
        tasks.append(asyncio.create_task(encode_load(), name="bench-encode-load"))
        try:
            await asyncio.sleep(1.0)  # let the load settle in
            total = s.presses * len(CONTROLLERS)
            with Progress("bench under load", total, "presses") as bar:
                for i in range(s.presses):
                    obj = OBJECTS[i % len(OBJECTS)]
                    for name in CONTROLLERS:
                        rec = await self._press_ok("load", name, obj)
                        bar.update(1, f"{name}, {obj}: {rec.result}, stop latency "
                                      f"{_fmt(rec.stop_latency_ms)} ms, overshoot "
                                      f"{_fmt(rec.overshoot_n, 3)} N")
            left = s.load_min_s - (time.monotonic() - t0)
            if left > 0:
                progress(f"  load continues {left:.0f} s more (sampler window)")
                await asyncio.sleep(left)
            cpu = cpu_times_since(cpu0)
            duration = time.monotonic() - t0
            sampled, window = window.close(), None
            self.windows["load"] = (t0, time.monotonic())
            await self._realtime_presses()
        finally:
            if window is not None:
                cpu = cpu_times_since(cpu0)
                duration = time.monotonic() - t0
                sampled = window.close()
            stop.set()
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
        progress(f"runtime: load off after {duration:.0f} s: {counters['vlm_asks']} VLM asks "
                 f"({counters['vlm_errors']} failed), {counters['encodes']} encodes, "
                 f"{polled.get('requests', '?')} API polls ({polled.get('errors', '?')} "
                 "failed)")

    async def _realtime_presses(self) -> None:
        """Production presses under the same load with the loop and bus threads at
        real-time priority on a CPU of their own (the daemon's [runtime] realtime)."""
        s = self.s
        rt = self.realtime
        self.rt_applied = rt.enable()
        state = (f"SCHED_FIFO {rt.priority} on CPU {rt.held_cpu}" if self.rt_applied
                 else "REFUSED by this host: the presses run without it")
        progress(f"runtime: {s.rt_presses} presses under the load, real-time scheduling "
                 f"{state}")
        if not self.rt_applied:
            self.notes.append("real-time scheduling was refused on this host (see the log): "
                              "the *_realtime figures ran without it")
        window = SamplerWindow(self.runtime.sampler)
        cpu0 = cpu_snapshot({})
        t0 = time.monotonic()
        try:
            with Progress("bench real-time", s.rt_presses, "presses") as bar:
                for i in range(s.rt_presses):
                    rec = await self._press_ok("load_rt", "per_frame", OBJECTS[i % len(OBJECTS)])
                    bar.update(1, f"{rec.object}: {rec.result}, stop latency "
                                  f"{_fmt(rec.stop_latency_ms)} ms")
            left = s.rt_min_s - (time.monotonic() - t0)
            if left > 0:
                progress(f"  real-time window continues {left:.0f} s more (sampler window)")
                await asyncio.sleep(left)
        finally:
            cpu = cpu_times_since(cpu0)
            rt.disable()
            self.rt_stats = window.close()
            self.rt_stats["loop_thread"] = {k: v for k, v in cpu.items()
                                            if k.startswith("loop_thread")}
            self.windows["load_rt"] = (t0, time.monotonic())

    def _cpu_figures(self) -> dict[str, Any]:
        """The hot path's thread CPU time (:class:`HotPathCPU`), under the load and without."""
        def within(window: str, t: float) -> bool:
            t0, t1 = self.windows.get(window, (0.0, 0.0))
            return t0 <= t <= t1

        frames = {w: [us for t, us in self.cpu.frames if within(w, t)] for w in ("quiet", "load")}
        stops = {w: [s for s in self.cpu.stops if within(w, s["t"]) and not s["in_flight"]]
                 for w in ("quiet", "load")}
        in_flight = sum(s["in_flight"] for s in self.cpu.stops if within("load", s["t"]))
        return {
            "frame_check_cpu_us": figure(
                frames["load"], "us", None, no_load=stats(frames["quiet"]),
                what="thread CPU time per frame on the loop thread, XELA message received -> "
                     "threshold checked, while the production controller watched it (closing, "
                     "holding), under load"),
            "stop_cpu_us": figure(
                [s["loop_us"] + s["bus_us"] for s in stops["load"]], "us", None,
                loop_us=stats([s["loop_us"] for s in stops["load"]]),
                bus_us=stats([s["bus_us"] for s in stops["load"]]),
                no_load=stats([s["loop_us"] + s["bus_us"] for s in stops["quiet"]]),
                in_flight_stops=in_flight,
                what="thread CPU time per production stop, frame received -> stop packet "
                     "written: the loop thread to the hand-over plus the bus thread to the "
                     "write call, under load (stops with a transaction in flight left out)"),
        }

    def _floor_in(self, window: str) -> list[tuple[float, float]]:
        """The floor's latencies (ms) of the frames received within a phase's window: to
        the write call, and to its return."""
        t0, t1 = self.windows.get(window, (0.0, 0.0))
        return [(1e3 * call, 1e3 * ret) for t, call, ret in self.floor_samples
                if t0 <= t <= t1]

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
            if rec.t_vlm is not None and rec.to_window_s is not None:
                rec.overhead_ms = 1e3 * (rec.t_vlm - rec.t_trigger - rec.to_window_s)
        missing = [m for m, r in wanted.items() if r.t_vlm is None]
        if missing:
            self.notes.append(f"{len(missing)} VLM requests never arrived: {missing[:5]}")

    # ----- figures

    def figures(self) -> dict[str, Any]:
        """Every figure of the phase, group by group, in the report's order."""
        figs = self._sampler_figures()
        figs |= self._stop_figures()
        figs |= self._floor_figures(figs)
        figs |= self._realtime_figures()
        figs |= self._pages_figures()
        figs |= self._controller_figures(figs)
        figs |= self._overhead_figures()
        return figs

    def _sampler_figures(self) -> dict[str, Any]:
        """The 125 Hz sampler's lateness under the load and with none."""
        load = self.load_stats
        late_ms = [1e3 * v for v in load.get("lateness_s", [])]
        return {
            "sampler_period_error_ms": figure(
                late_ms, "ms", target(("p99", "<=", 1.0), ("missed_ticks", "==", 0)),
                missed_ticks=load.get("missed_ticks"), ticks=load.get("ticks"),
                gaps=load.get("gaps"), duration_s=load.get("duration_s"),
                max_gap_ms=load.get("max_interval_ms"),
                what="lateness of each 125 Hz sampler wake-up vs its ideal deadline, under "
                     "load"),
            "sampler_period_error_ms_no_load": _sampler_figure(
                self.quiet_stats,
                "as sampler_period_error_ms, during the presses with no extra load"),
        }

    def _stop_figures(self) -> dict[str, Any]:
        """Each controller's stop latency under the load (its failures in the notes), and
        the production controller's with no load."""
        figs: dict[str, Any] = {}
        loaded = [r for r in self.records if r.phase == "load"]
        for name in CONTROLLERS:
            recs = [r for r in loaded if r.controller == name]
            failed = [f"{r.result}: {r.message}" for r in recs if r.stop_latency_ms is None]
            aborted = [r for r in recs if r.stop_latency_ms is not None and r.result != "ok"]
            # The controller's own crossing frame was a later one: it never saw the first
            # frame over x_th (a ticked check sees only the latest frame at each tick).
            later = [r for r in recs if r.stop_latency_ms is not None
                     and r.controller_latency_ms is not None
                     and r.stop_latency_ms - r.controller_latency_ms > 0.5]
            figs[_stop_key(name)] = figure(
                [r.stop_latency_ms for r in recs], "ms",
                target(("p99", "<=", STOP_P99_MS)) if name == "per_frame" else None,
                controller=CONTROLLER_TEXT[name], failed_presses=len(failed),
                aborted_after_stop=len(aborted), missed_first_crossing=len(later),
                **_stop_detail(recs),
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
            **_stop_detail(quiet),
            from_server_send_ms=stats([r.from_send_ms for r in quiet]),
            what="as stop_latency_ms, with no extra load (the overhead presses)")
        return figs

    def _floor_figures(self, figs: dict[str, Any]) -> dict[str, Any]:
        """The minimal loop's floor, the hot path's CPU time, and the production stop
        (``figs``) against the floor."""
        floor = {name: self._floor_in(name) for name in ("quiet", "load")}
        out: dict[str, Any] = {}
        out["stop_floor_ms"] = figure(
            [lat for lat, _ in floor["load"]], "ms", None,
            to_write_return_ms=stats([ret for _, ret in floor["load"]]),
            what=FLOOR_TEXT + ", under the same load, over the phase of stop_latency_ms")
        out["stop_floor_ms_no_load"] = figure(
            [lat for lat, _ in floor["quiet"]], "ms", None,
            to_write_return_ms=stats([ret for _, ret in floor["quiet"]]),
            what=FLOOR_TEXT + ", over the presses with no extra load")
        out.update(self._cpu_figures())
        out["stop_latency_ratio_floor"] = ratio_figure(
            figs[_stop_key("per_frame")], out["stop_floor_ms"],
            target(("p50", "<=", FLOOR_RATIO_P50)),
            what="stop_latency_ms / stop_floor_ms (statistic by statistic): vtzero's stop "
                 "against the minimal loop, same frames, host and load")
        out["stop_latency_ratio_floor_no_load"] = ratio_figure(
            figs["stop_latency_ms_no_load"], out["stop_floor_ms_no_load"],
            what="stop_latency_ms_no_load / stop_floor_ms_no_load")
        return out

    def _realtime_figures(self) -> dict[str, Any]:
        """The sampler and the production stop under the same load with the loop and bus
        threads at real-time priority."""
        rt = [r for r in self.records if r.phase == "load_rt"]
        applied = "applied" if self.rt_applied else "REFUSED by the host (ran without it)"
        rt_sampler = _sampler_figure(
            self.rt_stats, "as sampler_period_error_ms (the same load), with the loop and bus "
            f"threads at real-time priority on a CPU of their own ({applied}); loop_thread: "
            "its CPU, run-queue wait (cores) and preemptions per second over the window")
        rt_sampler["loop_thread"] = self.rt_stats.get("loop_thread")
        return {
            "sampler_period_error_ms_realtime": finish(
                rt_sampler, target(("p99", "<=", 1.0), ("missed_ticks", "==", 0))),
            "stop_latency_ms_realtime": figure(
                [r.stop_latency_ms for r in rt], "ms", target(("p99", "<=", STOP_P99_MS)),
                controller=CONTROLLER_TEXT["per_frame"], **_stop_detail(rt),
                floor_ms=stats([lat for lat, _ in self._floor_in("load_rt")]),
                what="as stop_latency_ms (the same load), with the loop and bus threads at "
                     f"real-time priority on a CPU of their own ({applied})"),
        }

    def _pages_figures(self) -> dict[str, Any]:
        """The sampler and the stop with operator pages open, and the pages' feed rate."""
        with_pages = [r for r in self.records if r.phase == "pages"]
        return {
            "sampler_period_error_ms_two_pages": _sampler_figure(
                self.pages_stats, f"as sampler_period_error_ms_no_load, with {PAGES} operator "
                "pages open"),
            "stop_latency_ms_two_pages": figure(
                [r.stop_latency_ms for r in with_pages], "ms", None,
                controller=CONTROLLER_TEXT["per_frame"],
                what=f"as stop_latency_ms_no_load, with {PAGES} operator pages open"),
            "operator_page_feed_fps": figure(
                [p["tactile_frames"] / p["seconds"] for p in self.page_stats
                 if p.get("seconds")],
                "frames/s", target(("p50", ">=", 25.0)),
                requests=sum(p.get("requests", 0) for p in self.page_stats),
                errors=sum(p.get("errors", 0) for p in self.page_stats),
                what="live tactile frames each open page received per second (/v1/tactile)"),
        }

    def _controller_figures(self, figs: dict[str, Any]) -> dict[str, Any]:
        """The ticked controllers' stop latencies (``figs``) against the production one's,
        and each controller's force overshoot per object."""
        out: dict[str, Any] = {
            "stop_latency_ratio_loop100": ratio_figure(
                figs[_stop_key("loop100")], figs[_stop_key("per_frame")],
                target(("p50", ">=", 5.0)),
                what="100 Hz loop stop latency / per-frame stop latency (statistic by "
                     "statistic)"),
            "stop_latency_ratio_tick125": ratio_figure(
                figs[_stop_key("tick125")], figs[_stop_key("per_frame")],
                what="125 Hz tick stop latency / per-frame stop latency (statistic by "
                     "statistic)"),
        }
        loaded = [r for r in self.records if r.phase == "load"]
        for obj in OBJECTS:
            for name in CONTROLLERS:
                recs = [r for r in loaded if r.controller == name and r.object == obj]
                out[f"force_overshoot_n_{obj}_{name}"] = figure(
                    [r.overshoot_n for r in recs], "N", None, controller=CONTROLLER_TEXT[name],
                    what=f"peak normal force minus the force at the first frame over x_th "
                         f"(SimWorld), {obj}")
        return out

    def _overhead_figures(self) -> dict[str, Any]:
        """What the daemon adds between the trigger and the VLM request, beyond the press."""
        out: dict[str, Any] = {}
        for phase, key, goal in (("quiet", "overhead_ms", target(("p99", "<=", 20.0))),
                                 ("load", "overhead_ms_under_load", None)):
            recs = [r for r in self.records if r.phase == phase]
            out[key] = figure(
                [r.overhead_ms for r in recs], "ms", goal,
                pre_press_ms_p50=stats([r.pre_press_ms for r in recs])["p50"],
                what="POST /v1/recognize -> VLM request received, minus the press's own "
                     "part of that way ('above' entered -> the model's crop window complete: "
                     "the stop + its last sample's time)" +
                     (", no extra load" if phase == "quiet" else ", under the load"))
        return out


def _stop_key(controller: str) -> str:
    """The figure of ``controller``'s stop latency under the load."""
    return "stop_latency_ms" if controller == "per_frame" else f"stop_latency_ms_{controller}"

def _stop_detail(recs: list[PressRecord]) -> dict[str, Any]:
    """The parts of the production stops among ``recs``, and how many read first."""
    parts = [r.parts for r in recs if r.parts is not None]
    detail: dict[str, Any] = {
        f"{name}_ms": stats([getattr(p, name) for p in parts]) for name in StopParts.NAMES}
    detail["in_flight_stops"] = sum(p.in_flight > 0 for p in parts)
    detail["fallback_stops"] = sum(r.fast is False for r in recs)
    return detail


def _sampler_figure(window: dict[str, Any], what: str) -> dict[str, Any]:
    """The sampler's lateness over one :class:`SamplerWindow` of presses."""
    return figure([1e3 * v for v in window.get("lateness_s", [])], "ms", None,
                  missed_ticks=window.get("missed_ticks"), ticks=window.get("ticks"),
                  duration_s=window.get("window_s"), max_gap_ms=window.get("max_interval_ms"),
                  what=what)


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def runtime_phase(s: Settings, tmp: Path) -> PhaseResult:
    from edge.app import new_event_loop

    progress("starting the emulated robot and the fake VLM (own processes)")
    robot = Helper("robot", "--config", str(SIM_CONFIG), "--object", OBJECTS[0],
                   "--nice", str(ROBOT_NICE))
    if robot.info.get("nice") is None:
        progress(f"  (the emulated robot could not be reniced to {ROBOT_NICE})")
    vlm = None
    try:
        vlm = Helper("vlm", "--latency-s", str(s.vlm_latency_s))
        bench = RuntimeBench(s, robot, vlm, tmp / "state")
        quiet_loggers = [logging.getLogger(n) for n in ("edge", "aiohttp")]
        levels = [lg.level for lg in quiet_loggers]
        for lg in quiet_loggers:
            lg.setLevel(logging.WARNING)
        try:
            # The daemon's own event loop (edge.app.new_event_loop), as `vt-edge run` has.
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
    return PhaseResult(bench.figures(), bench.notes, run={"load": load},
                       raw={"presses": [asdict(r) for r in bench.records]},
                       sections={"The load": load_text(load), "Reading the figures": READING})
