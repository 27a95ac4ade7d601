"""The load of ``vt-edge bench``: the processes around the daemon, and the work put on it.

On a robot the XELA server, the motors, the VLM and whoever scrapes ``/metrics`` are other
processes (or machines), so the bench runs each of them in its own process, never on the
daemon's event loop: ``python -m edge.bench.load ROLE`` with ROLE

- ``robot``: the emulated robot (:class:`~edge.sim.robot.SimRobot`), plus the contact force
  behind every tactile frame it sends, by sequence number (``GET /force?seq=N``), so the
  bench can read the force at the frame that crossed ``x_th``;
- ``vlm``: a slow :class:`~edge.sim.fake_vlm.FakeVLM` that also tells when each request
  arrived on the monotonic clock (``GET /received``), for the trigger-to-VLM overhead;
- ``poll``: polls the daemon's ``/healthz`` and ``/metrics``; prints a summary on SIGTERM.
- ``page``: what an open operator page asks of the daemon (edge/interfaces/http/static/app.js): the
  page, both event streams (``/v1/tactile`` at 30 Hz, ``/v1/events``), ``/healthz`` each
  second, the last episodes every 5 s and each new episode's trace and photo; prints the
  frames and requests it got on SIGTERM.
- ``floor``: the floor of the stop latency, the minimal loop a new user would write: an
  asyncio client (aiohttp, as the daemon's) receives the same ``xela_server`` frames,
  parses each (``json.loads``, the words into numpy), takes the norm against the first frame
  and writes a 16-byte WRITE Goal Position packet to a pseudo-terminal from the loop
  thread; every frame counts as crossing, so each is a sample of receive -> the write call
  (and -> the call returned). Prints every sample on SIGTERM.

Each prints one JSON line on stdout once it serves (its addresses), then runs until SIGTERM;
:class:`Helper` starts one and reads that line. ``time.monotonic`` is CLOCK_MONOTONIC, shared
by every process on the host, so times taken there compare directly with the daemon's.

The work put on the daemon itself: :func:`big_jpeg` (the camera-like still its VLM client
sends) and :func:`encode_for` (the encoder, run in the daemon's compute process). The compute
worker imports this module for :func:`encode_for`, so aiohttp is imported only where the
helper roles serve.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import logging
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from edge.bench.settings import HELPER_START_S, ROOT
from edge.core.tasks import cancel_and_wait

if TYPE_CHECKING:
    from aiohttp import web

log = logging.getLogger(__name__)

FORCE_TRACE_FRAMES = 1 << 16  # ~9 min of frames at 125 Hz
ROBOT_SWITCH_INTERVAL_S = 0.0002


# --------------------------------------------------------------------------------------
# The bench's side: a helper process, the work put on the daemon


class Helper:
    """One helper process (a ROLE of this module): its announcement line, then SIGTERM to stop."""

    def __init__(self, *args: str) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, "-m", "edge.bench.load", *args],
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


def encode_for(ref: Any, seconds: float) -> int:
    """The encoder load, in the compute process: encode and top-k back to back."""
    from edge.runtime.compute import model_for

    model = model_for(ref)
    x = np.random.default_rng(1).normal(0, 2e-3, (25, 96)).astype(np.float32)
    n, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        model.topk(model.encode(x)[0], 3)
        n += 1
    return n


# --------------------------------------------------------------------------------------
# The helper processes' side


class ForceTrace:
    """Wraps ``SimWorld.frame``: the i-th frame rendered is the emulator's sequence number i
    (``XelaServerEmulator`` numbers frames from 1, one per rendered frame)."""

    def __init__(self, world: Any, capacity: int = FORCE_TRACE_FRAMES) -> None:
        self._world = world
        self._frame = world.frame
        self.capacity = capacity
        self.t = np.zeros(capacity)
        self.force_n = np.zeros(capacity)
        self.count = 0

    def frame(self, t: float) -> np.ndarray:
        raw = self._frame(t)
        self.count += 1
        i = self.count % self.capacity
        self.t[i] = t
        self.force_n[i] = self._world.frame_force_n
        return raw

    def at(self, seq: int) -> dict[str, float] | None:
        if not (0 < seq <= self.count and seq > self.count - self.capacity):
            return None
        i = seq % self.capacity
        return {"seq": seq, "t": float(self.t[i]), "force_n": float(self.force_n[i])}


async def _control_app(routes: list[web.RouteDef]) -> tuple[web.AppRunner, str]:
    from aiohttp import web

    app = web.Application()
    app.add_routes(routes)
    runner = web.AppRunner(app, access_log=None, handle_signals=False)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = runner.addresses[0][1]
    return runner, f"http://127.0.0.1:{port}"


async def _until_signal(announce: dict[str, Any],
                        on_stop: Callable[[], Awaitable[None]] | None = None) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    print(json.dumps(announce), flush=True)
    await stop.wait()
    if on_stop is not None:
        await on_stop()


async def _robot(args: argparse.Namespace) -> None:
    from aiohttp import web

    from edge.core.config import Config, load_config
    from edge.sim.robot import SimRobot

    niced = None
    if args.nice:
        # The emulated motors and pads stand in for hardware, which never waits for a CPU:
        # on a shared box, favour them (threads started from here on inherit it).
        try:
            niced = os.nice(args.nice)
        except OSError as exc:
            log.warning("cannot renice the emulated robot by %d: %s", args.nice, exc)
    # Its Dynamixel thread must answer while the XELA loop steps the physics: a short GIL
    # switch interval keeps the emulated bus's reply time close to hardware's.
    sys.setswitchinterval(ROBOT_SWITCH_INTERVAL_S)
    cfg = load_config(args.config) if args.config else Config()
    robot = SimRobot(args.object, args.seed, rate_hz=cfg.sim.sensor_rate_hz, cfg=cfg)
    trace = ForceTrace(robot.world)
    robot.world.frame = trace.frame  # the XELA emulator renders through the trace

    async def force(request: web.Request) -> web.Response:
        try:
            seq = int(request.query["seq"])
        except (KeyError, ValueError):
            return web.json_response({"error": "give ?seq=N"}, status=400)
        found = trace.at(seq)
        if found is None:
            return web.json_response({"error": f"seq {seq} not in the trace"}, status=404)
        return web.json_response(found)

    async with robot:
        runner, url = await _control_app([web.get("/force", force)])
        try:
            await _until_signal({"xela_url": robot.xela.url, "dxl_port": robot.dxl.port,
                                 "control_url": robot.control_url, "bench_url": url,
                                 "nice": niced})
        finally:
            await runner.cleanup()


async def _vlm(args: argparse.Namespace) -> None:
    from aiohttp import web

    from edge.sim.fake_vlm import FakeRequest, FakeVLM

    arrivals: list[FakeRequest] = []

    def on_request(rec: FakeRequest) -> None:
        arrivals.append(rec)
        # Keep memory flat under a long load: images are not needed afterwards.
        rec.images, rec.raw, rec.body = [], b"", None

    fake = FakeVLM(model="fake-vlm", latency_s=args.latency_s, on_request=on_request)

    async def received(request: web.Request) -> web.Response:
        return web.json_response([
            {"t": rec.received_at, "candidates": rec.candidates, "status": rec.status,
             "error": rec.error} for rec in arrivals])

    async with fake:
        runner, url = await _control_app([web.get("/received", received)])
        try:
            await _until_signal({"base_url": fake.base_url, "bench_url": url})
        finally:
            await runner.cleanup()


async def _poll(args: argparse.Namespace) -> None:
    import aiohttp

    paths = ("/healthz", "/metrics")
    stats: dict[str, Any] = {"requests": 0, "errors": 0, "latency_ms": []}
    period = 1.0 / args.hz

    async def loop() -> None:
        timeout = aiohttp.ClientTimeout(total=5.0)
        async with aiohttp.ClientSession(timeout=timeout) as http:
            i = 0
            next_t = time.monotonic()
            while True:
                t0 = time.monotonic()
                try:
                    async with http.get(args.url + paths[i % 2]) as resp:
                        await resp.read()
                        # /healthz answers 503 while the sensor is stale: still an answer.
                        if resp.status not in (200, 503):
                            stats["errors"] += 1
                except (aiohttp.ClientError, TimeoutError):
                    stats["errors"] += 1
                stats["requests"] += 1
                stats["latency_ms"].append(1e3 * (time.monotonic() - t0))
                i += 1
                next_t += period
                await asyncio.sleep(max(0.0, next_t - time.monotonic()))

    task = asyncio.create_task(loop())

    async def on_stop() -> None:
        await cancel_and_wait(task)
        lat = stats.pop("latency_ms")
        stats["latency_ms_p50"] = float(np.median(lat)) if lat else None
        stats["latency_ms_max"] = float(np.max(lat)) if lat else None
        print(json.dumps(stats), flush=True)

    await _until_signal({"polling": args.url}, on_stop)


# What the operator page polls, and how often (edge/interfaces/http/static/app.js).
PAGE_HEALTH_S = 1.0
PAGE_EPISODES_S = 5.0


async def _page(args: argparse.Namespace) -> None:
    import aiohttp

    stats: dict[str, Any] = {"tactile_frames": 0, "events": 0, "requests": 0, "errors": 0}
    seen: set[str] = set()

    async def stream(http: aiohttp.ClientSession, path: str, key: str) -> None:
        async with http.get(args.url + path) as resp:
            async for line in resp.content:
                if line.startswith(b"data: "):
                    stats[key] += 1

    async def get(http: aiohttp.ClientSession, path: str) -> Any:
        stats["requests"] += 1
        try:
            async with http.get(args.url + path) as resp:
                body = await resp.read()
                if resp.status >= 500 and path != "/healthz":
                    stats["errors"] += 1
                return json.loads(body) if resp.content_type == "application/json" else None
        except (aiohttp.ClientError, TimeoutError, ValueError):
            stats["errors"] += 1
            return None

    async def every(period_s: float, fn: Callable[[], Awaitable[None]]) -> None:
        while True:
            await fn()
            await asyncio.sleep(period_s)

    async def episodes(http: aiohttp.ClientSession) -> None:
        for ep in (await get(http, "/v1/episodes?limit=8") or {}).get("episodes", []):
            if ep.get("id") not in seen:
                seen.add(ep["id"])
                await get(http, f"/v1/episodes/{ep['id']}/trace")
                await get(http, f"/v1/episodes/{ep['id']}/image")

    http = aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=None, sock_read=30))
    await get(http, "/")
    tasks = [asyncio.create_task(stream(http, "/v1/tactile", "tactile_frames")),
             asyncio.create_task(stream(http, "/v1/events", "events")),
             asyncio.create_task(every(PAGE_HEALTH_S, lambda: get(http, "/healthz"))),
             asyncio.create_task(every(PAGE_EPISODES_S, lambda: episodes(http)))]
    t0 = time.monotonic()

    async def on_stop() -> None:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await http.close()
        stats["seconds"] = time.monotonic() - t0
        print(json.dumps(stats), flush=True)

    await _until_signal({"page": args.url}, on_stop)


# The floor's stop packet: WRITE Goal Position (116) = 2048 to motor 15, 16 bytes with its CRC
# (edge.sim.dxl_emulator.encode_packet builds the same).
FLOOR_PACKET = bytes.fromhex("fffffd000f09000374000008000096c9")


def _floor_words(sensor: dict[str, Any]) -> np.ndarray:
    values = sensor.get("integer")
    if values is None:
        values = sensor["data"]
    if isinstance(values, str):
        return np.frombuffer(bytes.fromhex(values.replace(",", "")), dtype=">u2")
    return np.asarray(values)


async def _floor(args: argparse.Namespace) -> None:
    import tty

    import aiohttp

    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    loop = asyncio.get_running_loop()
    # The pty's other end is drained after each write, as the emulated motors drain theirs.
    loop.add_reader(master, lambda: os.read(master, 4096))
    samples: list[tuple[float, float, float]] = []

    async def run() -> None:
        tare = None
        async with aiohttp.ClientSession() as http, http.ws_connect(args.url) as ws:
            while True:
                msg = await ws.receive()
                t0 = time.monotonic()
                if msg.type != aiohttp.WSMsgType.TEXT:
                    return
                frame = json.loads(msg.data)
                if frame.get("message") == "Welcome":
                    continue
                raw = np.concatenate([_floor_words(frame[k]) for k in ("1", "2")])
                raw = raw.astype(np.float64)
                if tare is None:
                    tare = raw
                if np.linalg.norm(raw - tare) / 65536.0 >= 0.0:  # every frame "crosses"
                    t_call = time.monotonic()
                    os.write(slave, FLOOR_PACKET)
                    samples.append((t0, t_call - t0, time.monotonic() - t0))

    task = asyncio.create_task(run())

    async def on_stop() -> None:
        await cancel_and_wait(task)
        print(json.dumps({"samples": samples}), flush=True)

    await _until_signal({"floor": args.url}, on_stop)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m edge.bench.load", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="role", required=True)
    p = sub.add_parser("robot")
    p.add_argument("--config", default=None)
    p.add_argument("--object", default="stainless_cube")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--nice", type=int, default=0, help="renice by this (negative: favour)")
    p = sub.add_parser("vlm")
    p.add_argument("--latency-s", type=float, default=1.0)
    p = sub.add_parser("poll")
    p.add_argument("--url", required=True)
    p.add_argument("--hz", type=float, default=10.0)
    p = sub.add_parser("page")
    p.add_argument("--url", required=True)
    p = sub.add_parser("floor")
    p.add_argument("--url", required=True, help="the xela_server's WebSocket URL")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="bench-" + args.role + " %(levelname)s %(name)s: %(message)s")
    role = {"robot": _robot, "vlm": _vlm, "poll": _poll, "page": _page,
            "floor": _floor}[args.role]
    asyncio.run(role(args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
