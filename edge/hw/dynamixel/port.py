"""The SDK's port and packet handlers as the bus uses them, and the USB latency timer.

The SDK waits for status packets by spinning in pure Python, which holds the GIL and delays
the event loop by up to the interpreter's switch interval (5 ms). :class:`BlockingPortHandler`
replaces the spin: its reads wait in ``select()`` (GIL released) for the bytes or the SDK's own
packet deadline. ``tests/hw/test_dxl_bus.py`` measures the difference.
"""

from __future__ import annotations

import logging
import os
import select
import time
from collections.abc import Callable
from pathlib import Path

import dynamixel_sdk as sdk

_log = logging.getLogger(__name__)

LATENCY_TIMER_DIR = Path("/sys/bus/usb-serial/devices")
LATENCY_TIMER_UDEV_RULE = (
    'ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", ATTR{latency_timer}="1"'
)
# What the SDK's packet timeouts assume (dynamixel_sdk.port_handler.LATENCY_TIMER).
SDK_LATENCY_TIMER_MS = 16.0
# A pseudo-terminal is no USB adapter: what answers on it (the emulated robot, or a bridge to
# a bus elsewhere) is a process sharing the host or a network, whose reply can come tens of
# milliseconds late on a busy host. A daemon started beside a loaded test run once missed
# the SDK's 34 ms wait twice on one read and refused to start. Replies on a pty are waited
# for as through a 100 ms latency timer (about 0.2 s a packet); a missing motor takes that
# much longer to name.
PTY_LATENCY_TIMER_MS = 100.0
# Past the SDK's packet deadline, so the SDK's own timeout check fires after our wait.
_READ_DEADLINE_SLACK_S = 0.0002
# Status packet offsets (dynamixel_sdk.protocol2_packet_handler).
_PKT_ID, _PKT_LENGTH_L, _PKT_LENGTH_H = 4, 5, 6


def latency_timer_path(port: str, timer_dir: Path = LATENCY_TIMER_DIR) -> Path:
    """Where the kernel shows the USB latency timer of serial ``port`` (by-id links
    followed)."""
    return timer_dir / Path(os.path.realpath(port)).name / "latency_timer"


def read_latency_timer(path: Path) -> int | None:
    """The latency timer in ms; None when there is none (not a USB serial adapter). Raises
    OSError or ValueError when it cannot be read."""
    try:
        return int(path.read_text().strip())
    except FileNotFoundError:
        return None


class BlockingPortHandler(sdk.PortHandler):
    """A ``PortHandler`` whose reads block in ``select()`` instead of spinning.

    The SDK's receive loop calls ``readPort`` until the packet is complete or
    ``isPacketTimeout()``; the stock handler returns at once (pyserial timeout 0), so the loop
    spins holding the GIL. Here ``readPort`` first waits, GIL released, until a byte is
    readable or the SDK's packet deadline passes, then returns what is there. The SDK's
    deadlines stay its own; ``latency_timer_ms`` replaces its hard-coded 16 ms in them: on a
    pseudo-terminal ``PTY_LATENCY_TIMER_MS``, on a USB adapter its real latency timer once
    the driver has read it.
    """

    def __init__(self, port_name: str) -> None:
        super().__init__(port_name)
        self.latency_timer_ms = (PTY_LATENCY_TIMER_MS
                                 if os.path.realpath(port_name).startswith("/dev/pts/")
                                 else SDK_LATENCY_TIMER_MS)
        # Monotonic time of the last write call (the packet goes to the kernel from here:
        # the stop latency ends here), and when that call returned (later by the system
        # call, and by any wait of this thread for a CPU or the GIL after it).
        self.write_call_t = 0.0
        self.last_write_t = 0.0
        # Called on the bus thread after each write with (its time, the packet's first 8
        # bytes: header, ID, length, instruction): a benchmark's probe.
        self.on_write: Callable[[float, bytes], None] | None = None

    def writePort(self, packet) -> int:
        self.write_call_t = time.monotonic()
        written = super().writePort(packet)
        self.last_write_t = time.monotonic()
        if self.on_write is not None:
            self.on_write(self.last_write_t, bytes(packet[:8]))
        return written

    def setPacketTimeout(self, packet_length: int) -> None:
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = (self.tx_time_per_byte * packet_length
                               + self.latency_timer_ms * 2.0 + 2.0)

    def readPort(self, length: int) -> bytes:
        if length <= 0:
            return b""
        remaining_s = (self.packet_timeout - self.getTimeSinceStart()) / 1000.0
        if remaining_s > 0:
            select.select([self.ser.fileno()], [], [], remaining_s + _READ_DEADLINE_SLACK_S)
        return self.ser.read(length)


class CheckedPacketHandler(sdk.Protocol2PacketHandler):
    """The SDK's Protocol 2.0 packet handler, refusing status packets of the wrong size.

    The SDK takes the first status packet from the right ID as the answer. A motor that
    answers an instruction after the SDK gave up on it (a timeout) leaves that late packet
    on the wire while the next instruction waits for its own: a 10-byte sync-read status
    would be read as the 4-byte Present Position a stop is computed from. With
    ``expect_params`` set (by the bus thread, around each call), a status packet with a
    different number of parameters is skipped as stale and reading goes on until the
    packet deadline.
    """

    expect_params: int | None = None
    stale_skipped = 0
    # Every status packet the last transaction caused has been read: nothing is waiting on
    # the input, so a prepared packet (txPacket with bytes) needs no flush before it. Cleared
    # by every packet sent; set by the transaction that read all its replies
    # (Transactions.settle).
    settled = False

    def txPacket(self, port, txpacket):
        if not isinstance(txpacket, bytes):
            self.settled = False
            return super().txPacket(port, txpacket)
        # Built ahead, stuffed and with its CRC (edge.hw.dynamixel.stop.StopPacket): written
        # as it is. The SDK flushes the input before every packet so that a reply left
        # over cannot pass for this one's; with the line settled there is none to flush.
        if port.is_using:
            return sdk.COMM_PORT_BUSY
        port.is_using = True
        if not self.settled:
            port.clearPort()
        self.settled = False
        if port.writePort(txpacket) != len(txpacket):
            port.is_using = False
            return sdk.COMM_TX_FAIL
        return sdk.COMM_SUCCESS

    def rxPacket(self, port, fast_option):
        while True:
            packet, result = super().rxPacket(port, fast_option)
            if result != sdk.COMM_SUCCESS or self.expect_params is None:
                return packet, result
            # Status LENGTH = instruction + error + parameters + CRC (2).
            params = sdk.DXL_MAKEWORD(packet[_PKT_LENGTH_L], packet[_PKT_LENGTH_H]) - 4
            if params == self.expect_params:
                return packet, result
            self.stale_skipped += 1
            _log.warning("skipped a late status packet from motor %d (%d parameters, "
                         "expected %d): the answer to an instruction that timed out",
                         packet[_PKT_ID], params, self.expect_params)

