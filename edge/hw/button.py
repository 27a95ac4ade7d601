"""Hardware buttons that trigger a recognition.

The contract is :class:`~edge.hw.contracts.Button`: an async iterator of presses.
Implementations: a foot switch wired to a serial port's modem-status line (CTS or DSR, read
with pyserial: a common cheap wiring) and a GPIO line through libgpiod (optional extra
``gpio``). Both poll in a thread and debounce, so no blocking call touches the event loop.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import AsyncIterator, Callable
from typing import Literal

from edge.core.errors import DeviceError

log = logging.getLogger(__name__)

POLL_PERIOD_S = 0.01
DEBOUNCE_S = 0.05


class _PolledButton:
    """Polls ``read()`` (True while pressed) in a thread; emits debounced rising edges."""

    def __init__(self, read: Callable[[], bool], name: str) -> None:
        self._read = read
        self._name = name
        self._queue: asyncio.Queue[float] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _run(self) -> None:
        pressed = False
        changed_at = 0.0
        while not self._stop.wait(POLL_PERIOD_S):
            try:
                level = bool(self._read())
            except Exception as exc:  # a vanished device: report once, stop polling
                log.error("button %s: read failed: %s", self._name, exc)
                return
            now = time.monotonic()
            if level != pressed and now - changed_at >= DEBOUNCE_S:
                pressed, changed_at = level, now
                if pressed and self._loop and self._queue:
                    self._loop.call_soon_threadsafe(self._queue.put_nowait, now)

    async def presses(self) -> AsyncIterator[float]:
        if self._thread is None:
            self._loop = asyncio.get_running_loop()
            self._queue = asyncio.Queue()
            self._thread = threading.Thread(target=self._run, name=f"button-{self._name}",
                                            daemon=True)
            self._thread.start()
        assert self._queue is not None
        while True:
            yield await self._queue.get()

    async def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 1.0)


class SerialButton(_PolledButton):
    """A switch between RTS/DTR and CTS/DSR of a serial port (e.g. a USB-serial adapter)."""

    def __init__(self, port: str, line: Literal["cts", "dsr"] = "cts") -> None:
        import serial

        try:
            self._serial = serial.Serial(port)
        except (serial.SerialException, OSError) as exc:
            raise DeviceError(f"button port {port} cannot be opened: {exc}") from None
        attr = "cts" if line == "cts" else "dsr"
        try:
            # Drive the output lines high so the switch pulls the input up when closed.
            self._serial.rts = True
            self._serial.dtr = True
            getattr(self._serial, attr)
        except (serial.SerialException, OSError) as exc:
            # A port without modem-control lines (a pty, some USB CDC devices) refuses the
            # ioctl (ENOTTY): no switch could ever be read there.
            self._serial.close()
            raise DeviceError(
                f"button port {port} has no modem lines ({exc}): use a serial port with "
                "CTS/DSR (a USB-serial adapter), or [button] kind = \"gpio\"") from None
        super().__init__(lambda: getattr(self._serial, attr), f"{port}:{line}")

    async def close(self) -> None:
        await super().close()
        self._serial.close()


class GPIOButton(_PolledButton):
    """A button on a GPIO line, active low with the internal pull-up (libgpiod v2)."""

    def __init__(self, chip: str, line: int) -> None:
        try:
            import gpiod
            from gpiod.line import Bias, Direction, Value
        except ImportError:
            raise DeviceError(
                "GPIO button needs libgpiod bindings: pip install 'vtzero[gpio]'") from None
        try:
            settings = gpiod.LineSettings(direction=Direction.INPUT, bias=Bias.PULL_UP)
            self._request = gpiod.request_lines(chip, consumer="vtzero",
                                                config={line: settings})
        except OSError as exc:
            raise DeviceError(f"GPIO {chip} line {line} cannot be requested: {exc}") from None
        super().__init__(lambda: self._request.get_value(line) == Value.INACTIVE,
                         f"{chip}:{line}")

    async def close(self) -> None:
        await super().close()
        self._request.release()
