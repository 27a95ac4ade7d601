"""What ``vt-edge run`` checks on its devices before torque goes on.

A configuration that would make every press fail stops the start with one line
(:class:`StartError`, exit 2) and torque never on: a pad layout (pads, taxels per pad,
sensor model) that is not what ``xela_server`` sends, a model built for other pads (its
input channels are not the configured sensor's), or a camera that cannot take the photo
the VLM mode needs. (A serial button without modem lines is refused when it is opened.)

An ``xela_server`` that cannot be reached yet is a condition, not a configuration error:
the daemon starts with torque off and presses refused, and the runtime turns torque on when
the stream arrives (:meth:`edge.runtime.lifecycle.Runtime.power_on_with_stream`).
"""

from __future__ import annotations

import asyncio
import logging
import time

from edge.core.config import Config, SensorConfig
from edge.core.errors import EdgeError, SensorLayoutError, StaleSensorError, StartError
from edge.core.model import ModelLayout, ModelRef
from edge.core.tasks import cancel_and_wait
from edge.hw.contracts import Camera, Devices

log = logging.getLogger(__name__)

# After the handshake (up to [sensor] connect_timeout_s) a server sends ~100 frames a
# second: this covers a slow first one, and a server that comes up a moment late.
FIRST_FRAME_GRACE_S = 1.0
PHOTO_MODES = frozenset({"vision_tactile", "vision_only"})


def needs_photo(vlm_mode: str) -> bool:
    """Whether every recognition in this VLM prompt mode needs the camera's photo."""
    return vlm_mode in PHOTO_MODES


async def check_devices(cfg: Config, devices: Devices, vlm_mode: str) -> str | None:
    """Raise :class:`StartError` for a configuration that fails every press; return why the
    sensor stream is absent (the daemon then starts with torque off), or None.

    The photo is taken while the first frames are awaited: a good start pays for the
    longer of the two, not their sum.
    """
    started = time.monotonic()
    camera = None
    if devices.camera is not None and needs_photo(vlm_mode):
        camera = asyncio.create_task(_check_camera(devices.camera, vlm_mode),
                                     name="start-check camera")
    try:
        absent = await _check_sensor(cfg, devices)
        sensor_ms = (time.monotonic() - started) * 1e3
        if camera is not None:
            await camera
        log.info("start checks done in %.0f ms (sensor %s after %.0f ms%s)",
                 (time.monotonic() - started) * 1e3, "absent" if absent else "checked",
                 sensor_ms, ", one photo taken" if camera is not None else "")
    finally:
        if camera is not None and not camera.done():
            await cancel_and_wait(camera)
    return absent


BUILD_FOR_THESE_PADS = "build a model from this robot's presses (vt-train build)"


def model_mismatch(sensor: SensorConfig, layout: ModelLayout) -> str | None:
    """Why a model taking ``layout`` cannot recognise with the configured pads, or None."""
    same_pads = layout.pads in (None, sensor.pads) and layout.taxels_per_pad in (
        None, sensor.taxels_per_pad)
    if layout.channels == sensor.channels and same_pads:
        # (one pad of 32 taxels and two of 16 give the same count: the manifest tells them
        # apart where it names its pads)
        return None
    return (f"expects {layout.text()}; the sensor [sensor] gives {sensor.channels} "
            f"({sensor.layout_text()})")


def check_model(sensor: SensorConfig, model: ModelRef) -> None:
    """Raise :class:`StartError` for a model whose input is not the configured pads'
    channels: every recognition with it would fail."""
    why = model_mismatch(sensor, model.layout)
    if why is not None:
        raise StartError(f"model {model.directory} {why}: {BUILD_FOR_THESE_PADS}")


async def _check_sensor(cfg: Config, devices: Devices) -> str | None:
    try:
        await devices.tactile.wait_first_frame(
            cfg.sensor.connect_timeout_s + FIRST_FRAME_GRACE_S)
    except SensorLayoutError as exc:
        raise StartError(str(exc)) from None
    except StaleSensorError as exc:
        return str(exc)
    return None


async def _check_camera(camera: Camera, vlm_mode: str) -> None:
    try:
        photo = await camera.capture()
    except (EdgeError, OSError) as exc:
        why = " ".join(str(exc).split()) or type(exc).__name__
        raise StartError(f"{why}; [vlm] mode {vlm_mode} needs a photo for every press: fix "
                         '[camera], or set [vlm] mode = "tactile_only"') from None
    log.debug("camera took a %d-byte photo", len(photo))
