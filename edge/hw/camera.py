"""Cameras: one still image per recognition.

The contract is :class:`~edge.hw.contracts.Camera`; implementations: a still-capture
command (any program that writes a JPEG, e.g. ``libcamera-still`` or ``fswebcam``), a
V4L2/USB camera through OpenCV (optional extra ``camera``), and an HTTP snapshot URL (IP
cameras; the simulated robot serves one).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shlex
import tempfile
from pathlib import Path

from edge.core.errors import DeviceError, DeviceTimeoutError

log = logging.getLogger(__name__)

CAPTURE_TIMEOUT_S = 10.0
MAX_IMAGE_BYTES = 20 * 1024 * 1024


class CommandCamera:
    """Runs ``command`` with ``{out}`` replaced by a temp file path, then reads the file."""

    def __init__(self, command: str, timeout_s: float = CAPTURE_TIMEOUT_S) -> None:
        if "{out}" not in command:
            raise DeviceError(f"camera command {command!r} must contain {{out}} for the file")
        self.command = command
        self.timeout_s = timeout_s

    async def capture(self) -> bytes:
        with tempfile.TemporaryDirectory(prefix="vtzero-cam-") as tmp:
            out = Path(tmp) / "still.jpg"
            argv = [a.replace("{out}", str(out)) for a in shlex.split(self.command)]
            try:
                proc = await asyncio.create_subprocess_exec(
                    *argv, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
            except OSError as exc:
                raise DeviceError(f"camera command {self.command!r} cannot start: {exc}"
                                  ) from None
            try:
                _, err = await asyncio.wait_for(proc.communicate(), self.timeout_s)
            except TimeoutError:
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await proc.wait()
                raise DeviceTimeoutError(f"camera command {self.command!r} did not finish "
                                         f"within {self.timeout_s} s") from None
            if proc.returncode != 0:
                # Its last words on one line: the message goes into one log or status line.
                msg = " ".join(err.decode(errors="replace").split())[-300:]
                raise DeviceError(f"camera command {self.command!r} failed (exit "
                                  f"{proc.returncode}): {msg}")
            try:
                size = out.stat().st_size
            except FileNotFoundError:
                raise DeviceError(f"camera command {self.command!r} wrote no file at {{out}}"
                                  ) from None
            if not 0 < size <= MAX_IMAGE_BYTES:
                raise DeviceError(f"camera command {self.command!r} wrote an image of {size} "
                                  f"bytes; expected 1..{MAX_IMAGE_BYTES}")
            return await asyncio.to_thread(out.read_bytes)


class V4L2Camera:
    """A USB camera through OpenCV (``pip install 'vtzero[camera]'``); grabs in a thread."""

    def __init__(self, device: str | int = 0, warmup_frames: int = 3) -> None:
        try:
            import cv2  # noqa: F401  (optional extra)
        except ImportError:
            raise DeviceError(
                "V4L2 camera needs OpenCV: pip install 'vtzero[camera]', or use a "
                "still-capture command camera") from None
        self.device = device
        self.warmup_frames = warmup_frames

    def _grab(self) -> bytes:
        import cv2

        cap = cv2.VideoCapture(self.device)
        try:
            if not cap.isOpened():
                raise DeviceError(f"camera {self.device!r} cannot be opened")
            frame = None
            # Auto-exposure settles over the first frames.
            for _ in range(self.warmup_frames + 1):
                ok, frame = cap.read()
                if not ok:
                    raise DeviceError(f"camera {self.device!r} returned no frame")
            ok, buf = cv2.imencode(".jpg", frame)
            if not ok:
                raise DeviceError("camera frame could not be encoded as JPEG")
            return buf.tobytes()
        finally:
            cap.release()

    async def capture(self) -> bytes:
        try:
            return await asyncio.wait_for(asyncio.to_thread(self._grab), CAPTURE_TIMEOUT_S)
        except TimeoutError:
            raise DeviceTimeoutError(f"camera {self.device!r} gave no frame within "
                                     f"{CAPTURE_TIMEOUT_S} s") from None


class HttpCamera:
    """A snapshot URL (IP cameras; the simulated robot serves one)."""

    def __init__(self, url: str, timeout_s: float = CAPTURE_TIMEOUT_S) -> None:
        self.url = url
        self.timeout_s = timeout_s

    async def capture(self) -> bytes:
        import aiohttp

        timeout = aiohttp.ClientTimeout(total=self.timeout_s)
        try:
            async with aiohttp.ClientSession(timeout=timeout) as session, \
                    session.get(self.url) as resp:
                if resp.status != 200:
                    raise DeviceError(f"camera {self.url} answered HTTP {resp.status}")
                data = await resp.content.read(MAX_IMAGE_BYTES + 1)
        except TimeoutError:
            raise DeviceTimeoutError(
                f"camera {self.url} gave no image within {self.timeout_s} s") from None
        except aiohttp.ClientError as exc:
            raise DeviceError(f"camera {self.url} unreachable: {exc}") from None
        if not 0 < len(data) <= MAX_IMAGE_BYTES:
            raise DeviceError(f"camera {self.url} sent an image of {len(data)} bytes; expected "
                              f"1..{MAX_IMAGE_BYTES}")
        return data
