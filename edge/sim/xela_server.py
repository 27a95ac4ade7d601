"""An emulator of XELA's ``xela_server`` on loopback, speaking its WebSocket JSON.

Each client gets the Welcome frame, then one JSON text frame per tick, in the 1.7 dialect
(``data`` hex string, ``calibrated: null``), 1.7.7 (``data`` as a list of ints) or 1.8 (adds
``integer``, ``temp`` in kelvin, ``ups``). A :class:`FrameSource` gives the raw counts, or a
real recording is replayed (:mod:`edge.sim.xela_replay`): its frames at their recorded
times, starting when the first client connects (so it gets the whole recording), from the
first again after the last (``loop``) or then nothing more, the connection left open, as a
server whose sensors went quiet. Faults can be switched at run time to test
the client: silence, a frozen frame, dropped connections, garbage.

Run one by hand: ``python -m edge.sim.xela_server --port 5000 [--replay FILE]``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import enum
import json
import logging
import socket
import time
from typing import Literal, Protocol, Self

import msgspec
import numpy as np
from aiohttp import WSCloseCode, web

from edge.core.layout import PadLayout
from edge.core.tasks import cancel_and_wait
from edge.sim.skin import PadNoise, SkinDraw
from edge.sim.xela_replay import Replay, load_replay

log = logging.getLogger(__name__)

Dialect = Literal["1.7", "1.7.7", "1.8"]
DEFAULT_PORT = 5000
# Frames a slow client may fall behind before it loses the oldest (about 1 s at 125 Hz).
_CLIENT_QUEUE_FRAMES = 128
# Grace for clients to answer our close frame when the emulator stops.
_CLOSE_TIMEOUT_S = 0.5
# A replay this far behind its schedule (a stalled loop) starts its clock again from now
# rather than sending the missed frames in one burst; a shorter delay sends them late.
_REPLAY_MAX_LAG_S = 0.25


class FrameSource(Protocol):
    def frame(self, t: float) -> np.ndarray:
        """(sensors * taxels * 3,) uint16 raw counts for monotonic time ``t``."""
        ...


class IdleSource:
    """Unloaded pads like the XR1944: the simulator's pad model (:mod:`edge.sim.skin`: idle
    offsets per taxel, noise, cross-talk and drift as real pads show them) with no load."""

    def __init__(self, channels: int = 96, *, seed: int = 0, taxels: int = 16) -> None:
        if channels % (taxels * 3):
            raise ValueError(f"{channels} channels is not a whole number of {taxels}-taxel pads")
        rng = np.random.default_rng(seed)
        # Unloaded, the grid's shape makes no difference: one row of taxels per pad.
        self._draw = SkinDraw.draw(rng, PadLayout(channels // (taxels * 3), 1, taxels))
        self._noise = PadNoise(self._draw, rng)
        self._t0: float | None = None

    def frame(self, t: float) -> np.ndarray:
        if self._t0 is None:
            self._t0 = t
        since = t - self._t0
        values = self._draw.offsets + self._draw.drift(since) + self._noise.sample(since)
        return np.clip(np.rint(values), 0, 0xFFFF).astype(np.uint16)


class Fault(enum.Enum):
    NONE = "none"
    SILENT = "silent"  # connections stay open, nothing is sent
    FREEZE = "freeze"  # the last frame is resent unchanged (same seq and time)
    GARBAGE = "garbage"  # non-JSON or wrongly shaped frames instead of data


# What a broken server or link might emit; all of it must be refused by the client.
GARBAGE_FRAMES = (
    "not json {",
    '{"message": 1, "time": 1.0, "1": {"data": "ZZZZ,0000,0000"}}',
    '{"message": 1, "time": 1.0}',
    "[1, 2, 3]",
    '{"message": 1, "time": 1.0, "1": {"data": [70000, -1, 5]}}',
)


def encode_frame(
    seq: int,
    wall_time: float,
    raw: np.ndarray,
    *,
    sensors: int = 2,
    taxels: int = 16,
    model: str = "XR1944",
    dialect: Dialect = "1.8",
    newtons: np.ndarray | None = None,
) -> str:
    """One data frame as ``xela_server`` of ``dialect`` would send it; ``newtons``: the
    ``calibrated`` forces of a calibrated model, else none (the XR1944's)."""
    per = taxels * 3
    frame: dict[str, object] = {"message": seq, "time": wall_time, "sensors": sensors}
    if dialect == "1.8":
        frame |= {"type": "routine", "version": "1.8.0-vtzero-emulator"}
    for i in range(sensors):
        words = raw[i * per : (i + 1) * per]
        ints = words.tolist()
        sensor: dict[str, object] = {
            "time": wall_time,
            "sensor": str(i + 1),
            "model": model,
            "taxels": taxels,
        }
        if dialect == "1.7.7":
            sensor["data"] = ints
        else:
            sensor["data"] = _hex_words(words)
        if dialect == "1.8":
            # XR1944 has no calibration: 1.8 leaves `calibrated` out, 1.7 sends null.
            sensor |= {"integer": ints, "temp": [303.15] * taxels, "ups": [125.0] * taxels}
        else:
            sensor["calibrated"] = None
        if newtons is not None:
            sensor["calibrated"] = np.round(newtons[i * per : (i + 1) * per], 5).tolist()
        frame[str(i + 1)] = sensor
    if dialect == "1.8":
        frame["sendtime"] = time.time()
    # msgspec: 6 us where json.dumps took 57 for the same compact JSON (a float may be written
    # 0.00001 where json writes 1e-05; both are JSON numbers). The emulated robot sends 125
    # of these a second beside the daemon on a test or bench host.
    return _ENCODER.encode(frame).decode()


_ENCODER = msgspec.json.Encoder()


def _hex_words(words: np.ndarray) -> str:
    """``"0A1B,FFFF,..."``: each uint16 as four upper-case hex digits, comma-separated (as
    the 1.8 server writes ``data``): one ``bytes.hex`` with a separator every two bytes,
    not a format call per word."""
    return words.astype(">u2").tobytes().hex(",", 2).upper()


def welcome_frame(sensors: int) -> str:
    return json.dumps({"message": "Welcome", "time": time.time(), "sensors": sensors})


class XelaServerEmulator:
    """A ``xela_server`` stand-in on ``host:port`` (port 0: ephemeral, read ``.port``)."""

    def __init__(
        self,
        source: FrameSource | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        rate_hz: float = 125.0,
        sensors: int = 2,
        taxels: int = 16,
        model: str = "XR1944",
        dialect: Dialect = "1.8",
        replay: Replay | None = None,
        loop: bool = True,
        calibrated: bool = False,
    ) -> None:
        """``calibrated``: send the source's taxel forces (its ``frame_newtons()``) as a
        calibrated model's ``calibrated`` newtons."""
        if not 0 < rate_hz <= 2000:
            raise ValueError(f"rate_hz must be in (0, 2000], got {rate_hz!r}")
        if replay is not None:
            # The recording's layout and timing replace the ones given.
            sensors, taxels = replay.sensors, replay.taxels
        self._source = source or IdleSource(sensors * taxels * 3, taxels=taxels)
        self._replay, self._loop = replay, loop
        self._host, self._port = host, port
        self._period_s = 1.0 / rate_hz
        self._sensors, self._taxels, self._model = sensors, taxels, model
        self._dialect: Dialect = dialect
        self._calibrated = calibrated
        self.fault = Fault.NONE
        self.frames_sent = 0  # data frames produced (each goes to every client)
        self.late_ticks = 0  # ticks skipped because the loop woke more than a period late
        self.replay_laps = 0  # times a replay went through all its frames
        self._first_client = asyncio.Event()
        self._seq = 0
        self._last_text: str | None = None
        self._garbage_index = 0
        # Per connection: its request (for the transport) and its queue of frames to send.
        self._clients: dict[web.WebSocketResponse, tuple[web.Request, asyncio.Queue[str]]] = {}
        self._handlers: set[asyncio.Task[object]] = set()
        self._runner: web.AppRunner | None = None
        self._ticker: asyncio.Task[None] | None = None
        # Between a stop() and the next start(), the port stays bound (not listening), so
        # that a client sees the server gone (connection refused) while no other server on
        # the host can be given the port: the kernel hands out a port that any socket holds
        # to nobody else, so a restart serves the clients' URL again, not a stranger's.
        self._reserved: socket.socket | None = None

    @property
    def port(self) -> int:
        return self._port

    @property
    def url(self) -> str:
        return f"ws://{self._host}:{self._port}/"

    @property
    def clients(self) -> int:
        return len(self._clients)

    async def start(self) -> None:
        app = web.Application()
        app.router.add_get("/", self._handle)
        self._runner = web.AppRunner(
            app, access_log=None, handle_signals=False, shutdown_timeout=_CLOSE_TIMEOUT_S
        )
        await self._runner.setup()
        sock, self._reserved = self._reserved or self._bind(), None
        site = web.SockSite(self._runner, sock)
        await site.start()  # listens on the socket itself: no moment with the port free
        self._port = sock.getsockname()[1]
        if self._replay is not None:
            ticks = self._replay_loop()
            log.info(
                "XELA emulator on %s replaying %s, %s, dialect %s",
                self.url,
                self._replay.describe(),
                "looping" if self._loop else "once",
                self._dialect,
            )
        else:
            ticks = self._tick_loop()
            log.info(
                "XELA emulator on %s at %.0f Hz, %d x %s, dialect %s",
                self.url,
                1 / self._period_s,
                self._sensors,
                self._model,
                self._dialect,
            )
        self._ticker = asyncio.create_task(ticks, name=f"xela-emulator:{self._port}")

    def _bind(self) -> socket.socket:
        family, kind, proto, _, address = socket.getaddrinfo(
            self._host, self._port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
        sock = socket.socket(family, kind, proto)
        try:
            # As a listening server would: the last run's closed connections in TIME_WAIT
            # must not keep the restart off its port.
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(address)
        except OSError:
            sock.close()
            raise
        return sock

    async def stop(self, *, keep_port: bool = True) -> None:
        """Stop ticking and close every connection. Idempotent. ``keep_port``: the port is
        kept for a ``start()`` (clients meanwhile are refused); otherwise it is freed, as
        leaving the context does."""
        ticker, self._ticker = self._ticker, None
        failure: Exception | None = None
        if ticker is not None:
            ticker.cancel()
            try:
                await ticker
            except asyncio.CancelledError:
                pass
            except Exception as exc:
                # A broken frame source: free the port first, then say so.
                failure = exc
        await self.drop_connections()
        runner, self._runner = self._runner, None
        if runner is not None:
            await runner.cleanup()
            if keep_port:  # (start() took any earlier reservation)
                try:
                    self._reserved = self._bind()
                except OSError as exc:  # taken in the moment it was free
                    log.warning("XELA emulator: cannot keep port %d for a restart: %s",
                                self._port, exc)
        if not keep_port:
            reserved, self._reserved = self._reserved, None
            if reserved is not None:
                reserved.close()
        if failure is not None:
            raise failure

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.stop(keep_port=False)

    async def drop_connections(self, *, abrupt: bool = False) -> None:
        """Close every client connection (``abrupt``: reset TCP, no close handshake)."""
        for ws, (request, _) in list(self._clients.items()):
            if abrupt and request.transport is not None:
                request.transport.abort()
            else:
                await ws.close(code=WSCloseCode.GOING_AWAY, message=b"emulator drop")
        handlers = list(self._handlers)
        if handlers:
            await asyncio.wait(handlers, timeout=_CLOSE_TIMEOUT_S * 2)

    async def _handle(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(compress=False, timeout=_CLOSE_TIMEOUT_S)
        await ws.prepare(request)
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        queue: asyncio.Queue[str] = asyncio.Queue(maxsize=_CLIENT_QUEUE_FRAMES)
        queue.put_nowait(welcome_frame(self._sensors))
        self._clients[ws] = (request, queue)
        self._first_client.set()
        sender = asyncio.create_task(self._send_loop(ws, queue), name="xela-emulator-send")
        log.info("XELA emulator: client %s connected", request.remote)
        try:
            # Reading keeps the close handshake and pings answered while the sender sends.
            async for _ in ws:
                pass
        finally:
            await cancel_and_wait(sender)
            self._clients.pop(ws, None)
            self._handlers.discard(task)
            log.info("XELA emulator: client %s gone", request.remote)
        return ws

    async def _send_loop(self, ws: web.WebSocketResponse, queue: asyncio.Queue[str]) -> None:
        try:
            while True:
                await ws.send_str(await queue.get())
        except (ConnectionError, RuntimeError) as exc:
            # The peer went away mid-send; the handler's read loop sees it and cleans up.
            log.debug("XELA emulator: send failed: %s", exc)

    async def _tick_loop(self) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time()
        while True:
            deadline += self._period_s
            now = loop.time()
            if now > deadline + self._period_s:
                # Woke far too late (a stalled loop): skip the missed ticks, do not burst.
                missed = int((now - deadline) / self._period_s)
                self.late_ticks += missed
                deadline += missed * self._period_s
            await asyncio.sleep(deadline - now)
            if not self._clients:
                # A frame nobody receives is not rendered: an emulated robot waiting for its
                # daemon or between two commands cost a sixth of a core. The pads' noise is
                # advanced over the gap at the next frame (skin.PadNoise), as over any other.
                continue
            try:
                text = self._next_text(time.monotonic())
            except Exception:
                log.exception("XELA emulator: frame source failed; no more frames")
                raise
            self._broadcast(text)

    async def _replay_loop(self) -> None:
        """The replay's frames at their recorded times (loop time) from the first client's
        connection, lap after lap."""
        assert self._replay is not None
        frames, times = self._replay.frames, self._replay.times_s
        # One lap: the recording plus one typical interval before its first frame again.
        lap_s = self._replay.duration_s + self._replay.period_s
        loop = asyncio.get_running_loop()
        await self._first_client.wait()
        start = loop.time()
        i = 0
        while True:
            if i == len(frames):
                self.replay_laps += 1
                if not self._loop:
                    log.info(
                        "XELA emulator: replay of %d frames ended; sending nothing more "
                        "(connections stay open)",
                        len(frames),
                    )
                    return
                i, start = 0, start + lap_s
            deadline = start + times[i]
            now = loop.time()
            if now > deadline + _REPLAY_MAX_LAG_S:
                # A stalled loop: go on from here at the recorded pace, no burst.
                self.late_ticks += 1
                start += now - deadline
                deadline = now
            await asyncio.sleep(deadline - now)
            self._broadcast(self._next_text(time.monotonic(), frames[i]))
            i += 1

    def _broadcast(self, text: str | None) -> None:
        if text is None:
            return
        for _, queue in self._clients.values():
            if queue.full():
                queue.get_nowait()
            queue.put_nowait(text)

    def _next_text(self, t: float, raw: np.ndarray | None = None) -> str | None:
        """The next frame's text: ``raw`` (a replay's frame) or the source's at ``t``, or
        what the switched fault sends instead."""
        fault = self.fault
        if fault is Fault.SILENT:
            return None
        if fault is Fault.FREEZE and self._last_text is not None:
            return self._last_text
        if fault is Fault.GARBAGE:
            self._garbage_index += 1
            return GARBAGE_FRAMES[self._garbage_index % len(GARBAGE_FRAMES)]
        if raw is None:
            raw = np.asarray(self._source.frame(t))
        expected = self._sensors * self._taxels * 3
        if raw.shape != (expected,) or raw.dtype != np.uint16:
            raise ValueError(
                f"frame source gave {raw.dtype} {raw.shape}, need uint16 ({expected},)"
            )
        self._seq += 1
        self.frames_sent += 1
        newtons = self._source.frame_newtons() if self._calibrated else None  # type: ignore[attr-defined]
        self._last_text = encode_frame(
            self._seq,
            time.time(),
            raw,
            sensors=self._sensors,
            taxels=self._taxels,
            model=self._model,
            dialect=self._dialect,
            newtons=newtons,
        )
        return self._last_text


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description="Emulate xela_server (idle XR1944 pads, or a real recording replayed)."
    )
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT)
    parser.add_argument("--rate", type=float, default=125.0, help="frames per second")
    parser.add_argument("--sensors", type=int, default=2)
    parser.add_argument("--dialect", choices=["1.7", "1.7.7", "1.8"], default="1.8")
    parser.add_argument(
        "--replay",
        default=None,
        metavar="FILE",
        help="serve this recording's frames at their recorded times "
        "(XELA CSV directory or .press.npz)",
    )
    parser.add_argument(
        "--replay-once",
        action="store_true",
        help="stop sending after the last frame instead of starting over",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    replay = None
    if args.replay is not None:
        try:
            replay = load_replay(args.replay)
        except ValueError as exc:
            parser.exit(2, f"xela_server emulator: {exc}\n")

    async def serve() -> None:
        async with XelaServerEmulator(
            host=args.host,
            port=args.port,
            rate_hz=args.rate,
            sensors=args.sensors,
            dialect=args.dialect,
            replay=replay,
            loop=not args.replay_once,
        ):
            await asyncio.Event().wait()

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve())


if __name__ == "__main__":
    main()
