"""The device contracts: importable without any hardware library, and every fake and every
real driver satisfies its Protocol."""

from __future__ import annotations

import inspect
import subprocess
import sys

import numpy as np
import pytest

from edge.core.config import BusConfig, SensorConfig
from edge.hw.arm import DynamixelArm, DynamixelGripper
from edge.hw.button import GPIOButton, SerialButton, _PolledButton
from edge.hw.camera import CommandCamera, HttpCamera, V4L2Camera
from edge.hw.contracts import Arm, Button, Camera, Gripper, MotorBus, TactileSource
from edge.hw.dynamixel import DynamixelBus
from edge.hw.xela import XelaClient
from edge.sim.virtual import Transport, VirtualTactileSource
from edge.sim.world import SimWorld
from tests.support.daemon import QUICK_OBJECT
from tests.support.fakes import FakeArm, FakeButton, FakeCamera, FakeGripper, FakeTactileSource

HARDWARE_LIBRARIES = ("dynamixel_sdk", "serial", "aiohttp", "cv2", "gpiod")
POSES = {"home": (2048, 2048, 2048, 2048)}


def _signature_mismatches(impl: object, contract: type) -> list[str]:
    """Methods of ``contract`` that ``impl`` does not take the same parameters for.

    isinstance() on a runtime_checkable Protocol only checks that the names exist; a fake
    left on an old signature (say ``open()`` without the width) would still pass it.
    """
    cls = impl if isinstance(impl, type) else type(impl)
    bad = []
    for name, member in vars(contract).items():
        if name.startswith("_") and name not in ("__aenter__", "__aexit__"):
            continue
        if not inspect.isfunction(member):
            continue  # a property or data member: isinstance already checks it exists
        wanted = list(inspect.signature(member).parameters)[1:]
        params = list(inspect.signature(getattr(cls, name)).parameters.values())[1:]
        if any(p.kind is p.VAR_POSITIONAL for p in params):
            continue
        names = [p.name for p in params[: len(wanted)]]
        extra = params[len(wanted):]
        if names != wanted or any(p.default is p.empty for p in extra):
            bad.append(f"{cls.__name__}.{name}{inspect.signature(getattr(cls, name))}")
    return bad


def test_contracts_import_no_sdk_network_or_serial_library():
    # A fresh interpreter: this test process has long since imported the drivers.
    code = (
        "import sys\n"
        "import edge.hw.contracts\n"
        f"libs = {HARDWARE_LIBRARIES!r}\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in libs))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", f"edge.hw.contracts loaded {out.stdout.strip()}"


@pytest.mark.asyncio  # the tactile source and the button make asyncio queues
@pytest.mark.parametrize(
    ("make", "contract"),
    [
        (lambda: FakeTactileSource(np.zeros((1, 96), dtype=np.uint16)), TactileSource),
        (lambda: FakeGripper(), Gripper),
        (lambda: FakeArm(POSES), Arm),
        (lambda: FakeCamera(b"\xff\xd8\xff"), Camera),
        (lambda: FakeButton(), Button),
    ],
    ids=["tactile", "gripper", "arm", "camera", "button"],
)
async def test_each_fake_satisfies_its_contract(make, contract):
    fake = make()
    assert isinstance(fake, contract)
    assert not _signature_mismatches(fake, contract)


@pytest.mark.asyncio
@pytest.mark.parametrize(
    ("make", "contract"),
    [
        (lambda: XelaClient(SensorConfig()), TactileSource),
        (lambda: DynamixelBus(BusConfig()), MotorBus),
        (lambda: DynamixelGripper(DynamixelBus(BusConfig())), Gripper),
        (lambda: DynamixelArm(DynamixelBus(BusConfig()), POSES), Arm),
        (lambda: CommandCamera("fswebcam {out}"), Camera),
        (lambda: HttpCamera("http://127.0.0.1:9/still.jpg"), Camera),
        (lambda: _PolledButton(lambda: False, "test"), Button),
    ],
    ids=["xela", "dxl-bus", "dxl-gripper", "dxl-arm", "command-camera", "http-camera",
         "polled-button"],
)
async def test_each_real_driver_satisfies_its_contract(make, contract):
    # Built, not started: no port, server or camera is touched.
    driver = make()
    assert isinstance(driver, contract)
    assert not _signature_mismatches(driver, contract)


@pytest.mark.parametrize(
    ("cls", "contract"),
    [(V4L2Camera, Camera), (SerialButton, Button), (GPIOButton, Button)],
)
def test_drivers_that_need_their_device_to_be_built_satisfy_their_contract(cls, contract):
    # These open OpenCV, a serial port or a GPIO chip in __init__; their contracts have
    # methods only, so the class itself can be checked.
    assert issubclass(cls, contract)
    assert not _signature_mismatches(cls, contract)


def test_the_virtual_robots_stream_satisfies_the_tactile_contract():
    # Built on a world, not started: its frames are made on the virtual clock when read.
    rng = np.random.default_rng(0)
    source = VirtualTactileSource(SimWorld(QUICK_OBJECT, rng), 125.0, Transport(), rng)
    assert isinstance(source, TactileSource)
    assert not _signature_mismatches(source, TactileSource)
    assert source.server_models == ("XR1944", "XR1944")
