"""``vt-edge doctor``'s host timing: this computer measured for a few seconds as the daemon
runs on it.

On the daemon's own event loop (:func:`edge.app.new_event_loop`), in a thread of its
own, for ``duration_s``: the daemon's 125 Hz sampler (:class:`edge.runtime.sensor.Sampler`)
records how late each tick wakes up (its period error), while frames arrive on a loopback
socket at the same rate and every ``STOP_EVERY_FRAMES``-th is answered as the press answers
the one that crosses ``x_th``: the gripper's stop through the real bus driver
(:meth:`DynamixelGripper.stop_now`, a Goal Position WRITE from the gripper's last state, read
after every second frame as the press reads it), to an emulated motor on a pseudo-terminal.
The frame-to-stop time runs from the frame's send to the stop packet's write call. With
``[runtime] realtime = true`` the loop and bus threads get the daemon's real-time
scheduling meanwhile; without it, whether the host would allow it is tried on a thread that
ends at once. Nothing touches the robot's own bus.
"""

from __future__ import annotations

import asyncio
import os
import socket
import struct
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from edge.app import new_event_loop
from edge.core.config import Config
from edge.hw.arm import DynamixelGripper
from edge.hw.dynamixel import DynamixelBus
from edge.runtime.realtime import Realtime
from edge.runtime.ring import FrameRing
from edge.runtime.sensor import Sampler
from edge.sim.dxl_emulator import DxlEmulator

# How long the host is measured: a few hundred sampler ticks and a hundred stops.
MEASURE_S = 3.0
# The sampler's and the frames' rate (the XELA stream's, the model's grid).
RATE_HZ = 125.0
# One stop per this many frames: the gripper's state read in between (every second frame)
# is fresh and settled, as before a press's stop.
STOP_EVERY_FRAMES = 5
# The press's stop squeeze (raw counts), as configs ship it; the goal is what is timed, not
# where it lands.
SQUEEZE_RAW = 2
_STAMP = struct.Struct("=d")


@dataclass(frozen=True)
class HostTiming:
    """What :func:`measure` saw; times in seconds."""

    duration_s: float
    ticks: int
    missed_ticks: int
    late_p50_s: float
    late_p99_s: float
    late_max_s: float
    stops: int
    stop_p50_s: float
    stop_p99_s: float
    stop_max_s: float
    # Whether the loop and bus threads ran real-time ([runtime] realtime = true, granted).
    realtime_applied: bool
    # Why the host refuses SCHED_FIFO at the configured priority; None: it allows it.
    realtime_refused: str | None


def measure(cfg: Config, duration_s: float = MEASURE_S) -> HostTiming:
    """Blocking: the measurement on an event loop of its own (call it from a thread)."""
    with asyncio.Runner(loop_factory=new_event_loop) as runner:
        return runner.run(_measure(cfg, duration_s))


def realtime_refusal(priority: int) -> str | None:
    """Why SCHED_FIFO at ``priority`` is refused here, or None; tried on a short-lived thread
    so that nothing else changes."""
    refused: list[str] = []

    def attempt() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as exc:
            refused.append(exc.strerror or str(exc))

    probe = threading.Thread(target=attempt, name="realtime-probe")
    probe.start()
    probe.join()
    return refused[0] if refused else None


async def _measure(cfg: Config, duration_s: float) -> HostTiming:
    bc = cfg.bus
    emulator = DxlEmulator((*bc.joint_ids, bc.gripper_id)).start()
    bus = DynamixelBus(replace(bc, port=emulator.port))
    realtime = None
    applied = False
    try:
        await bus.connect()
        gripper = DynamixelGripper(bus)
        loop_thread = threading.get_native_id()
        if cfg.runtime.realtime:
            realtime = Realtime(cfg.runtime.realtime_priority, cfg.runtime.realtime_cpu,
                                lambda: [loop_thread, bus.native_thread_id or 0])
            applied = realtime.enable()
        lateness, stops, missed, ticks = await _run(gripper, duration_s)
    finally:
        if realtime is not None:
            realtime.disable()
        await bus.close()
        emulator.stop()
    late = np.array(lateness or [0.0])
    stop = np.array(stops or [0.0])
    return HostTiming(
        duration_s, ticks, missed, float(np.percentile(late, 50)),
        float(np.percentile(late, 99)), float(late.max()), len(stops),
        float(np.percentile(stop, 50)), float(np.percentile(stop, 99)), float(stop.max()),
        applied,
        realtime_refusal(cfg.runtime.realtime_priority))


async def _run(gripper: DynamixelGripper,
               duration_s: float) -> tuple[list[float], list[float], int, int]:
    """(sampler lateness per tick, frame-to-stop per stop, missed ticks, ticks)."""
    ring = FrameRing(1, 256)
    sampler = Sampler(ring, RATE_HZ)
    lateness: list[float] = []
    sampler.on_tick = lambda _now, late: lateness.append(late)
    stops: list[float] = []
    trace_due = asyncio.Event()
    ours, theirs = socket.socketpair()
    done = threading.Event()
    sender = threading.Thread(target=_send_frames, args=(theirs, done), name="frames",
                              daemon=True)
    reader, writer = await asyncio.open_connection(sock=ours)
    zero = np.zeros(1, dtype=np.uint16)

    async def frames() -> None:
        n = 0
        while True:
            (sent,) = _STAMP.unpack(await reader.readexactly(_STAMP.size))
            n += 1
            ring.push(zero, time.monotonic(), sent, n)
            if n % STOP_EVERY_FRAMES == 0:
                stop = await gripper.stop_now(SQUEEZE_RAW)
                stops.append(stop.t_sent - sent)
            elif n % 2 == 0:
                trace_due.set()

    async def trace() -> None:
        while True:
            await trace_due.wait()
            trace_due.clear()
            await gripper.state()

    tasks = [asyncio.create_task(c) for c in (sampler.run(), frames(), trace())]
    sender.start()
    try:
        await asyncio.sleep(duration_s)
    finally:
        done.set()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        sender.join()
        writer.close()
        theirs.close()
    return lateness, stops, sampler.stats.missed_ticks, sampler.stats.ticks


def _send_frames(sock: socket.socket, done: threading.Event) -> None:
    """Each frame is its send time, on an absolute RATE_HZ grid, as xela_server sends."""
    period = 1.0 / RATE_HZ
    deadline = time.monotonic()
    while not done.wait(max(0.0, deadline - time.monotonic())):
        try:
            sock.sendall(_STAMP.pack(time.monotonic()))
        except OSError:
            return
        deadline += period
