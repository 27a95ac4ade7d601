"""Build the daemon's devices from the configuration (real drivers in both modes: in sim
mode they talk to the emulated robot)."""

from __future__ import annotations

import contextlib
import logging

from edge.core.config import Config
from edge.core.errors import DeviceError, StartError
from edge.hw.arm import DynamixelArm, DynamixelGripper
from edge.hw.button import GPIOButton, SerialButton
from edge.hw.camera import CommandCamera, HttpCamera, V4L2Camera
from edge.hw.contracts import Devices
from edge.hw.dynamixel import DynamixelBus
from edge.hw.xela import XelaClient

log = logging.getLogger(__name__)


def make_camera(cfg: Config):
    c = cfg.camera
    if c.kind == "command":
        return CommandCamera(c.command, c.timeout_s)
    if c.kind == "v4l2":
        return V4L2Camera(c.device)
    if c.kind == "http":
        return HttpCamera(c.url, c.timeout_s)
    return None


def make_button(cfg: Config):
    b = cfg.button
    if b.kind == "serial":
        return SerialButton(b.port, b.line)  # type: ignore[arg-type]
    if b.kind == "gpio":
        return GPIOButton(b.chip, int(b.line))
    return None


async def open_devices(cfg: Config) -> Devices:
    """Connect everything, torque still off (see :func:`enable_torque`); on failure, close
    what was opened and re-raise."""
    tactile = XelaClient(cfg.sensor)
    bus = DynamixelBus(cfg.bus)
    try:
        # The bus first: a port another process owns is refused before anything else starts.
        await bus.connect()
        await tactile.start()
        gripper = DynamixelGripper(bus)
        arm = DynamixelArm(bus, cfg.poses, move_time_s=cfg.runtime.move_time_s)
        try:
            camera, button = make_camera(cfg), make_button(cfg)
        except DeviceError as exc:
            # Configured, but never usable this way (no OpenCV, a port without modem lines).
            raise StartError(str(exc)) from None
        return Devices(tactile=tactile, gripper=gripper, arm=arm, camera=camera,
                       button=button, bus=bus)
    except BaseException:
        with contextlib.suppress(Exception):
            await bus.close()
        with contextlib.suppress(Exception):
            await tactile.close()
        raise


async def enable_torque(devices: Devices) -> None:
    """The last step of a start: from here on the arm holds its pose and can move."""
    if devices.bus is not None:
        await devices.bus.set_torque(True)


async def close_devices(devices: Devices, rest_timeout_s: float) -> None:
    """Arm to ``rest`` (if torque is on), torque off, bus closed, sensor and button
    closed. Each step runs even if one before it failed."""
    if devices.bus is not None:
        try:
            await devices.bus.close(
                safe_pose=lambda: devices.arm.move_to("rest", rest_timeout_s))
        except Exception as exc:
            log.error("bus shutdown: %s", exc)
    with contextlib.suppress(Exception):
        await devices.tactile.close()
    if devices.button is not None:
        with contextlib.suppress(Exception):
            await devices.button.close()
