"""The emulator's pty transport: one thread serves the slave side of a pty pair, so the real
``dynamixel_sdk.PortHandler(port)`` talks to the emulated motors byte for byte, with each
motor's Return Delay Time and the emulator's ``reply_latency_s`` before its status packet.

The port is a symbolic link to the pty's slave (as ``/dev/serial/by-id/...`` is to a USB
adapter's tty), so that the adapter can be unplugged and plugged back under the same name:
:meth:`PtyTransport.unplug` hangs the pty up and removes the link (the client's next read or
write fails with an I/O error, opening the port fails: no such file), :meth:`plug` serves a
new pty under it, and :meth:`serial_error_once` does both at the next instruction packet,
while its client waits for the reply: an I/O error inside a transaction, then a working line.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import select
import tempfile
import threading
import time
import tty
from pathlib import Path
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
# The port's name inside the emulator's own temporary directory.
PORT_LINK_NAME = "ttyDXL"


class PtyTransport:
    """Serves ``emulator`` on a pty from :meth:`start` (which returns the port's path) to
    :meth:`stop`."""

    def __init__(self, emulator: DxlEmulator) -> None:
        self._emu = emulator
        self._master = self._slave = self._wake_r = self._wake_w = -1
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._link_dir: Path | None = None
        # What the thread is asked to do with the line (see _apply): plugged or not, and
        # an I/O error at the next instruction packet.
        self._want_plugged = True
        self._error_next = False
        # Set by the thread once it has done what _ask asked.
        self._applied = threading.Event()

    @property
    def serving(self) -> bool:
        return self._thread is not None

    @property
    def link(self) -> Path:
        if self._link_dir is None:
            raise RuntimeError("emulator not started")
        return self._link_dir / PORT_LINK_NAME

    @property
    def plugged(self) -> bool:
        return self._master >= 0

    def start(self) -> str:
        if self._thread is not None:
            raise RuntimeError("emulator already started")
        self._link_dir = Path(tempfile.mkdtemp(prefix="vtzero-dxl-"))
        self._want_plugged, self._error_next = True, False
        self._plug()
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="dxl-emulator", daemon=True)
        self._thread.start()
        return str(self.link)

    def stop(self) -> None:
        if self._thread is None:
            return
        self._stopping.set()
        os.write(self._wake_w, b"x")
        self._thread.join(STOP_JOIN_TIMEOUT_S)
        if self._thread.is_alive():
            _log.error("Dynamixel emulator thread did not stop within %.1f s", STOP_JOIN_TIMEOUT_S)
        self._thread = None
        self._unplug()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1
        if self._link_dir is not None:
            with contextlib.suppress(OSError):
                self._link_dir.rmdir()
            self._link_dir = None
        self._stopping.clear()

    def unplug(self) -> None:
        """The adapter pulled out: the line hangs up and the port's path is gone."""
        self._ask(plugged=False)

    def plug(self) -> None:
        """The adapter plugged back: a new line under the same path."""
        self._ask(plugged=True)

    def serial_error_once(self) -> None:
        """At the next instruction packet, the line fails (the client, waiting for the
        reply, reads an I/O error) and comes back at once under the same path."""
        self._error_next = True

    def _ask(self, *, plugged: bool) -> None:
        """Have the thread plug or unplug, and return once it has (a caller then finds the
        port's path there, or gone)."""
        self._want_plugged = plugged
        if self._thread is None:
            return
        self._applied.clear()
        os.write(self._wake_w, b"p")
        if not self._applied.wait(STOP_JOIN_TIMEOUT_S):
            _log.error("Dynamixel emulator thread did not %s the adapter within %.1f s",
                       "plug in" if plugged else "unplug", STOP_JOIN_TIMEOUT_S)

    def _plug(self) -> None:
        self._master, self._slave = os.openpty()
        # Raw from the start: no echo, no CR/LF translation, before any client opens the port.
        tty.setraw(self._slave)
        # Keep the slave open ourselves so the master never reads EIO between clients.
        fl = fcntl.fcntl(self._master, fcntl.F_GETFL)
        fcntl.fcntl(self._master, fcntl.F_SETFL, fl | os.O_NONBLOCK)
        # Pointed at the new slave in one step: a client opening the path never finds it
        # half made.
        tmp = self.link.with_name(PORT_LINK_NAME + ".new")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(os.ttyname(self._slave))
        tmp.replace(self.link)
        _log.info("emulated Dynamixel adapter plugged in: %s -> %s", self.link,
                  os.ttyname(self._slave))

    def _unplug(self) -> None:
        if self._link_dir is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        if self._master >= 0:
            _log.info("emulated Dynamixel adapter unplugged: %s", self.link)
        self._master = self._slave = -1

    def _apply(self) -> None:
        """Plug or unplug as asked (on the thread: the pty's descriptors are its own)."""
        if self._want_plugged and not self.plugged:
            self._plug()
        elif not self._want_plugged and self.plugged:
            self._unplug()

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
                watch = [self._wake_r] + ([self._master] if self.plugged else [])
                ready, _, _ = select.select(watch, [], [], IDLE_WAKE_S)
                if self._wake_r in ready:
                    os.read(self._wake_r, 64)
                    if self._stopping.is_set():
                        break
                    self._apply()
                    self._applied.set()
                    buf.clear()
                    continue
                last, woke = woke, time.monotonic()
                stalled = woke - last - IDLE_WAKE_S
                if wall and stalled > STALL_S:
                    # A motor's watchdog counts silence on the wire; while this thread did
                    # not run, the host's packets waited in the pty unseen. That time is not
                    # the host's silence: a loaded test host must not trip the watchdog.
                    emu.pause_watchdogs(stalled)
                now = emu.clock()
                if self.plugged and self._master in ready:
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
                    if self._error_next:
                        # Inside the transaction: its client now waits for the reply.
                        self._error_next = False
                        _log.info("emulated Dynamixel line: I/O error inside a transaction")
                        self._unplug()
                        self._plug()
                        buf.clear()
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
                if self._stopping.is_set():
                    return False
                if not self._want_plugged:
                    return True  # unplugged meanwhile: the rest is lost with the line
            try:
                os.write(self._master, packet)
            except BlockingIOError:
                _log.warning("emulated motor %d: pty full, status packet dropped", motor_id)
            due = max(due, clock())
        return True
