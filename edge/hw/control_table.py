"""The XM430-W350-T control table (Dynamixel Protocol 2.0): one register table, no I/O.

Addresses and sizes follow the ROBOTIS e-Manual and the ``xm430_w350.model`` file shipped in
the ``dynamixel-sdk`` wheel (``tests/sim/test_dxl_emulator.py`` cross-checks them). Defaults
are the factory values; ranges are the static limits a write is checked against (limits that
depend on other registers, such as Goal Current <= Current Limit, are the emulator's job).
The indirect address/data area (168..661) is not listed: nothing here uses it.
"""

from __future__ import annotations

import enum
import itertools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass


class Area(enum.Enum):
    """EEPROM registers keep their value over a power cycle and are writable only torque off."""

    EEPROM = "EEPROM"
    RAM = "RAM"


class Access(enum.Enum):
    R = "R"
    RW = "RW"


@dataclass(frozen=True)
class Register:
    name: str
    address: int
    size: int  # bytes, little endian on the wire
    access: Access
    area: Area
    default: int = 0
    signed: bool = False
    minimum: int | None = None  # static write range, inclusive; None: any value of the size
    maximum: int | None = None

    @property
    def writable(self) -> bool:
        return self.access is Access.RW

    @property
    def end(self) -> int:
        """One past the last byte of the register."""
        return self.address + self.size

    def encode(self, value: int) -> bytes:
        """``value`` as the little-endian bytes sent on the wire (two's complement if signed)."""
        bits = 8 * self.size
        if not -(1 << (bits - 1)) <= value < (1 << bits):
            raise ValueError(f"{self.name}: {value} does not fit in {self.size} bytes")
        return (value & ((1 << bits) - 1)).to_bytes(self.size, "little")

    def decode(self, data: bytes | bytearray | list[int]) -> int:
        """The register value from its wire bytes (sign applied if the register is signed)."""
        if len(data) != self.size:
            raise ValueError(f"{self.name}: expected {self.size} bytes, got {len(data)}")
        return int.from_bytes(bytes(data), "little", signed=self.signed)

    def from_unsigned(self, raw: int) -> int:
        """Apply the sign to an unsigned value as the SDK's readNByte calls return it."""
        bits = 8 * self.size
        if self.signed and raw >= 1 << (bits - 1):
            return raw - (1 << bits)
        return raw

    def to_unsigned(self, value: int) -> int:
        """The unsigned value the SDK's writeNByte calls expect."""
        return int.from_bytes(self.encode(value), "little")

    def check(self, value: int) -> bool:
        """Whether ``value`` is inside the static write range."""
        lo = self.minimum if self.minimum is not None else (
            -(1 << (8 * self.size - 1)) if self.signed else 0)
        hi = self.maximum if self.maximum is not None else (
            (1 << (8 * self.size - 1)) - 1 if self.signed else (1 << (8 * self.size)) - 1)
        return lo <= value <= hi


class ControlTable(Mapping[str, Register]):
    """Registers of one model by name, with lookup by address."""

    def __init__(self, model: str, model_number: int, registers: list[Register]) -> None:
        self.model = model
        self.model_number = model_number
        self._by_name = {r.name: r for r in registers}
        self._by_address = {r.address: r for r in registers}
        if len(self._by_name) != len(registers) or len(self._by_address) != len(registers):
            raise ValueError(f"{model}: duplicate register name or address")
        spans = sorted((r.address, r.end, r.name) for r in registers)
        for (_, end, name), (start, _, nxt) in itertools.pairwise(spans):
            if start < end:
                raise ValueError(f"{model}: {name} overlaps {nxt}")
        self.size = max(r.end for r in registers)

    def __getitem__(self, name: str) -> Register:
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"{self.model} has no register {name!r}") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self._by_name)

    def __len__(self) -> int:
        return len(self._by_name)

    def at(self, address: int) -> Register | None:
        """The register starting at ``address``, or None."""
        return self._by_address.get(address)

    def covering(self, address: int, length: int) -> list[Register] | None:
        """The registers exactly tiling ``[address, address + length)``, or None if the span
        starts or ends inside a register or crosses a reserved gap."""
        regs = []
        pos = address
        while pos < address + length:
            reg = self._by_address.get(pos)
            if reg is None:
                return None
            regs.append(reg)
            pos = reg.end
        return regs if pos == address + length and regs else None


_E, _M = Area.EEPROM, Area.RAM
_R, _RW = Access.R, Access.RW

# XM430-W350-T. Model Number 1020: the SDK's dynamixel.model maps 1020 to xm430_w350.model
# (1060 is the XL430-W250).
XM430_W350 = ControlTable("XM430-W350", 1020, [
    Register("Model Number", 0, 2, _R, _E, default=1020),
    Register("Model Information", 2, 4, _R, _E),
    Register("Firmware Version", 6, 1, _R, _E),
    Register("ID", 7, 1, _RW, _E, default=1, minimum=0, maximum=252),
    # 0: 9600, 1: 57600, 2: 115200, 3: 1M, 4: 2M, 5: 3M, 6: 4M, 7: 4.5M bps.
    Register("Baud Rate", 8, 1, _RW, _E, default=1, minimum=0, maximum=7),
    # Unit 2 us: the factory 250 adds 500 us before every status packet.
    Register("Return Delay Time", 9, 1, _RW, _E, default=250, minimum=0, maximum=254),
    # Bit 0: reverse direction; bit 2: time-based profile; bit 3: torque on by goal update.
    Register("Drive Mode", 10, 1, _RW, _E, default=0, minimum=0, maximum=13),
    # 0 current, 1 velocity, 3 position, 4 extended position, 5 current-based position, 16 PWM.
    Register("Operating Mode", 11, 1, _RW, _E, default=3, minimum=0, maximum=16),
    Register("Secondary ID", 12, 1, _RW, _E, default=255, minimum=0, maximum=255),
    Register("Protocol Type", 13, 1, _RW, _E, default=2, minimum=1, maximum=2),
    Register("Homing Offset", 20, 4, _RW, _E, signed=True, minimum=-1_044_479,
             maximum=1_044_479),
    Register("Moving Threshold", 24, 4, _RW, _E, default=10, minimum=0, maximum=1023),
    Register("Temperature Limit", 31, 1, _RW, _E, default=80, minimum=0, maximum=100),
    Register("Max Voltage Limit", 32, 2, _RW, _E, default=160, minimum=95, maximum=160),
    Register("Min Voltage Limit", 34, 2, _RW, _E, default=95, minimum=95, maximum=160),
    Register("PWM Limit", 36, 2, _RW, _E, default=885, minimum=0, maximum=885),
    # Unit 2.69 mA.
    Register("Current Limit", 38, 2, _RW, _E, default=1193, minimum=0, maximum=1193),
    # Unit 0.229 rev/min.
    Register("Velocity Limit", 44, 4, _RW, _E, default=200, minimum=0, maximum=1023),
    Register("Max Position Limit", 48, 4, _RW, _E, default=4095, minimum=0, maximum=4095),
    Register("Min Position Limit", 52, 4, _RW, _E, default=0, minimum=0, maximum=4095),
    Register("Shutdown", 63, 1, _RW, _E, default=52),
    Register("Torque Enable", 64, 1, _RW, _M, minimum=0, maximum=1),
    Register("LED", 65, 1, _RW, _M, minimum=0, maximum=1),
    # 0: answer PING only, 1: PING and READ, 2: every instruction.
    Register("Status Return Level", 68, 1, _RW, _M, default=2, minimum=0, maximum=2),
    Register("Registered Instruction", 69, 1, _R, _M),
    Register("Hardware Error Status", 70, 1, _R, _M),
    Register("Velocity I Gain", 76, 2, _RW, _M, default=1920, minimum=0, maximum=16383),
    Register("Velocity P Gain", 78, 2, _RW, _M, default=100, minimum=0, maximum=16383),
    Register("Position D Gain", 80, 2, _RW, _M, default=0, minimum=0, maximum=16383),
    Register("Position I Gain", 82, 2, _RW, _M, default=0, minimum=0, maximum=16383),
    Register("Position P Gain", 84, 2, _RW, _M, default=800, minimum=0, maximum=16383),
    Register("Feedforward 2nd Gain", 88, 2, _RW, _M, minimum=0, maximum=16383),
    Register("Feedforward 1st Gain", 90, 2, _RW, _M, minimum=0, maximum=16383),
    # Unit 20 ms; 0 disarms and clears a trip; -1 (0xFF) reads back after a trip.
    Register("Bus Watchdog", 98, 1, _RW, _M, signed=True, minimum=0, maximum=127),
    Register("Goal PWM", 100, 2, _RW, _M, signed=True, minimum=-885, maximum=885),
    Register("Goal Current", 102, 2, _RW, _M, signed=True, minimum=-1193, maximum=1193),
    Register("Goal Velocity", 104, 4, _RW, _M, signed=True, minimum=-1023, maximum=1023),
    # Velocity-based profile: unit 214.577 rev/min^2; time-based: acceleration time in ms.
    Register("Profile Acceleration", 108, 4, _RW, _M, minimum=0, maximum=32767),
    # Velocity-based profile: unit 0.229 rev/min; time-based: time to the goal in ms.
    Register("Profile Velocity", 112, 4, _RW, _M, minimum=0, maximum=32767),
    Register("Goal Position", 116, 4, _RW, _M, signed=True, minimum=-1_048_575,
             maximum=1_048_575),
    Register("Realtime Tick", 120, 2, _R, _M),
    Register("Moving", 122, 1, _R, _M),
    Register("Moving Status", 123, 1, _R, _M),
    Register("Present PWM", 124, 2, _R, _M, signed=True),
    Register("Present Current", 126, 2, _R, _M, signed=True),
    Register("Present Velocity", 128, 4, _R, _M, signed=True),
    Register("Present Position", 132, 4, _R, _M, signed=True),
    Register("Velocity Trajectory", 136, 4, _R, _M, signed=True),
    Register("Position Trajectory", 140, 4, _R, _M, signed=True),
    # Unit 0.1 V.
    Register("Present Input Voltage", 144, 2, _R, _M, default=120),
    Register("Present Temperature", 146, 1, _R, _M, default=30),
])

# Unit conversions of the XM430 registers.
CURRENT_MA_PER_UNIT = 2.69
RAW_PER_REV = 4096
VELOCITY_RPM_PER_UNIT = 0.229
ACCELERATION_RPM2_PER_UNIT = 214.577
# Raw position counts per second for one Profile/Goal Velocity unit (0.229 rev/min).
RAW_PER_S_PER_VELOCITY_UNIT = VELOCITY_RPM_PER_UNIT * RAW_PER_REV / 60.0
# Raw counts per second squared for one Profile Acceleration unit (214.577 rev/min^2).
RAW_PER_S2_PER_ACCELERATION_UNIT = ACCELERATION_RPM2_PER_UNIT * RAW_PER_REV / 3600.0
BUS_WATCHDOG_UNIT_S = 0.020
# The oldest XM430 firmware with every register the driver uses (Bus Watchdog came with 38).
MIN_FIRMWARE = 38
RETURN_DELAY_UNIT_S = 2e-6

# Drive Mode bits.
DRIVE_MODE_REVERSE = 0x01
DRIVE_MODE_TIME_BASED_PROFILE = 0x04

# Operating Mode values.
MODE_CURRENT = 0
MODE_VELOCITY = 1
MODE_POSITION = 3
MODE_EXTENDED_POSITION = 4
MODE_CURRENT_BASED_POSITION = 5
MODE_PWM = 16
OPERATING_MODES = frozenset({MODE_CURRENT, MODE_VELOCITY, MODE_POSITION,
                             MODE_EXTENDED_POSITION, MODE_CURRENT_BASED_POSITION, MODE_PWM})

# Hardware Error Status bits.
HARDWARE_ERROR_BITS = {
    0x01: "input voltage",
    0x04: "overheating",
    0x08: "motor encoder",
    0x10: "electrical shock",
    0x20: "overload",
}


def describe_hardware_error(status: int) -> str:
    """Hardware Error Status as words, e.g. ``"overload, overheating"``."""
    names = [name for bit, name in HARDWARE_ERROR_BITS.items() if status & bit]
    unknown = status & ~sum(HARDWARE_ERROR_BITS)
    if unknown:
        names.append(f"unknown bits 0x{unknown:02x}")
    return ", ".join(names) or "none"
