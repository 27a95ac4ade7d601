"""The Protocol 2.0 emulator, driven by the real dynamixel_sdk over a real pty."""

from __future__ import annotations

import importlib.util
import math
import os
import threading
import time
from pathlib import Path

import dynamixel_sdk as sdk
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.hw.control_table import XM430_W350
from edge.sim.dxl_emulator import (
    INST_SYNC_READ,
    DxlEmulator,
    crc16,
    encode_packet,
    parse_packet,
    stuff,
    unstuff,
)

IDS = (11, 12, 13, 14, 15)
BROADCAST = 0xFE


class ManualClock:
    """A clock the test moves by hand, so motion checks are exact and never flaky."""

    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


# How long an answer is waited for. The stock SDK gives up after about 34 ms, and the
# emulator's thread shares this process's interpreter with the test (and two cores with the
# other test workers): a loaded host held it past that (a ping answered, the next read
# "no status packet"). These tests check the protocol; the latency test measures time.
PACKET_TIMEOUT_MS = 500.0


class RecordingPortHandler(sdk.PortHandler):
    """The stock SDK port handler, keeping every byte it wrote and read, waiting
    ``PACKET_TIMEOUT_MS`` for an answer."""

    def __init__(self, port_name: str) -> None:
        super().__init__(port_name)
        self.written = bytearray()
        self.read = bytearray()

    def setPacketTimeout(self, packet_length):
        super().setPacketTimeout(packet_length)
        self.packet_timeout = max(self.packet_timeout, PACKET_TIMEOUT_MS)

    def writePort(self, packet):
        self.written += bytes(packet)
        return super().writePort(packet)

    def readPort(self, length):
        data = super().readPort(length)
        self.read += data
        return data


def _start(**kwargs) -> DxlEmulator:
    emu = DxlEmulator(**kwargs).start()
    for i in IDS:
        emu.set_register(i, "Return Delay Time", 0)
    return emu


@pytest.fixture
def emu():
    emulator = _start()
    yield emulator
    emulator.stop()


@pytest.fixture
def clocked():
    clock = ManualClock()
    emulator = _start(clock=clock)
    yield emulator, clock
    emulator.stop()


@pytest.fixture
def port(emu):
    handler = RecordingPortHandler(emu.port)
    assert handler.openPort()
    yield handler
    handler.closePort()


def _open(emulator: DxlEmulator) -> sdk.PortHandler:
    handler = RecordingPortHandler(emulator.port)
    assert handler.openPort()
    return handler


PH = sdk.PacketHandler(2.0)


def _ok(result_error):
    result, error = result_error[-2:]
    assert result == sdk.COMM_SUCCESS, PH.getTxRxResult(result)
    assert error == 0, PH.getRxPacketError(error)
    return result_error[0] if len(result_error) == 3 else None


# ------------------------------------------------------------------ control table and framing


def _model_file(name: str) -> Path | None:
    spec = importlib.util.find_spec("dynamixel_easy_sdk")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))) / "control_table" / name
    return path if path.exists() else None


def test_control_table_matches_the_sdk_model_file():
    path = _model_file("xm430_w350.model")
    if path is None:
        pytest.skip("dynamixel_easy_sdk control tables not installed")
    lines = path.read_text().splitlines()
    start = lines.index("[control table]") + 2  # skip the column header
    model: dict[str, tuple[int, int]] = {}
    for line in lines[start:]:
        if not line.strip():
            break
        address, size, name = line.split("\t")
        model.setdefault(name, (int(address), int(size)))
    aliases = {"Secondary ID": "Secondary(Shadow) ID"}
    for reg in XM430_W350.values():
        assert model[aliases.get(reg.name, reg.name)] == (reg.address, reg.size), reg.name
    ours = {aliases.get(n, n) for n in XM430_W350}
    uncovered = [n for n, (a, _) in model.items() if a < 168 and n not in ours]
    assert uncovered == []
    numbers = _model_file("dynamixel.model")
    assert numbers is not None
    assert f"{XM430_W350.model_number}\txm430_w350.model" in numbers.read_text().splitlines()


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=0, max_size=64))
def test_crc_matches_the_sdk(data):
    assert crc16(data) == PH.updateCRC(0, list(data), len(data))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from([0x00, 0x01, 0xFD, 0xFF]), min_size=1, max_size=40))
def test_stuffing_matches_the_sdk(body):
    # The SDK's own framing of the same body: header, ID 1, length, body, CRC.
    length = len(body) + 2
    packet = [0xFF, 0xFF, 0xFD, 0x00, 1, length & 0xFF, length >> 8, *body, 0, 0]
    packet = PH.addStuffing(packet)
    total = packet[5] + (packet[6] << 8) + 7
    packet = packet[:total]
    crc = PH.updateCRC(0, packet, total - 2)
    packet[-2:] = [crc & 0xFF, crc >> 8]
    assert encode_packet(1, bytes(body)) == bytes(packet)
    assert unstuff(stuff(bytes(body))) == bytes(body)
    buf = bytearray(b"\x00\xff" + bytes(packet))
    parsed = parse_packet(buf)
    assert parsed is not None and parsed.crc_ok and buf == b""
    assert bytes([parsed.instruction]) + parsed.params == bytes(body)


# ------------------------------------------------------------------ instructions


def test_ping_reports_model_and_firmware(emu, port):
    for i in IDS:
        assert _ok(PH.ping(port, i)) == 1020
        assert _ok(PH.read1ByteTxRx(port, i, 6)) == 48
    found, result = PH.broadcastPing(port)
    assert result == sdk.COMM_SUCCESS
    assert found == {i: [1020, 48] for i in IDS}


def test_read_write_round_trip_through_byte_stuffing(emu, port):
    # Goal PWM -1 then Goal Current 253 is FF FF FD 00 on the wire: the header pattern.
    value = 0x00FDFFFF
    # Sent stuffed, as the protocol says (built here: dynamixel-sdk 4.1.0's txPacket drops
    # addStuffing's result whenever stuffing lengthens the packet, so it sends it unstuffed).
    body = bytes((0x03, 100, 0)) + value.to_bytes(4, "little")
    packet = encode_packet(11, body)
    assert b"\xff\xff\xfd\xfd" in packet
    port.clearPort()
    port.writePort(packet)
    port.setPacketTimeout(11)
    status, result = PH.rxPacket(port, False)
    assert result == sdk.COMM_SUCCESS and status[8] == 0
    assert emu.get_register(11, "Goal PWM") == -1
    assert emu.get_register(11, "Goal Current") == 253
    # What the SDK sends (unstuffed today) is framed by its length and accepted too.
    _ok(PH.write4ByteTxRx(port, 12, 100, value))
    assert emu.get_register(12, "Goal Current") == 253
    port.read.clear()
    assert _ok(PH.read4ByteTxRx(port, 11, 100)) == value
    assert b"\xff\xff\xfd\xfd" in port.read[7:]  # stuffed by us, unstuffed by the SDK


def test_sync_write_then_sync_fast_sync_and_bulk_read_all_five(emu, port):
    for i in IDS:
        _ok(PH.write1ByteTxRx(port, i, 64, 1))
    goals = {i: 1000 + 100 * i for i in IDS}
    writer = sdk.GroupSyncWrite(port, PH, 116, 4)
    for i, goal in goals.items():
        assert writer.addParam(i, list(goal.to_bytes(4, "little")))
    assert writer.txPacket() == sdk.COMM_SUCCESS
    deadline = time.monotonic() + 3.0
    reader = sdk.GroupSyncRead(port, PH, 126, 10)
    for i in IDS:
        reader.addParam(i)
    while True:
        assert reader.txRxPacket() == sdk.COMM_SUCCESS
        present = {i: reader.getData(i, 132, 4) for i in IDS}
        if present == goals or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert present == goals
    assert reader.fastSyncRead() == sdk.COMM_SUCCESS
    assert {i: reader.getData(i, 132, 4) for i in IDS} == goals
    bulk = sdk.GroupBulkRead(port, PH)
    for i in IDS:
        assert bulk.addParam(i, 132 if i % 2 else 11, 4 if i % 2 else 1)
    assert bulk.txRxPacket() == sdk.COMM_SUCCESS
    assert bulk.getData(11, 132, 4) == goals[11]
    assert bulk.getData(12, 11, 1) == 3


def test_broadcast_write_changes_every_motor_and_gets_no_reply(emu, port):
    assert PH.write1ByteTxRx(port, BROADCAST, 65, 1) == (sdk.COMM_SUCCESS, 0)
    time.sleep(0.02)
    assert port.getBytesAvailable() == 0
    assert all(emu.get_register(i, "LED") == 1 for i in IDS)


def test_reg_write_waits_for_action(emu, port):
    _ok(PH.regWriteTxRx(port, 11, 65, 1, [1]))
    _ok(PH.regWriteTxRx(port, 12, 65, 1, [1]))
    assert emu.get_register(11, "LED") == 0
    assert emu.get_register(11, "Registered Instruction") == 1
    assert PH.action(port, BROADCAST) == sdk.COMM_SUCCESS
    time.sleep(0.02)
    assert emu.get_register(11, "LED") == 1 and emu.get_register(12, "LED") == 1
    assert emu.get_register(13, "LED") == 0


def test_eeprom_write_refused_while_torque_on(emu, port):
    _ok(PH.write1ByteTxRx(port, 15, 64, 1))
    result, error = PH.write1ByteTxRx(port, 15, 11, 5)
    assert result == sdk.COMM_SUCCESS and error == 7  # Access error
    assert "not available" in PH.getRxPacketError(error)
    assert emu.get_register(15, "Operating Mode") == 3
    _ok(PH.write1ByteTxRx(port, 15, 64, 0))
    _ok(PH.write1ByteTxRx(port, 15, 11, 5))
    assert emu.get_register(15, "Operating Mode") == 5


def test_write_limits(emu, port):
    assert PH.write1ByteTxRx(port, 11, 11, 2) == (sdk.COMM_SUCCESS, 4)  # no such mode
    assert PH.write2ByteTxRx(port, 11, 102, 1194) == (sdk.COMM_SUCCESS, 4)  # static range
    _ok(PH.write2ByteTxRx(port, 11, 38, 300))
    assert PH.write2ByteTxRx(port, 11, 102, 301) == (sdk.COMM_SUCCESS, 6)  # > Current Limit
    assert PH.write1ByteTxRx(port, 11, 132, 0) == (sdk.COMM_SUCCESS, 7)  # read-only
    assert PH.write2ByteTxRx(port, 11, 117, 0) == (sdk.COMM_SUCCESS, 7)  # inside a register


def test_status_return_level_one_answers_reads_only(emu, port):
    _ok(PH.write1ByteTxRx(port, 12, 68, 1))
    assert PH.read1ByteTxRx(port, 12, 68)[:2] == (1, sdk.COMM_SUCCESS)
    assert PH.write1ByteTxRx(port, 12, 65, 1)[0] == sdk.COMM_RX_TIMEOUT
    assert emu.get_register(12, "LED") == 1


# Long enough for the late reply to a timed-out ping to arrive (10 ms of reply latency).
LATE_REPLY_S = 0.1


def test_return_delay_and_reply_latency_are_honoured(emu, port):
    # The best of several pings, a timed-out one not counted: a loaded host now and then
    # holds the emulator's thread past PACKET_TIMEOUT_MS.
    # The reply to a timed-out ping still comes, late: it is waited out and discarded, or
    # the next ping would take it for its own and look faster than the latency allows (seen
    # beside a CPU hog: 0.46 ms with 10 ms of reply latency).
    def ping_s() -> float:
        t0 = time.perf_counter()
        answered = PH.ping(port, 11)[1] == sdk.COMM_SUCCESS
        if answered:
            return time.perf_counter() - t0
        time.sleep(LATE_REPLY_S)
        port.clearPort()
        return math.inf

    fast = min(ping_s() for _ in range(5))
    emu.set_register(11, "Return Delay Time", 250)
    slow = min(ping_s() for _ in range(5))
    emu.reply_latency_s = 0.01
    slower = min(ping_s() for _ in range(5))
    print(f"ping: {fast * 1e3:.2f} ms at Return Delay Time 0, {slow * 1e3:.2f} ms at 250, "
          f"{slower * 1e3:.2f} ms with 10 ms reply latency")
    assert max(fast, slow, slower) < math.inf, "no ping answered"
    assert slow >= 0.0005 and slower >= 0.010


def test_ping_id_and_id_change(emu, port):
    _ok(PH.write1ByteTxRx(port, 14, 7, 21))
    assert PH.ping(port, 14)[1] == sdk.COMM_RX_TIMEOUT
    assert _ok(PH.ping(port, 21)) == 1020


# ------------------------------------------------------------------ motion


def _write_goal(port, motor_id: int, goal: int) -> None:
    _ok(PH.write4ByteTxRx(port, motor_id, 116, goal))


def test_time_based_profile(clocked):
    emu, clock = clocked
    port = _open(emu)
    try:
        _ok(PH.write1ByteTxRx(port, 11, 10, 4))  # time-based profile
        _ok(PH.write4ByteTxRx(port, 11, 112, 400))  # 400 ms to the goal
        _ok(PH.write4ByteTxRx(port, 11, 108, 100))  # 100 ms acceleration
        _ok(PH.write1ByteTxRx(port, 11, 64, 1))
        _write_goal(port, 11, 3048)
        clock.t += 0.05
        # Half of the acceleration phase: a quarter of its distance (v = 1000 / 0.3 s).
        assert emu.true_position(11) == pytest.approx(2048 + 0.5 * (1000 / 0.3) / 0.1 * 0.05 ** 2,
                                                      abs=3)
        clock.t += 0.15
        assert emu.true_position(11) == pytest.approx(2548, abs=3)  # half way at half time
        assert _ok(PH.read1ByteTxRx(port, 11, 122)) == 1  # Moving
        clock.t += 0.25
        assert emu.true_position(11) == 3048
        assert _ok(PH.read1ByteTxRx(port, 11, 122)) == 0
        assert _ok(PH.read4ByteTxRx(port, 11, 132)) == 3048
    finally:
        port.closePort()


def test_velocity_based_profile(clocked):
    emu, clock = clocked
    port = _open(emu)
    try:
        _ok(PH.write4ByteTxRx(port, 12, 112, 64))  # 64 * 0.229 rev/min = 1000.5 raw/s
        _ok(PH.write1ByteTxRx(port, 12, 64, 1))
        _write_goal(port, 12, 1048)
        clock.t += 0.5
        assert emu.true_position(12) == pytest.approx(2048 - 500.2, abs=2)
        velocity = sdk.PacketHandler(2.0).read4ByteTxRx(port, 12, 128)[0]
        assert velocity - (1 << 32) == -64
        clock.t += 0.6
        assert emu.true_position(12) == 1048
    finally:
        port.closePort()


def test_gripper_stalls_on_the_load_and_reports_it(clocked):
    contact_raw = 2000.0
    stiffness_ma_per_raw = 10.0
    clock = ManualClock()

    def load(motor_id: int, position_raw: float, t: float) -> float:
        if motor_id != 15:
            return 0.0
        return max(0.0, (contact_raw - position_raw) * stiffness_ma_per_raw)

    emu = _start(clock=clock, load=load)
    port = _open(emu)
    try:
        _ok(PH.write1ByteTxRx(port, 15, 11, 5))  # current-based position
        _ok(PH.write2ByteTxRx(port, 15, 102, 100))  # cap 269 mA
        _ok(PH.write4ByteTxRx(port, 15, 112, 32))  # about 500 raw/s
        _ok(PH.write1ByteTxRx(port, 15, 64, 1))
        _write_goal(port, 15, 1500)
        for _ in range(20):
            clock.t += 0.1
            emu.true_position(15)
        stall = emu.true_position(15)
        assert stall == pytest.approx(contact_raw - 26.9, abs=1.5)
        current = sdk.PacketHandler(2.0).read2ByteTxRx(port, 15, 126)[0] - (1 << 16)
        assert current * 2.69 == pytest.approx(-269, abs=6)  # closing draws negative current
        assert _ok(PH.read1ByteTxRx(port, 15, 122)) == 0  # not moving: stalled
        # A stronger cap pushes further in.
        _ok(PH.write2ByteTxRx(port, 15, 102, 200))
        clock.t += 0.2
        assert emu.true_position(15) == pytest.approx(contact_raw - 53.8, abs=1.5)
        # Take the object away: the profile resumes to the goal.
        contact_raw = -1e9
        clock.t += 2.0
        assert emu.true_position(15) == 1500
    finally:
        port.closePort()
        emu.stop()


def test_watchdog_trip_and_recovery(clocked):
    emu, clock = clocked
    port = _open(emu)
    try:
        _ok(PH.write1ByteTxRx(port, 13, 64, 1))
        _ok(PH.write1ByteTxRx(port, 13, 98, 5))  # 100 ms
        _write_goal(port, 13, 3000)  # about 0.3 s at the default speed
        clock.t += 0.09
        _ok(PH.read4ByteTxRx(port, 13, 132))  # any packet feeds it
        clock.t += 0.09
        assert emu.get_register(13, "Bus Watchdog") == 5
        moved = emu.true_position(13)
        clock.t += 0.03  # 120 ms since the last packet: tripped at 100 ms
        stopped = emu.true_position(13)
        assert moved < stopped < 3000
        clock.t += 0.2
        assert emu.true_position(13) == stopped  # motion stopped...
        assert _ok(PH.read1ByteTxRx(port, 13, 64)) == 1  # ...torque stays on
        assert _ok(PH.read1ByteTxRx(port, 13, 98)) == 0xFF  # reads -1
        result, error = PH.write4ByteTxRx(port, 13, 116, 2048)
        assert (result, error) == (sdk.COMM_SUCCESS, 4)  # Data Range error
        _ok(PH.write1ByteTxRx(port, 13, 98, 0))
        _write_goal(port, 13, 2048)
        clock.t += 1.0
        assert emu.true_position(13) == 2048
    finally:
        port.closePort()


def test_a_stalled_emulator_thread_is_not_host_silence(emu, port):
    # The host keeps talking every 40 ms while the emulator's thread cannot run for 0.4 s
    # (a loaded test host): the packets wait in the pty, and the 100 ms watchdog must not
    # count that wait as the host's silence.
    _ok(PH.write1ByteTxRx(port, 13, 64, 1))
    _ok(PH.write1ByteTxRx(port, 13, 98, 5))  # 100 ms
    with emu._lock:  # the thread blocks on its next step of the motion model
        for _ in range(10):
            PH.write4ByteTxOnly(port, 13, 116, 2048)
            time.sleep(0.04)
    time.sleep(0.05)
    assert _ok(PH.read1ByteTxRx(port, 13, 98)) == 5  # armed, not tripped (-1)


# ------------------------------------------------------------------ faults and lifecycle


def test_missing_motor_does_not_answer(emu, port):
    emu.set_missing(13)
    assert PH.ping(port, 13)[1] == sdk.COMM_RX_TIMEOUT
    reader = sdk.GroupSyncRead(port, PH, 132, 4)
    for i in IDS:
        reader.addParam(i)
    assert reader.txRxPacket() == sdk.COMM_RX_TIMEOUT
    emu.set_missing(13, False)
    assert _ok(PH.ping(port, 13)) == 1020


def test_corrupted_crc_is_caught_by_the_sdk(emu, port):
    emu.corrupt_crc(12, 1)
    assert PH.read4ByteTxRx(port, 12, 132)[1] == sdk.COMM_RX_CORRUPT
    assert _ok(PH.read4ByteTxRx(port, 12, 132)) == 2048


def test_bad_instruction_crc_answers_crc_error(emu, port):
    packet = bytearray(encode_packet(11, bytes((0x02, 132, 0, 4, 0))))
    packet[-1] ^= 0xFF
    port.clearPort()
    port.writePort(packet)
    port.setPacketTimeout(11)
    status, result = PH.rxPacket(port, False)
    assert result == sdk.COMM_SUCCESS and status[8] == 3  # CRC error


def test_hardware_error_sets_alert_and_shuts_down(emu, port):
    _ok(PH.write1ByteTxRx(port, 14, 64, 1))
    emu.set_hardware_error(14, 0x20)  # overload
    value, result, error = PH.read1ByteTxRx(port, 14, 70)
    assert (value, result) == (0x20, sdk.COMM_SUCCESS)
    assert error & 0x80 and "Hardware error" in PH.getRxPacketError(error)
    assert PH.read1ByteTxRx(port, 14, 64)[0] == 0  # torque went off
    assert PH.write1ByteTxRx(port, 14, 64, 1) == (sdk.COMM_SUCCESS, 0x81)  # until reboot
    emu.set_hardware_error(14, 0)
    _ok(PH.write1ByteTxRx(port, 14, 64, 1))


def test_sync_read_order_is_logged(emu, port):
    reader = sdk.GroupSyncRead(port, PH, 132, 4)
    for i in IDS:
        reader.addParam(i)
    assert reader.txRxPacket() == sdk.COMM_SUCCESS
    last = emu.received[-1]
    assert last.instruction == INST_SYNC_READ and last.motor_id == BROADCAST
    assert list(last.params[4:]) == list(IDS)


def _open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


def test_start_stop_leaks_no_thread_or_fd():
    before_fds = _open_fds()
    before_threads = threading.active_count()
    for _ in range(3):
        with DxlEmulator() as emulator:
            handler = sdk.PortHandler(emulator.port)
            assert handler.openPort()
            # (up to three tries: a loaded host can hold the new emulator past the SDK timeout)
            assert any(PH.ping(handler, 11)[1] == sdk.COMM_SUCCESS for _ in range(3))
            handler.closePort()
    assert threading.active_count() == before_threads
    assert _open_fds() == before_fds


def test_every_stop_is_checked_against_the_true_position():
    # A stop is a goal short of the one the gripper is closing to, written while it closes;
    # the emulator measures where it lands against the true position at arrival.
    clock = ManualClock()
    emu = _start(clock=clock)
    port = _open(emu)
    try:
        _ok(PH.write1ByteTxRx(port, 15, 11, 5))  # current-based position
        _ok(PH.write4ByteTxRx(port, 15, 112, 32))  # about 500 raw/s
        _ok(PH.write1ByteTxRx(port, 15, 64, 1))
        _write_goal(port, 15, 1000)  # closing (decreasing raw), from 2048
        clock.t += 0.5
        true = emu.true_position(15)
        assert 1000 < true < 2048
        _write_goal(port, 15, round(true) - 2)  # a stop 2 counts past it: kept
        assert emu.stops_behind == 0
        (check,) = emu.stop_checks
        assert check.motor_id == 15 and check.ahead_raw == pytest.approx(2, abs=0.5)
        _write_goal(port, 15, 1000)  # closing again
        clock.t += 0.1
        true = emu.true_position(15)
        _write_goal(port, 15, round(true) + 3)  # a stop behind it: it backs off
        assert emu.stops_behind == 1
        assert emu.stop_checks[-1].ahead_raw == pytest.approx(-3, abs=0.5)
        _write_goal(port, 15, 500)  # not a stop: closing further
        _write_goal(port, 11, 100)  # nor a joint's goal (position mode)
        assert len(emu.stop_checks) == 2
    finally:
        port.closePort()
        emu.stop()
