"""XELA uSkin through ``xela_server``: the frame parser and an aiohttp WebSocket client.

The server sends one JSON text frame per update: bookkeeping keys (``message`` = sequence
number, ``time``, ``sensors``, ...) plus one object per sensor under its number (``"1"``,
``"2"``) whose ``data`` holds x, y, z hex words per taxel (1.7.7: a list of ints; 1.8 adds
``integer``, ``temp``, ``ups``). See docs/hardware.md, 'XELA server', and a real frame in
``tests/fixtures/xela/``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import re
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import Any, Self

import aiohttp
import msgspec
import numpy as np

from edge.core.backoff import Backoff
from edge.core.config import SensorConfig
from edge.core.errors import SensorError, SensorLayoutError, StaleSensorError
from edge.core.reconnect import Reconnect
from edge.core.tasks import cancel_and_wait
from edge.hw.contracts import StreamStats, TactileFrame

log = logging.getLogger(__name__)

# A 2-sensor 1.8 frame with calibration is ~7 kB; far above that is a broken or hostile peer.
MAX_FRAME_CHARS = 256 * 1024
# First reconnect delay; it doubles per failed attempt up to reconnect_max_backoff_s.
_RECONNECT_MIN_BACKOFF_S = 0.05
# Waiting for the server's close reply when we hang up; a dead server never answers.
_CLOSE_TIMEOUT_S = 0.5
# A consumer this many frames behind loses the oldest ones (about 2 s at 125 Hz).
_QUEUE_FRAMES = 256
# A stale stream is warned about at most this often: a busy host stalls it for a moment now
# and then (22 warnings in 3 idle minutes, seen), and each such spell is counted into the
# next warning instead.
STALE_WARN_INTERVAL_S = 60.0

_HEX_WORD = re.compile(r"[0-9A-Fa-f]{1,4}")
# Dropped from inside hex words: what a wrapped or indented capture puts there. Anything else
# (another control character, a stray letter) still makes the word "not a 16-bit hex word".
_DROP_WHITESPACE = str.maketrans("", "", " \t\r\n")
# strict=False: see _load. One decoder for every frame (json.loads would build one a call).
# It reads what msgspec refuses; msgspec reads a usual frame in a third of its time.
_DECODER = json.JSONDecoder(strict=False)
_FAST_DECODER = msgspec.json.Decoder()




@dataclass(frozen=True, eq=False)
class ParsedFrame:
    """One data frame as the server sent it; sensors in number order."""

    seq: int
    time: float
    raw: np.ndarray  # (sum of taxels * 3,) uint16, channel order of edge.hw.contracts
    sensors: tuple[str, ...]  # sensor numbers, e.g. ("1", "2")
    models: tuple[str, ...]
    taxels: tuple[int, ...]
    # `calibrated` newtons (float64, like ``raw``) when asked for and every sensor sends them.
    newtons: np.ndarray | None = None

    def describe(self) -> str:
        """The layout in words, e.g. ``2 sensors: 1 = uSPa46 x 24 taxels, 2 = ...``."""
        parts = ", ".join(
            f"{s} = {m} x {n} taxels"
            for s, m, n in zip(self.sensors, self.models, self.taxels, strict=True)
        )
        return f"{len(self.sensors)} sensor{'s' if len(self.sensors) != 1 else ''}: {parts}"


def parse_layout_free(msg: str | bytes | Mapping[str, Any], *,
                      newtons: bool = False) -> ParsedFrame | None:
    """Parse one server frame without a layout expectation; None for the Welcome frame.
    ``newtons``: also read the sensors' ``calibrated`` forces (see :func:`_newtons`).

    Raises SensorError, naming what is wrong, for anything that is not a well-formed frame.
    """
    return _from_object(_load(msg), newtons)


def _from_object(obj: Mapping[str, Any], newtons: bool) -> ParsedFrame | None:
    seq = obj.get("message")
    if seq == "Welcome":
        return None
    # The runtime keeps sequence numbers as int64 (ring buffer, recordings).
    if type(seq) is not int or not -(2**63) <= seq < 2**63:
        raise SensorError(
            f"XELA frame: 'message' (sequence number) must be a 64-bit int, got {seq!r:.40}"
        )
    # Sensor objects sit under their number; every other key is bookkeeping.
    numbers = sorted(
        (k for k in obj if isinstance(k, str) and k.isascii() and k.isdecimal()), key=int
    )
    if not numbers:
        raise SensorError(f"XELA frame {seq}: no sensor keys ('1', '2', ...) in the frame")
    sensors = [obj[number] for number in numbers]
    # Every sensor's words at once; where that fails, one sensor at a time, which says what
    # is wrong (in sensor order, among the other checks).
    decoded = _frame_words(sensors)
    arrays, models, taxels = [], [], []
    for i, (number, sensor) in enumerate(zip(numbers, sensors, strict=True)):
        if decoded is None:
            arrays.append(_sensor_words(sensor, seq, number))
            count = len(arrays[-1])
        else:
            count = decoded[1][i]
        if count % 3:
            raise SensorError(
                f"XELA frame {seq}, sensor {number}: {count} values is not x, y, z per taxel"
            )
        declared = sensor.get("taxels")
        if declared is not None and declared != count // 3:
            raise SensorError(
                f"XELA frame {seq}, sensor {number}: says {declared!r:.20} taxels but sends "
                f"{count} values"
            )
        model = sensor.get("model", "?")
        models.append(model[:40] if isinstance(model, str) else repr(model)[:40])
        taxels.append(count // 3)
    if decoded is not None:
        raw = decoded[0]
    else:
        raw = arrays[0] if len(arrays) == 1 else np.concatenate(arrays)
    return ParsedFrame(
        seq, _frame_time(obj, seq, numbers[0]), raw, tuple(numbers), tuple(models), tuple(taxels),
        _newtons(obj, numbers, raw.size) if newtons else None,
    )


def _newtons(obj: Mapping[str, Any], numbers: list[str], channels: int) -> np.ndarray | None:
    """Every sensor's ``calibrated`` list (newtons, x, y, z per taxel) joined, or None when
    one is absent, null (uncalibrated models such as the XR1944) or not one number per
    channel: the forces are a measurement aid, never a reason to drop a frame."""
    values: list[Any] = []
    for number in numbers:
        forces = obj[number].get("calibrated")
        if not isinstance(forces, list):
            return None
        values.extend(forces)
    if len(values) != channels or not all(type(v) in (int, float) for v in values):
        return None
    return np.array(values, dtype=np.float64)


def _frame_time(obj: Mapping[str, Any], seq: int, first_sensor: str) -> float:
    # XELA's own 1.7 ROS bridge reads only the per-sensor time and defaults it, so do not
    # insist on the top-level one: fall back to sensor 1's, else NaN (the seq still counts).
    t = obj.get("time")
    if t is None:
        t = obj[first_sensor].get("time")
        if t is None:
            return math.nan
    try:
        # float() of an integer beyond any float overflows: not a time either.
        value = float(t) if type(t) in (int, float) else math.nan
    except OverflowError:
        value = math.inf
    if not math.isfinite(value):
        raise SensorError(f"XELA frame {seq}: 'time' must be a finite number, got {t!r:.40}")
    return value


def parse_frame(
    msg: str | bytes | Mapping[str, Any],
    expected_pads: int,
    expected_taxels: int,
    *,
    expected_model: str | None = None,
    newtons: bool = False,
) -> ParsedFrame | None:
    """Parse one frame and check it has ``expected_pads`` sensors of ``expected_taxels``.

    Returns None for the Welcome frame. Raises SensorLayoutError when the layout differs
    (the message names both sides) and SensorError for a malformed frame.
    """
    frame = _from_object(_load(msg), newtons)
    if frame is not None:
        _check_layout(frame, expected_pads, expected_taxels, expected_model)
    return frame


def _check_layout(frame: ParsedFrame, expected_pads: int, expected_taxels: int,
                  expected_model: str | None) -> None:
    configured = (
        f"configured {expected_pads} x {expected_model or 'sensor'} ({expected_taxels} taxels each)"
    )
    if len(frame.sensors) != expected_pads:
        raise SensorLayoutError(
            f"XELA layout mismatch: {configured} but the server sends {frame.describe()}. "
            "Check that every pad is connected and listed in xela_server's configuration, "
            "or set sensor.pads to match."
        )
    for number, model, n in zip(frame.sensors, frame.models, frame.taxels, strict=True):
        if n != expected_taxels:
            raise SensorLayoutError(
                f"XELA layout mismatch: {configured} but the server sends sensor {number} "
                f"model {model} with {n} taxels ({frame.describe()}). Set sensor.model and "
                "sensor.taxels_per_pad to the hardware, or fix xela_server's configuration."
            )
        # A server that does not name its model ("?") is taken at its layout.
        if expected_model and model != "?" and model.casefold() != expected_model.casefold():
            raise SensorLayoutError(
                f"XELA layout mismatch: {configured} but the server sends sensor {number} "
                f"model {model} ({frame.describe()}). Set sensor.model to the hardware, or "
                "fix xela_server's configuration."
            )


def _load(msg: str | bytes | Mapping[str, Any]) -> Mapping[str, Any]:
    if isinstance(msg, Mapping):
        return msg
    if not isinstance(msg, str | bytes | bytearray):
        raise SensorError(f"XELA frame must be text or a JSON object, got {type(msg).__name__}")
    if len(msg) > MAX_FRAME_CHARS:
        raise SensorError(
            f"XELA frame of {len(msg)} characters exceeds the {MAX_FRAME_CHARS} limit"
        )
    try:
        # What msgspec reads, it reads as the standard decoder does (integers beyond 64
        # bits too).
        obj = _FAST_DECODER.decode(msg)
    except (msgspec.MsgspecError, RecursionError):
        # Not strict JSON in UTF-8 (raw control characters, NaN, a float beyond range,
        # other encodings, ...), or not JSON at all: the standard decoder reads the first
        # and names the fault in the second.
        obj = _load_lenient(msg)
    if not isinstance(obj, dict):
        raise SensorError(f"XELA frame must be a JSON object, got {type(obj).__name__}")
    return obj


def _load_lenient(msg: str | bytes | bytearray) -> Any:
    """The standard decoder's reading, raising SensorError for what is not JSON."""
    try:
        # strict=False: frames captured from XELA's tools can carry raw newlines, carriage
        # returns and tabs inside the long `data` string (a logger wrapping the line), which
        # strict JSON refuses; XELA's own replay server sanitises them before parsing too.
        if not isinstance(msg, str):  # as json.loads takes bytes
            msg = msg.decode(json.detect_encoding(msg), "surrogatepass")
        obj = _DECODER.decode(msg)
    except (ValueError, RecursionError) as exc:
        # UnicodeDecodeError is a ValueError; RecursionError comes from absurd nesting.
        raise SensorError(f"XELA frame is not JSON ({exc}): {msg[:60]!r}") from None
    return obj


def _frame_words(sensors: list[Any]) -> tuple[np.ndarray, list[int]] | None:
    """Every sensor's words decoded at once, and how many each sent, when every one is
    well formed as the usual frame has them (4-digit hex words, or ints 0..65535); else
    None, and :func:`_sensor_words` checks each sensor to say what is wrong."""
    values = []
    for sensor in sensors:
        if type(sensor) is not dict:
            return None
        words = sensor.get("integer")
        if words is None:
            words = sensor.get("data")
        values.append(words)
    if all(type(v) is list for v in values):
        joined: list[Any] = []
        for v in values:
            joined += v
        # Checked in Python before numpy sees them: on the per-frame path, where its code is
        # out of the caches, every numpy call costs more than these.
        if set(map(type, joined)) != {int} or min(joined) < 0 or max(joined) > 0xFFFF:
            return None  # (a bool is no int here)
        return np.array(joined, dtype=np.uint16), [len(v) for v in values]
    if all(type(v) is str for v in values):
        words = _usual_hex(",".join(values))  # one pass over the words of every sensor
        return None if words is None else (words, [(len(v) + 1) // 5 for v in values])
    return None


def _usual_hex(text: str) -> np.ndarray | None:
    """The words of the usual "8125,81B2,...", else None: commas exactly every 5th
    character, so every word is 4 characters; fromhex then refuses non-hex, and a short
    result means whitespace inside a word."""
    n = text.count(",") + 1
    if len(text) != 5 * n - 1 or text[4::5] != "," * (n - 1):
        return None
    try:
        packed = bytes.fromhex(text.replace(",", ""))
    except ValueError:
        return None
    if len(packed) != 2 * n:
        return None
    return np.frombuffer(packed, dtype=">u2").astype(np.uint16)


def _sensor_words(sensor: Any, seq: int, number: str) -> np.ndarray:
    if not isinstance(sensor, Mapping):
        raise SensorError(f"XELA frame {seq}: sensor {number} is not an object")
    # 1.8 sends the same words as ints in `integer`: cheaper than hex, so prefer it.
    values = sensor.get("integer")
    if values is None:
        values = sensor.get("data")
    if isinstance(values, str):
        return _hex_words(values, seq, number)
    if isinstance(values, list):
        return _int_words(values, seq, number)
    if values is None:
        raise SensorError(f"XELA frame {seq}: sensor {number} has no 'data' or 'integer'")
    raise SensorError(
        f"XELA frame {seq}: sensor {number} 'data' must be a hex string or a list of ints, "
        f"got {type(values).__name__}"
    )


def _hex_words(text: str, seq: int, number: str) -> np.ndarray:
    usual = _usual_hex(text)
    if usual is not None:
        return usual
    words = []
    for i, part in enumerate(text.split(",")):
        # Whitespace inside a word too: a wrapped capture may break a line mid-word.
        word = part.translate(_DROP_WHITESPACE).strip()
        if not _HEX_WORD.fullmatch(word):
            raise SensorError(
                f"XELA frame {seq}, sensor {number}: value {i} {part[:20]!r} is not a 16-bit "
                "hex word"
            )
        words.append(word)
    return np.array([int(w, 16) for w in words], dtype=np.uint16)


def _int_words(values: list[Any], seq: int, number: str) -> np.ndarray:
    if not all(type(v) is int for v in values):
        bad = next(v for v in values if type(v) is not int)
        raise SensorError(f"XELA frame {seq}, sensor {number}: value {bad!r:.20} is not an int")
    if values and (min(values) < 0 or max(values) > 0xFFFF):
        raise SensorError(
            f"XELA frame {seq}, sensor {number}: values must be 0..65535, got "
            f"{min(values)}..{max(values)}"
        )
    return np.array(values, dtype=np.uint16)


_CLOSED = object()


class XelaClient:
    """:class:`~edge.hw.contracts.TactileSource` reading ``xela_server`` over WebSocket.

    A background task owns the connection: it skips the Welcome frame, drops repeated
    frames (counted), timestamps fresh ones with ``time.monotonic()`` and queues them; it
    reconnects with capped exponential backoff. ``on_frame``, when set, is awaited with each
    fresh frame in that task before the frame is queued: a consumer's time-critical step
    (the threshold check and the stop) without the hop through the queue to its own task.
    Malformed frames are skipped and counted in ``stats.skipped`` (a stream of them reads as
    stale); a layout that does not match the configuration stops the client and
    ``frames()`` raises :class:`SensorLayoutError`.
    """

    def __init__(self, config: SensorConfig) -> None:
        self._cfg = config
        self.stats = StreamStats()
        self.server_layout: str | None = None  # what the server sends, in words
        self.server_models: tuple[str, ...] | None = None  # the model of each sensor it sends
        self._queue: asyncio.Queue[object] = asyncio.Queue(maxsize=_QUEUE_FRAMES)
        self._task: asyncio.Task[None] | None = None
        self._session: aiohttp.ClientSession | None = None
        self._fatal: SensorError | None = None
        self._last_fresh: float | None = None  # monotonic time of the last fresh frame
        cap_s = config.reconnect_max_backoff_s
        self._link = Reconnect(f"XELA server {config.url}",
                               Backoff(min(_RECONNECT_MIN_BACKOFF_S, cap_s), cap_s), log)
        self._closed = False
        self._stale_reported = False
        # The last stale warning (monotonic), the spells since it that were not warned about,
        # and whether the present spell was (its end is said where its start was).
        self._stale_warned_t = -math.inf
        self._stale_unwarned = 0
        self._stale_said = False
        # Set by the first fresh frame, or by a layout refused: what wait_first_frame awaits.
        self._arrived = asyncio.Event()
        # Called with (seq, receive time, time parsed) for each fresh frame: a benchmark's
        # probe (the parse's share of the stop latency); None in production.
        self.on_parsed: Callable[[int, float, float], None] | None = None
        # Called as each message arrives, before it is parsed: a benchmark's probe (the
        # thread CPU time a frame costs up to its threshold check); None in production.
        self.on_received: Callable[[], None] | None = None
        # Awaited with each fresh frame before it is queued (see the class docstring); it
        # must not raise.
        self.on_frame: Callable[[TactileFrame], Awaitable[None]] | None = None
        # Keep the `calibrated` newtons in each frame (vt-edge calibrate threshold); off on the
        # press's path, which never reads them.
        self.newtons = False

    def set_frame_hook(self, hook: Callable[[TactileFrame], Awaitable[None]] | None) -> bool:
        self.on_frame = hook
        return True

    @property
    def connected(self) -> bool:
        return self._link.connected

    async def start(self) -> None:
        if self._closed:
            raise RuntimeError("XelaClient cannot be restarted after close()")
        if self._task is not None:
            return
        # No session-wide total timeout: a WebSocket stays open for days.
        timeout = aiohttp.ClientTimeout(total=None, connect=self._cfg.connect_timeout_s)
        self._session = aiohttp.ClientSession(timeout=timeout)
        self._task = asyncio.create_task(self._run(), name=f"xela-client {self._cfg.url}")

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._task is not None:
            await cancel_and_wait(self._task)
        if self._session is not None:
            await self._session.close()
        self._put(_CLOSED)

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    def is_fresh(self) -> bool:
        """True while the last fresh frame is younger than ``stale_timeout_s``."""
        return (
            self._fatal is None
            and not self._closed
            and self._last_fresh is not None
            and time.monotonic() - self._last_fresh < self._cfg.stale_timeout_s
        )

    async def frames(self, *, first_timeout_s: float | None = None) -> AsyncIterator[TactileFrame]:
        """Yield fresh frames; raise StaleSensorError after ``stale_timeout_s`` without one.

        ``first_timeout_s`` allows longer for the first frame (e.g. while connecting at
        start-up). After a StaleSensorError the client keeps (re)connecting: call again.
        """
        if self._task is None:
            raise RuntimeError("XelaClient.frames() before start()")
        loop = asyncio.get_running_loop()
        # Frames carry time.monotonic(); deadlines are in loop time (the same clock on
        # CPython's loop, not necessarily on others).
        to_loop_s = loop.time() - time.monotonic()
        stale_s = self._cfg.stale_timeout_s
        deadline = loop.time() + (stale_s if first_timeout_s is None else first_timeout_s)
        if self._last_fresh is not None:
            deadline = max(deadline, self._last_fresh + to_loop_s + stale_s)
        while not self._closed:
            if self._fatal is not None:
                raise self._fatal
            try:
                async with asyncio.timeout_at(deadline):
                    item = await self._queue.get()
            except TimeoutError:
                if self._queue.empty():
                    raise self._stale_error() from None
                # A frame came in while the loop was late to look: the stream is alive.
                item = self._queue.get_nowait()
            if item is _CLOSED:
                return
            if isinstance(item, SensorError):
                raise item
            assert isinstance(item, TactileFrame)
            deadline = item.recv_time + to_loop_s + stale_s
            yield item

    async def wait_first_frame(self, timeout_s: float) -> None:
        """Until the first fresh frame has arrived (its layout checked against the
        configuration). Raises :class:`SensorLayoutError` for a layout the configuration
        does not match, and :class:`StaleSensorError` saying whether the server could be
        reached when no frame came within ``timeout_s``. Consumes no frame."""
        if self._task is None:
            raise RuntimeError("XelaClient.wait_first_frame() before start()")
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._arrived.wait(), timeout_s)
        if self._fatal is not None:
            raise self._fatal
        if self._last_fresh is None:
            if self._link.connections:
                why = f"connected, but no data frame within {timeout_s:.1f} s"
            else:
                failure = self._link.last_failure or f"no connection in {timeout_s:.1f} s"
                why = f"unreachable ({failure})"
            raise StaleSensorError(f"sensor server {self._cfg.url} {why}")

    def _stale_error(self) -> StaleSensorError:
        age = None if self._last_fresh is None else time.monotonic() - self._last_fresh
        state = "connected" if self.connected else "not connected"
        since = "no frame yet" if age is None else f"last fresh frame {age:.3f} s ago"
        msg = (
            f"XELA stream at {self._cfg.url} is stale: {since} (stale_timeout_s="
            f"{self._cfg.stale_timeout_s}), {state}, {self.stats.repeats} repeated and "
            f"{self.stats.skipped} malformed frames so far"
        )
        if not self._stale_reported:
            self._stale_reported = True
            self._warn_stale(msg)
        return StaleSensorError(msg)

    def _warn_stale(self, msg: str) -> None:
        """A new stale spell: warned about, or counted into the next warning within
        ``STALE_WARN_INTERVAL_S`` of the last one."""
        now = time.monotonic()
        since = now - self._stale_warned_t
        self._stale_said = since >= STALE_WARN_INTERVAL_S
        if not self._stale_said:
            self._stale_unwarned += 1
            log.debug("%s", msg)
            return
        if self._stale_unwarned:
            log.warning("%s (%d more in the last %.0f s)", msg, self._stale_unwarned, since)
        else:
            log.warning("%s", msg)
        self._stale_warned_t, self._stale_unwarned = now, 0

    def _put(self, item: object) -> None:
        if self._queue.full():
            self._queue.get_nowait()
            self.stats.overruns += 1
            if self.stats.overruns % 100 == 1:
                log.warning("tactile consumer is behind: %d frames dropped", self.stats.overruns)
        self._queue.put_nowait(item)

    async def _run(self) -> None:
        try:
            await self._link.run(self._attempt, (aiohttp.ClientError, OSError, TimeoutError),
                                 fatal=(SensorLayoutError,))
        except SensorLayoutError as exc:
            # Not transient: reconnecting gives the same layout. Stop and tell the consumer
            # (which reports it: logged here too, it would be said twice).
            self._fatal = exc
            self._arrived.set()
            self._put(exc)

    async def _attempt(self) -> bool:
        """One connection; returns whether it delivered a fresh frame (the backoff then
        starts again from its base: a server that accepts and sends nothing is not dialled
        at the base rate)."""
        try:
            return await self._connect_and_read()
        except (SensorLayoutError, aiohttp.ClientError, OSError, TimeoutError):
            raise
        except Exception:
            # A bug here must not silently end the sensor path: log loudly, keep trying.
            log.exception("XELA client: unexpected error; trying again")
            return False

    async def _connect_and_read(self) -> bool:
        assert self._session is not None
        async with asyncio.timeout(self._cfg.connect_timeout_s):
            ws = await self._session.ws_connect(
                self._cfg.url,
                timeout=aiohttp.ClientWSTimeout(ws_receive=None, ws_close=_CLOSE_TIMEOUT_S),
                max_msg_size=MAX_FRAME_CHARS,
            )
        if self._link.connections:
            self.stats.reconnects += 1
        self._link.up()
        self.stats.new_connection()
        log.info("%s XELA server %s", "reconnected to" if self.stats.reconnects else "connected to",
                 self._cfg.url)
        delivered = False
        loop = asyncio.get_running_loop()
        # A server that hangs (or a host that vanished without closing TCP) sends nothing
        # fresh: give up on the connection after dead_timeout_s and dial again.
        progress = loop.time()
        try:
            while True:
                remaining = progress + self._cfg.dead_timeout_s - loop.time()
                try:
                    # aiohttp reads a zero timeout as "none": keep it positive.
                    msg = await ws.receive(timeout=max(remaining, 1e-3))
                except TimeoutError:
                    log.warning(
                        "XELA server %s: no fresh frame for %.1f s; reconnecting",
                        self._cfg.url,
                        self._cfg.dead_timeout_s,
                    )
                    return delivered
                recv_time = time.monotonic()
                if self.on_received is not None:
                    self.on_received()
                if msg.type in (aiohttp.WSMsgType.TEXT, aiohttp.WSMsgType.BINARY):
                    frame = self._handle(msg.data, recv_time)
                    if frame is not None:
                        delivered = True
                        progress = loop.time()
                        if self.on_frame is not None:
                            await self.on_frame(frame)
                        self._put(frame)
                elif msg.type in (
                    aiohttp.WSMsgType.CLOSE,
                    aiohttp.WSMsgType.CLOSING,
                    aiohttp.WSMsgType.CLOSED,
                    aiohttp.WSMsgType.ERROR,
                ):
                    log.warning(
                        "XELA server %s: connection lost (%s %s %s)",
                        self._cfg.url,
                        msg.type.name,
                        msg.data,
                        msg.extra or "",
                    )
                    return delivered
        finally:
            await ws.close()

    def _handle(self, data: str | bytes, recv_time: float) -> TactileFrame | None:
        """Parse and count one message; the frame when it is a fresh one."""
        cfg = self._cfg
        try:
            frame = parse_frame(data, cfg.pads, cfg.taxels_per_pad, expected_model=cfg.model,
                                newtons=self.newtons)
        except SensorLayoutError:
            raise
        except SensorError as exc:
            self.stats.skipped += 1
            if self.stats.skipped % 100 == 1:
                log.warning(
                    "skipping malformed XELA frame (%d so far): %s", self.stats.skipped, exc
                )
            return None
        if frame is None:
            log.debug("XELA server welcome skipped")
            return None
        if self.server_layout is None:
            self.server_layout = frame.describe()
            self.server_models = frame.models
            log.info("XELA server sends %s", self.server_layout)
        if not self.stats.observe(frame.seq, frame.time):
            return None
        if self._stale_reported:
            self._stale_reported = False
            log.log(logging.INFO if self._stale_said else logging.DEBUG,
                    "XELA stream fresh again (frame %d)", frame.seq)
        self._last_fresh = recv_time
        self._arrived.set()
        if self.on_parsed is not None:
            self.on_parsed(frame.seq, recv_time, time.monotonic())
        return TactileFrame(frame.seq, frame.time, recv_time, frame.raw, frame.models,
                            frame.newtons)
