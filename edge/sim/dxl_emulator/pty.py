"""The emulator's pty transport: one thread serves the slave side of a pty pair, so the real
``dynamixel_sdk.PortHandler(port)`` talks to the emulated motors byte for byte, with each
motor's Return Delay Time and the emulator's ``reply_latency_s`` before its status packet."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import select
import threading
import time
import tty
from typing import TYPE_CHECKING

from edge.sim.dxl_emulator.codec import parse_packet

if TYPE_CHECKING:
    from edge.sim.dxl_emulator.model import DxlEmulator

_log = logging.getLogger(__name__)

# A packet whose declared length never arrives is dropped after this long, so one corrupt
# length field cannot wedge the parser.
PARTIAL_PACKET_TIMEOUT_S = 0.05
# The thread wakes at least this often to step the motion model while the bus is quiet.
IDLE_WAKE_S = 0.01
# A wake-up later than this past IDLE_WAKE_S means this thread was not running (a loaded
# host), not that the bus was quiet: see PtyTransport._run.
STALL_S = 0.05
STOP_JOIN_TIMEOUT_S = 2.0


class PtyTransport:
    """Serves ``emulator`` on a pty from :meth:`start` (which returns the port's path) to
    :meth:`stop`."""

    def __init__(self, emulator: DxlEmulator) -> None:
        self._emu = emulator
        self._master = self._slave = self._wake_r = self._wake_w = -1
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()

    @property
    def serving(self) -> bool:
        return self._thread is not None

    def start(self) -> str:
        if self._thread is not None:
            raise RuntimeError("emulator already started")
        self._master, self._slave = os.openpty()
        # Raw from the start: no echo, no CR/LF translation, before any client opens the port.
        tty.setraw(self._slave)
        # Keep the slave open ourselves so the master never reads EIO between clients.
        port = os.ttyname(self._slave)
        fl = fcntl.fcntl(self._master, fcntl.F_GETFL)
        fcntl.fcntl(self._master, fcntl.F_SETFL, fl | os.O_NONBLOCK)
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="dxl-emulator", daemon=True)
        self._thread.start()
        return port

    def stop(self) -> None:
        if self._thread is None:
            return
        self._stopping.set()
        os.write(self._wake_w, b"x")
        self._thread.join(STOP_JOIN_TIMEOUT_S)
        if self._thread.is_alive():
            _log.error("Dynamixel emulator thread did not stop within %.1f s", STOP_JOIN_TIMEOUT_S)
        self._thread = None
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = self._wake_r = self._wake_w = -1

    def _run(self) -> None:
        emu = self._emu
        buf = bytearray()
        partial_since: float | None = None
        # Only on the wall clock does this thread's stall pass on the motors' clock (a test's
        # manual clock moves when the test moves it).
        wall = emu.clock is time.monotonic
        woke = time.monotonic()
        try:
            while not self._stopping.is_set():
                ready, _, _ = select.select([self._master, self._wake_r], [], [], IDLE_WAKE_S)
                if self._wake_r in ready:
                    break
                last, woke = woke, time.monotonic()
                stalled = woke - last - IDLE_WAKE_S
                if wall and stalled > STALL_S:
                    # A motor's watchdog counts silence on the wire; while this thread did
                    # not run, the host's packets waited in the pty unseen. That time is not
                    # the host's silence: a loaded test host must not trip the watchdog.
                    emu.pause_watchdogs(stalled)
                now = emu.clock()
                if self._master in ready:
                    try:
                        buf += os.read(self._master, 4096)
                    except BlockingIOError:
                        pass
                    except OSError as exc:
                        if exc.errno != errno.EIO:
                            raise
                emu.advance(now)
                while True:
                    ins = parse_packet(buf)
                    if ins is None:
                        break
                    if not self._send(emu.execute(ins, now), now):
                        return
                if buf:
                    partial_since = partial_since if partial_since is not None else now
                    if now - partial_since > PARTIAL_PACKET_TIMEOUT_S:
                        del buf[:1]
                        partial_since = None
                else:
                    partial_since = None
        except Exception:
            _log.exception("Dynamixel emulator thread died")

    def _send(self, replies: list[tuple[int, float, bytes]], arrival: float) -> bool:
        """Write the status packets (motor ID, its Return Delay Time, packet) with their
        delays; False if asked to stop meanwhile."""
        clock = self._emu.clock
        due = arrival + self._emu.reply_latency_s
        for motor_id, return_delay_s, packet in replies:
            due += return_delay_s
            wait = due - clock()
            if wait > 0 and select.select([self._wake_r], [], [], wait)[0]:
                return False
            try:
                os.write(self._master, packet)
            except BlockingIOError:
                _log.warning("emulated motor %d: pty full, status packet dropped", motor_id)
            due = max(due, clock())
        return True
