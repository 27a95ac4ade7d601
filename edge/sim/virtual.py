"""The emulated robot on a virtual clock: what the dataset recorder presses with.

The robot's own drivers run unchanged on it: :class:`edge.hw.arm.DynamixelGripper` and
``DynamixelArm`` over the real :class:`edge.hw.dynamixel.DynamixelBus` (the real
``dynamixel_sdk`` packet handler, every transaction, the stop, the watchdog feed, the close)
built with two parts of its own: its port is an in-process loopback to the same
:class:`~edge.sim.dxl_emulator.DxlEmulator` the daemon talks to over a pty, and its executor
is :class:`VirtualExecutor` (an op runs on the loop when its modelled transaction time has
passed, not on a thread). The tactile source renders the same
:class:`~edge.sim.world.SimWorld` the XELA emulator serves, on the same 125 Hz grid.

Everything runs on :class:`VirtualClockLoop`, an asyncio loop whose clock jumps to the next
timer instead of waiting: a press that takes ten seconds on the robot takes a fraction of one
here, and the same seed gives the same bytes.

What is left different from the daemon on the emulated robot is only transport timing, which
:class:`Transport` models with figures measured on the emulated robot (see each field).
"""

from __future__ import annotations

import asyncio
import logging
import math
import selectors
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self

import numpy as np

from edge.core.config import Config
from edge.core.layout import PadLayout
from edge.hw.arm import DynamixelArm, DynamixelGripper
from edge.hw.contracts import FrameHook, StreamStats, TactileFrame
from edge.hw.dynamixel import BlockingPortHandler, DynamixelBus
from edge.sim.dxl_emulator import DxlEmulator
from edge.sim.skin import SkinDraw
from edge.sim.world import SimWorld, raw_from_width, robot_motors

log = logging.getLogger(__name__)

# xela_server's clock is Unix time; only its advance matters to the client.
SENSOR_EPOCH_S = 1.77e9
SENSOR_MODEL = "XR1944"


class VirtualClockStall(RuntimeError):
    """The virtual loop has nothing scheduled and nothing can wake it: it would wait forever."""


class _VirtualSelector(selectors.DefaultSelector):
    """Polls the real file descriptors (the loop's self-pipe) without blocking; where the loop
    would block until its next timer, the virtual clock jumps there instead."""

    def __init__(self, loop: VirtualClockLoop) -> None:
        super().__init__()
        self._loop = loop

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        ready = super().select(0)
        if ready or timeout == 0:
            return ready
        if timeout is None:
            raise VirtualClockStall("the virtual clock has no timer to jump to: every task "
                                    "waits on something that cannot happen")
        self._loop.advance(timeout)
        return []


class VirtualClockLoop(asyncio.SelectorEventLoop):
    """An asyncio loop on a virtual clock that starts at ``start`` (seconds) and advances
    only when every task waits on a timer. Run it with ``asyncio.Runner(loop_factory=...)``;
    no threads (``to_thread``) or real I/O waits belong on it."""

    def __init__(self, start: float = 0.0) -> None:
        self._virtual_now = float(start)
        super().__init__(selector=_VirtualSelector(self))

    def time(self) -> float:
        return self._virtual_now

    def advance(self, seconds: float) -> None:
        self._virtual_now += max(seconds, 0.0)


# The daemon's stop (one WRITE) as the bench measures it: `make bench`, row `stop_latency_ms`
# (first frame over x_th received -> stop packet at the port, under load), on a quiet host:
# p50 0.22 / p99 0.84 ms (issue 19). The recorder presses with it, so the datasets' presses
# overshoot as the daemon's do.
STOP_LATENCY_P50_S = 0.00022
STOP_LATENCY_P99_S = 0.00084


@dataclass(frozen=True)
class Transport:
    """Transport timing of the emulated robot, which the virtual clock would otherwise make
    zero. Measured on this project's emulated robot (``vt-edge bench``, 'stop latency' and
    'bus' rows; ``vt-edge sim consistency`` reports the daemon's own figures beside the
    dataset's)."""

    # Frame that crosses x_th -> stop packet at the port: log-normal through these two points.
    stop_latency_p50_s: float = STOP_LATENCY_P50_S
    stop_latency_p99_s: float = STOP_LATENCY_P99_S
    # One bus transaction (instruction out, status back) on the pty.
    transaction_s: float = 0.0004
    # xela_server's tick lateness past its 8 ms grid (half-normal sd), then the WebSocket hop
    # to the client (fixed part plus an exponential tail).
    frame_lateness_sd_s: float = 0.0003
    frame_delivery_s: float = 0.0003
    frame_delivery_tail_s: float = 0.0001

    def stop_latency_s(self, rng: np.random.Generator) -> float:
        sigma = math.log(self.stop_latency_p99_s / self.stop_latency_p50_s) / 2.326
        return float(self.stop_latency_p50_s * math.exp(sigma * rng.standard_normal()))


class LoopbackPort(BlockingPortHandler):
    """A ``PortHandler`` whose wire is :meth:`DxlEmulator.transact`: the status packets of an
    instruction are there to read as soon as it is written."""

    def __init__(self, port_name: str, emulator: DxlEmulator, clock: Callable[[], float]) -> None:
        super().__init__(port_name)
        self._emulator = emulator
        self._clock = clock
        self._rx = bytearray()

    def setupPort(self, cflag_baud: int) -> bool:
        self.is_open = True
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True

    def closePort(self) -> None:
        self.is_open = False

    def clearPort(self) -> None:
        self._rx.clear()

    def getBytesAvailable(self) -> int:
        return len(self._rx)

    def writePort(self, packet: Any) -> int:
        data = bytes(packet)
        self.last_write_t = self.write_call_t = self._clock()
        if self.on_write is not None:
            self.on_write(self.last_write_t, data[:8])
        self._rx += self._emulator.transact(data)
        return len(data)

    def readPort(self, length: int) -> bytes:
        out = bytes(self._rx[:length])
        del self._rx[:length]
        return out


class VirtualExecutor:
    """The bus's executor on the virtual clock: no thread; an operation runs on the loop once
    the bus is free and its transaction time has passed; an urgent one (the stop) jumps the
    queue and takes a drawn stop latency."""

    # Nothing runs between the loop's steps: a stop never waits for a transaction in flight
    # (the measured stop latency already holds that wait). The loop's thread is the owner.
    busy = False
    thread_id = native_thread_id = None

    def __init__(self, transport: Transport, rng: np.random.Generator) -> None:
        self._transport = transport
        self._rng = rng
        self._busy_until = 0.0

    def start(self) -> None:
        self._busy_until = 0.0

    async def submit(self, label: str, fn: Callable[[], Any], urgent: bool = False) -> Any:
        now = asyncio.get_running_loop().time()
        if urgent:
            due = now + self._transport.stop_latency_s(self._rng)
        else:
            due = max(now, self._busy_until) + self._transport.transaction_s
            self._busy_until = due
        await asyncio.sleep(due - now)
        return fn()

    async def stop(self, last: Callable[[], None]) -> None:
        last()

    def on_wire(self) -> None:
        pass  # a stop's hand-over waits for nothing here: see ``busy``


class VirtualTactileSource:
    """The XELA stream of ``world`` on the virtual clock: a frame rendered on every tick of
    the 125 Hz grid (late by the server's jitter), received after the WebSocket hop."""

    def __init__(self, world: SimWorld, rate_hz: float, transport: Transport,
                 rng: np.random.Generator, pads: int = 2, stale_timeout_s: float = 0.1,
                 model: str = SENSOR_MODEL) -> None:
        self.stats = StreamStats()
        self._world = world
        self._period_s = 1.0 / rate_hz
        self._transport = transport
        self._rng = rng
        self._models = (model,) * pads
        self.server_models: tuple[str, ...] | None = self._models
        self._seq = int(rng.integers(1000, 100_000))
        self._closed = False
        self._last_recv = -math.inf
        self._stale_timeout_s = stale_timeout_s
        # The contact force behind each delivered frame, by receive time (for benches).
        self.force_at: dict[float, float] = {}

    async def start(self) -> None:
        self._closed = False

    async def close(self) -> None:
        self._closed = True

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.close()

    def set_frame_hook(self, hook: FrameHook | None) -> bool:
        return False  # no queue to skip: each frame goes straight to frames()

    async def wait_first_frame(self, timeout_s: float) -> None:
        return None  # rendered in this process on the next tick: there from the start

    def is_fresh(self) -> bool:
        loop = asyncio.get_running_loop()
        return loop.time() - self._last_recv < self._stale_timeout_s

    async def frames(self) -> AsyncIterator[TactileFrame]:
        loop = asyncio.get_running_loop()
        t = self._transport
        tick = loop.time() + self._rng.uniform(0.0, self._period_s)
        while not self._closed:
            made = tick + abs(self._rng.normal(0.0, t.frame_lateness_sd_s))
            await asyncio.sleep(made - loop.time())
            raw = self._world.frame(made)
            raw.flags.writeable = False
            arrive = made + t.frame_delivery_s + self._rng.exponential(t.frame_delivery_tail_s)
            await asyncio.sleep(arrive - loop.time())
            self._seq += 1
            self.stats.observe(self._seq, SENSOR_EPOCH_S + made)
            self._last_recv = loop.time()
            self.force_at[self._last_recv] = self._world.frame_force_n
            yield TactileFrame(self._seq, SENSOR_EPOCH_S + made, self._last_recv, raw,
                               self._models)
            tick += self._period_s


class VirtualRobot:
    """World, motors, bus, drivers and tactile stream of one press on the virtual clock.

    Use inside a :class:`VirtualClockLoop`: ``async with VirtualRobot(cfg, name, rng) as r``
    connects the bus (torque off, as the daemon's start does); the arm stands at ``above``
    and the gripper at its open width, where a previous press left them.
    """

    def __init__(self, cfg: Config, object_name: str, rng: np.random.Generator, *,
                 skin_draw: SkinDraw | None = None, transport: Transport = Transport(),
                 pads_age_s: float = 0.0) -> None:
        loop = asyncio.get_running_loop()
        clock = loop.time
        bus_cfg = cfg.bus
        self.world = SimWorld(object_name, rng, gripper_id=bus_cfg.gripper_id,
                              skin_draw=skin_draw, layout=PadLayout.of(cfg.sensor),
                              clock=clock, pads_age_s=pads_age_s)
        positions = {mid: float(v) for mid, v in
                     zip(bus_cfg.joint_ids, cfg.poses["above"], strict=True)}
        positions[bus_cfg.gripper_id] = raw_from_width(cfg.press.open_width_m)
        self.dxl = robot_motors(self.world, bus_cfg.joint_ids, positions, clock=clock)
        self.bus = DynamixelBus(bus_cfg, executor=VirtualExecutor(transport, rng),
                                port_handler_factory=lambda name: LoopbackPort(
                                    name, self.dxl, clock),
                                clock=clock, exclusive=False)
        self.gripper = DynamixelGripper(self.bus)
        self.arm = DynamixelArm(self.bus, cfg.poses, move_time_s=cfg.runtime.move_time_s)
        self.tactile = VirtualTactileSource(self.world, cfg.sim.sensor_rate_hz, transport, rng,
                                            pads=cfg.sensor.pads,
                                            stale_timeout_s=cfg.sensor.stale_timeout_s,
                                            model=cfg.sensor.model)

    async def __aenter__(self) -> Self:
        await self.bus.connect()
        await self.tactile.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.tactile.close()
        await self.bus.close()
