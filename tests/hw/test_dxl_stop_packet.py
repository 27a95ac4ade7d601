"""The stop's packet built ahead: the SDK's bytes, and the input flushed whenever a reply may
be left on it (against the emulator over a pty)."""

from __future__ import annotations

import asyncio
import logging
import random
import time

import dynamixel_sdk as sdk
import pytest

from edge.core.config import BusConfig
from edge.core.errors import MotorError
from edge.hw.dynamixel import DynamixelBus, transactions
from edge.hw.dynamixel.executor import STOP_HANDOVER_MAX_S, ThreadExecutor
from edge.hw.dynamixel.port import PTY_LATENCY_TIMER_MS, BlockingPortHandler
from edge.hw.dynamixel.stop import StopPacket
from edge.hw.dynamixel.transactions import GOAL_POSITION
from edge.sim.dxl_emulator import INST_WRITE, DxlEmulator

# A goal whose bytes (FF FF FD FF) hold the protocol's header: the SDK's way.
STUFFED_GOAL = -131073


class _Capture:
    """Just enough of a port for the SDK's txPacket: keeps what is written."""

    is_using = False

    def __init__(self) -> None:
        self.written = b""

    def clearPort(self) -> None:
        pass

    def writePort(self, packet) -> int:
        self.written = bytes(packet)
        return len(packet)


def _sdk_packet(motor_id: int, goal: int) -> bytes:
    port = _Capture()
    data = list(GOAL_POSITION.encode(goal))
    result = sdk.Protocol2PacketHandler().writeTxOnly(port, motor_id, GOAL_POSITION.address,
                                                      GOAL_POSITION.size, data)
    assert result == sdk.COMM_SUCCESS
    return port.written


def test_stop_packet_is_the_sdks():
    rng = random.Random(19)
    goals = [*range(-4096, 8192, 7), *(rng.randint(-(1 << 20), 1 << 20) for _ in range(3000)),
             0, 1, -1, 4095, (1 << 31) - 1, -(1 << 31)]
    built = 0
    for motor_id in (1, 11, 15, 0xFD):
        prepared = StopPacket(motor_id)
        for goal in goals:
            packet = prepared.build(goal)
            if packet is not None:
                assert packet == _sdk_packet(motor_id, goal), (motor_id, goal)
                built += 1
        assert prepared.build(STUFFED_GOAL) is None
    print(f"\n{built} stop packets equal to the SDK's; {STUFFED_GOAL} left to the SDK")
    assert built >= 4 * len(goals) - 8


class _CountingPort(BlockingPortHandler):
    flushes = 0

    def clearPort(self) -> None:
        type(self).flushes += 1
        super().clearPort()


@pytest.mark.asyncio
async def test_stop_flushes_only_when_a_reply_may_be_left(caplog, monkeypatch):
    emu = DxlEmulator().start()
    try:
        async with DynamixelBus(BusConfig(port=emu.port),
                                port_handler_factory=_CountingPort) as bus:
            gid = bus.config.gripper_id
            # Settled: the last transaction read all its replies; the stop writes at once.
            await bus.read_state()
            flushes = _CountingPort.flushes
            record = await bus.stop_ahead(gid, 2, max_age_s=10.0)
            assert record.fast and _CountingPort.flushes == flushes
            assert emu.get_register(gid, "Goal Position") == record.goal

            await asyncio.sleep(0.02)  # past STOP_STATE_SETTLE_S after that goal
            await bus.read_state()
            # A read the motor answers too late: its reply lands on the input afterwards.
            # A timed-out read is tried again after LATE_REPLY_DRAIN_S, so the first reply
            # must land after the first try gives up (about 2 x PTY_LATENCY_TIMER_MS) and
            # before the drain's flush, and the second after the second try gives up: each
            # by 150 ms here, far more than a loaded host holds a thread back (the SDK takes
            # a reply that is there when its thread wakes).
            monkeypatch.setattr(transactions, "LATE_REPLY_DRAIN_S", 0.5)
            late_s = 2 * PTY_LATENCY_TIMER_MS / 1000 + 0.15
            emu.reply_latency_s = late_s
            with pytest.raises(MotorError, match="no status packet"):
                await bus.read(gid, "Present Position")
            await asyncio.sleep(2 * late_s)  # the second try's reply, on the input by now
            emu.reply_latency_s = 0.0
            mark = len(emu.received)
            flushes = _CountingPort.flushes
            caplog.clear()
            with caplog.at_level(logging.WARNING, logger="edge.hw.dynamixel.port"):
                record = await bus.stop_ahead(gid, 3, max_age_s=10.0)
            # The late 4-byte reply was flushed, not skipped as the stop's status.
            assert record.fast and _CountingPort.flushes == flushes + 1
            assert not [r for r in caplog.records if "late status packet" in r.message]
            writes = [r for r in list(emu.received)[mark:] if r.instruction == INST_WRITE]
            assert len(writes) == 1
            assert emu.get_register(gid, "Goal Position") == record.goal
    finally:
        emu.stop()


@pytest.mark.asyncio
async def test_urgent_handover_to_the_owner():
    """Submission of an urgent operation -> the owner thread running it (the stop's
    hand-over with nothing on the wire); the submitter resumes once it is on the wire."""
    executor = ThreadExecutor()
    executor.start()
    handover = []
    try:
        for _ in range(300):
            started = []

            def op(started=started) -> None:
                started.append(time.monotonic())
                executor.on_wire()

            t0 = time.monotonic()
            await executor.submit("stop", op, urgent=True)
            handover.append(started[0] - t0)
            await asyncio.sleep(0.001)  # the owner back asleep in select()
    finally:
        await executor.stop(lambda: None)
    ms = sorted(1e3 * h for h in handover)
    print(f"\nurgent hand-over to the owner thread: p50 {ms[len(ms) // 2]:.3f} ms, "
          f"p90 {ms[int(0.9 * len(ms))]:.3f} ms, max {ms[-1]:.2f} ms")
    assert ms[len(ms) // 2] < 1e3 * STOP_HANDOVER_MAX_S
