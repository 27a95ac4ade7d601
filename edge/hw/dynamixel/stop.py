"""The stop policy: where the gripper's stop puts Goal Position, and what a stop records.

The stop is one WRITE of Goal Position: the goal comes from the motor's last state read
(position and velocity, stamped when the read went out), extrapolated to the moment of the
write, plus the squeeze. Only a state too old, or one read before the motor's last goal,
makes it read Present Position first (counted in ``DynamixelBus.stop_fallbacks``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import dynamixel_sdk as sdk

from edge.hw.dynamixel.transactions import GOAL_POSITION, PRESENT_POSITION, Transactions

# The stop's goal is extrapolated from a state read no older than this. The press reads the
# gripper after every second tactile frame while closing (16 ms at 125 Hz, 20 ms at
# 100 Hz: edge.runtime.press.GRIPPER_TRACE_FRAMES); 50 ms rides out one late or lost read.
# At a constant velocity the estimate is then off by less than one count: 0.5 for Present
# Position's resolution, 0.4 for Present Velocity's (0.5 of its 15.6 raw/s unit over 50 ms),
# inside the default 2-count squeeze. What a state cannot show is a change of velocity
# after it was read: slowing down (contact, stall) only puts the goal further in the
# closing direction (more squeeze, capped by Goal Current); speeding up happens as a motion
# starts, hence STOP_STATE_SETTLE_S.
STOP_STATE_MAX_AGE_S = 0.05
# A state read sooner than this after the motor's last goal write may show it still
# accelerating (a real XM430 takes a few ms to reach its profile velocity): not used.
STOP_STATE_SETTLE_S = 0.01


@dataclass(frozen=True)
class StopRecord:
    """What one stop did, and when (the bus clock).

    ``t_submit``: the stop handed to the bus (event loop); ``t_start``: the bus thread began
    it; ``t_write_call``: its Goal Position packet's write call (the packet goes to the
    kernel from here: the stop's time); ``t_written``: that call returned. ``in_flight_s``:
    how long a transaction already on the wire at the hand-over still took. ``fast``: one
    WRITE from a state ``state_age_s`` old; else ``fallback`` says why it read first.
    """

    goal: int
    fast: bool
    state_age_s: float | None
    fallback: str | None
    t_submit: float
    t_start: float
    t_write_call: float
    t_written: float
    in_flight_s: float


def stop_goal(tx: Transactions, motor_id: int, offset_raw: int,
              max_age_s: float | None) -> tuple[int, float | None, str | None]:
    """(goal, age of the state used, why the state was not used); on the bus's owner.
    ``max_age_s`` None: read Present Position, whatever was seen."""
    now = tx.clock()
    seen = tx.seen.get(motor_id)
    goal_t = tx.goal_t.get(motor_id, -math.inf)
    if max_age_s is None:
        why = "asked to read"
    elif seen is None:
        why = "no state read yet"
    elif now - seen.t > max_age_s:
        why = f"state {1e3 * (now - seen.t):.0f} ms old"
    elif seen.t < goal_t + STOP_STATE_SETTLE_S:
        why = "state read before the motor's last goal had settled"
    else:
        estimate = seen.position + seen.velocity_raw_s * (now - seen.t)
        return round(estimate) + offset_raw, now - seen.t, None
    return tx.read(motor_id, PRESENT_POSITION) + offset_raw, None, why


# Protocol 2.0's header: where it appears inside a packet the SDK stuffs a byte after it.
_HEADER = b"\xff\xff\xfd"
_PKT_LENGTH_L = 5


def _crc_table() -> tuple[int, ...]:
    # The SDK's CRC-16 table, as its own updateCRC gives it for one byte from 0.
    ph = sdk.Protocol2PacketHandler()
    return tuple(ph.updateCRC(0, [b], 1) for b in range(256))


_CRC_TABLE = _crc_table()


class StopPacket:
    """The stop's WRITE of Goal Position to one motor, built ahead but for its goal.

    The SDK builds every packet in Python as it sends it (a copy for byte stuffing, a CRC
    over the whole packet). Only the stop's 4 goal bytes are unknown until the stop, so
    what comes before them, and the CRC over it, is computed once: at the stop, 4 CRC steps
    and a concatenation. :meth:`build` gives the bytes the SDK's ``write4ByteTxRx`` sends
    (``tests/hw/test_dxl_stop_packet.py``).
    """

    def __init__(self, motor_id: int) -> None:
        length = GOAL_POSITION.size + 5  # instruction, address (2), data, CRC (2)
        head = [0xFF, 0xFF, 0xFD, 0x00, motor_id, length & 0xFF, length >> 8, sdk.INST_WRITE,
                GOAL_POSITION.address & 0xFF, GOAL_POSITION.address >> 8]
        self.motor_id = motor_id
        self._head = bytes(head)
        self._crc = sdk.Protocol2PacketHandler().updateCRC(0, head, len(head))

    def build(self, goal: int) -> bytes | None:
        """The packet writing ``goal``; None where it needs byte stuffing (the goal's bytes
        hold the header), which is left to the SDK."""
        data = GOAL_POSITION.encode(goal)
        crc = self._crc
        for b in data:
            crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
        packet = self._head + data
        if packet.find(_HEADER, _PKT_LENGTH_L) >= 0:
            return None
        return packet + crc.to_bytes(2, "little")
