"""The Dynamixel Protocol 2.0 packet codec: header ``FF FF FD 00``, CRC-16 (poly 0x8005),
byte stuffing both ways, instruction packets parsed off a byte stream."""

from __future__ import annotations

from dataclasses import dataclass

BROADCAST_ID = 0xFE
HEADER = b"\xff\xff\xfd\x00"
MAX_PACKET_LENGTH = 1024

INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REG_WRITE = 0x04
INST_ACTION = 0x05
INST_REBOOT = 0x08
INST_STATUS = 0x55
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83
INST_FAST_SYNC_READ = 0x8A
INST_BULK_READ = 0x92
INST_BULK_WRITE = 0x93

ERR_RESULT_FAIL = 0x01
ERR_INSTRUCTION = 0x02
ERR_CRC = 0x03
ERR_DATA_RANGE = 0x04
ERR_DATA_LENGTH = 0x05
ERR_DATA_LIMIT = 0x06
ERR_ACCESS = 0x07
ERR_ALERT = 0x80


def _make_crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _make_crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16 of Protocol 2.0 (poly 0x8005, initial 0, not reflected), as the SDK computes it."""
    for byte in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes | bytearray) -> bytes:
    """Insert an ``FD`` after every ``FF FF FD`` of a packet body (instruction to last param)."""
    out = bytearray()
    prev2 = prev1 = 0
    for byte in body:
        out.append(byte)
        if byte == 0xFD and prev1 == 0xFF and prev2 == 0xFF:
            out.append(0xFD)
        prev2, prev1 = prev1, byte
    return bytes(out)


def unstuff(body: bytes | bytearray) -> bytes:
    """Undo :func:`stuff`: ``FF FF FD FD`` becomes ``FF FF FD``."""
    out = bytearray()
    i = 0
    while i < len(body):
        byte = body[i]
        out.append(byte)
        if (byte == 0xFD and len(out) >= 3 and out[-2] == 0xFF and out[-3] == 0xFF
                and i + 1 < len(body) and body[i + 1] == 0xFD):
            i += 1
        i += 1
    return bytes(out)


def encode_packet(packet_id: int, body: bytes | bytearray) -> bytes:
    """A whole Protocol 2.0 packet: header, ID, length, stuffed body, CRC."""
    stuffed = stuff(body)
    length = len(stuffed) + 2
    packet = HEADER + bytes((packet_id, length & 0xFF, length >> 8)) + stuffed
    return packet + crc16(packet).to_bytes(2, "little")


@dataclass(frozen=True)
class Instruction:
    """One parsed instruction packet (body unstuffed)."""

    motor_id: int
    instruction: int
    params: bytes
    crc_ok: bool


def parse_packet(buf: bytearray) -> Instruction | None:
    """Take the first complete packet off the front of ``buf``; drop garbage before it.

    Returns None when no complete packet is there yet (``buf`` then starts with a possible
    header, or holds at most the last three bytes of garbage).
    """
    while True:
        idx = buf.find(HEADER)
        if idx < 0:
            del buf[: max(0, len(buf) - 3)]
            return None
        del buf[:idx]
        if len(buf) < 7:
            return None
        length = buf[5] | (buf[6] << 8)
        if length < 3 or length > MAX_PACKET_LENGTH:
            del buf[:1]
            continue
        total = 7 + length
        if len(buf) < total:
            return None
        packet = bytes(buf[:total])
        del buf[:total]
        crc_ok = crc16(packet[:-2]) == int.from_bytes(packet[-2:], "little")
        body = unstuff(packet[7:-2])
        return Instruction(packet[4], body[0], body[1:], crc_ok)
