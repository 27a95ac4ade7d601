"""Collect mode: the robot side of adapting the system at low cost.

``vt-edge collect``: press an object N times and write each press in the recordings format
(the same files the simulator writes and training reads). Between presses the user moves the
object slightly, so the references vary as they will at recognition time.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from pathlib import Path

from edge.core import recording
from edge.core.config import Config
from edge.core.errors import EdgeError
from edge.daemon.press import PressController, outcome_recording
from edge.daemon.sensor import FrameRing, SensorTask

log = logging.getLogger(__name__)

# Presses that may fail in a row (no contact, a stale stream) before collecting stops, and
# the pause after each.
MAX_FAILED_IN_A_ROW = 5
FAILED_PRESS_PAUSE_S = 0.5
# The ring keeps the last minute of frames (a press and its margins take a few seconds).
RING_FRAMES = 8000


async def collect(cfg: Config, label: str, presses: int, out: str | Path,
                  prompt: Callable[[str], object] | None = input, devices=None) -> list[Path]:
    """Record ``presses`` presses of ``label`` into ``out/label/``; returns the files."""
    from edge.daemon.devices import close_devices, enable_torque, open_devices

    if not label.replace("_", "").isalnum():
        raise EdgeError(f"label {label!r}: use letters, digits and underscores")
    out_dir = Path(out) / label
    start = len(list(out_dir.glob(f"*{recording.SUFFIX}"))) if out_dir.exists() else 0
    own = devices is None
    if own:
        devices = await open_devices(cfg)
    ring = FrameRing(cfg.sensor.channels, RING_FRAMES)
    controller = PressController(cfg, devices.gripper, devices.arm, ring)
    task = asyncio.create_task(SensorTask(devices.tactile, ring, controller).run(),
                               name="sensor")
    written: list[Path] = []
    try:
        if own:
            await enable_torque(devices)
        await asyncio.sleep(0.5)
        i = failures = 0
        while i < presses:
            if prompt is not None and i > 0:
                await asyncio.to_thread(
                    prompt, f"press {i + 1}/{presses}: move the {label} slightly, then Enter ")
            outcome = await controller.run()
            if not outcome.contact:
                failures += 1
                print(f"press {i + 1}: {outcome.result}: {outcome.message}; not kept")
                if prompt is None or failures >= MAX_FAILED_IN_A_ROW:
                    raise EdgeError(f"press failed ({failures} in a row): {outcome.message}")
                # (a stale stream refuses at once: give it time to come back)
                await asyncio.sleep(FAILED_PRESS_PAUSE_S)
                continue
            failures = 0
            path = out_dir / f"{label}_{start + i:03d}{recording.SUFFIX}"
            recording.save(outcome_recording(outcome, cfg, label), path)
            written.append(path)
            print(f"press {i + 1}/{presses}: stop latency "
                  f"{(outcome.stop_latency_s or 0) * 1e3:.1f} ms -> {path}")
            i += 1
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        if own:
            await close_devices(devices, cfg.runtime.move_timeout_s)
    return written

