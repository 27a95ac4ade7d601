"""The emulated robot's control API (``vt-edge sim serve``): POST /fault switches the
emulators' faults as the real drivers then see them, GET /motors shows each motor from
outside, and a bad request gets a 400 that says what to send."""

from __future__ import annotations

import os
from pathlib import Path

import aiohttp
import pytest

from edge.core.config import BusConfig
from edge.core.errors import DeviceError, MotorError
from edge.hw.dynamixel import DynamixelBus
from edge.sim.robot import FAULTS, SimRobot
from edge.sim.xela_server import Fault

IDS = (11, 12, 13, 14, 15)


async def post(http: aiohttp.ClientSession, robot: SimRobot, body: object,
               ) -> tuple[int, dict]:
    async with http.post(f"{robot.control_url}/fault", json=body) as resp:
        return resp.status, await resp.json()


async def motors(http: aiohttp.ClientSession, robot: SimRobot) -> dict:
    async with http.get(f"{robot.control_url}/motors") as resp:
        assert resp.status == 200
        return await resp.json()


@pytest.mark.asyncio
async def test_faults_switched_from_outside_reach_the_real_driver():
    async with SimRobot() as robot, aiohttp.ClientSession() as http, \
            DynamixelBus(BusConfig(port=robot.dxl.port)) as bus:
        shown = await motors(http, robot)
        print("GET /motors:", shown)
        assert shown["plugged"] is True
        assert [m["id"] for m in shown["motors"]] == list(IDS)
        assert all(not m["torque"] and m["hardware_error"] == 0 and not m["silent"]
                   for m in shown["motors"])
        await bus.set_torque(True)
        shown = await motors(http, robot)
        assert all(m["torque"] and m["bus_watchdog"] > 0 for m in shown["motors"])
        assert shown["motors"][4]["position"] == pytest.approx(robot.dxl.true_position(15),
                                                               abs=1)

        assert await post(http, robot, {"fault": "motor_silent", "motor": 12}) == (
            200, {"fault": "motor_silent", "motor": 12, "on": True})
        with pytest.raises(MotorError, match=r"motor 12.*no status packet"):
            await bus.read(12, "Present Position")
        assert (await motors(http, robot))["motors"][1]["silent"] is True
        await post(http, robot, {"fault": "motor_silent", "motor": 12, "on": False})
        await bus.read(12, "Present Position")

        await post(http, robot, {"fault": "crc_errors", "motor": 13, "count": -1})
        with pytest.raises(MotorError, match=r"motor 13.*Incorrect status packet"):
            await bus.read(13, "Present Position")
        await post(http, robot, {"fault": "crc_errors", "motor": 13, "count": 0})
        await bus.read(13, "Present Position")

        await post(http, robot, {"fault": "hardware_error", "motor": 15, "bits": 0x20})
        with pytest.raises(MotorError, match="overload"):
            await bus.read(15, "Present Position")
        gripper = (await motors(http, robot))["motors"][4]
        assert gripper["hardware_error"] == 0x20 and gripper["torque"] is False
        await post(http, robot, {"fault": "hardware_error", "motor": 15, "bits": 0})

        await bus.set_torque(False)  # no watchdog feed: the reads below meet the line's faults
        await post(http, robot, {"fault": "serial_error"})
        with pytest.raises(DeviceError, match="device disconnected"):
            await bus.read(11, "Present Position")
        await bus.read(11, "Present Position")  # the bus reopened the port meanwhile

        await post(http, robot, {"fault": "unplug"})
        assert not os.path.exists(robot.dxl.port)  # noqa: ASYNC240 - a stat of a link
        assert (await motors(http, robot))["plugged"] is False
        with pytest.raises(DeviceError, match=robot.dxl.port):
            await bus.read(11, "Present Position")
        await post(http, robot, {"fault": "plug"})
        assert (await motors(http, robot))["plugged"] is True
        await bus.read(11, "Present Position")

        for fault in Fault:
            assert await post(http, robot, {"fault": "sensor", "mode": fault.value}) == (
                200, {"fault": "sensor", "mode": fault.value})
            assert robot.xela.fault is fault


@pytest.mark.parametrize(("body", "says"), [
    ("not json", "send a JSON object"),
    ([1, 2], "send a JSON object"),
    ({}, "unknown fault None; one of: motor_silent, crc_errors"),
    ({"fault": "melt"}, "unknown fault 'melt'"),
    ({"fault": "motor_silent"}, "motor: missing (an integer)"),
    ({"fault": "motor_silent", "motor": 99}, "motor: 99 is not on the bus (motors 11, 12"),
    ({"fault": "motor_silent", "motor": True}, "motor: True is not an integer"),
    ({"fault": "motor_silent", "motor": 12, "on": "yes"}, "on: 'yes' is not true or false"),
    ({"fault": "crc_errors", "motor": 12, "count": -2}, "count: -2; -1 (every packet)"),
    ({"fault": "hardware_error", "motor": 15}, "bits: missing"),
    ({"fault": "hardware_error", "motor": 15, "bits": 256}, "bits: 256 is not a byte"),
    ({"fault": "unplug", "motor": 12}, "unplug takes no motor; its fields: none"),
    ({"fault": "sensor", "mode": "stalled"}, "mode: 'stalled'; one of: none, silent, freeze"),
])
@pytest.mark.asyncio
async def test_a_bad_fault_request_is_refused_saying_what_to_send(body, says):
    async with SimRobot() as robot, aiohttp.ClientSession() as http:
        data = body if isinstance(body, str) else None
        async with http.post(f"{robot.control_url}/fault", data=data,
                             json=None if data is not None else body) as resp:
            status, answer = resp.status, await resp.json()
        print(body, "->", answer)
        assert status == 400 and says in answer["error"]
        # Nothing was switched.
        assert robot.dxl.plugged and robot.xela.fault is Fault.NONE
        assert not any(robot.dxl.missing(i) for i in IDS)


def test_every_fault_is_documented():
    page = (Path(__file__).resolve().parents[2] / "docs" / "reliability.md").read_text()
    section = page.split("## The emulated robot's control API")[1].split("\n## ")[0]
    for name, fields in FAULTS.items():
        assert f"`{name}`" in section and all(f"`{field}`" in section for field in fields)
        if fields:
            assert f'"fault": "{name}"' in section  # a curl example
