"""systemd integration without dependencies: sd_notify and the watchdog's period (the unit
file is edge.deploy.unit's)."""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)

class Notifier:
    """Sends sd_notify datagrams to ``$NOTIFY_SOCKET``; a no-op when not under systemd."""

    def __init__(self, address: str | None = None) -> None:
        address = address if address is not None else os.environ.get("NOTIFY_SOCKET")
        self._sock: socket.socket | None = None
        self._address = None
        if not address:
            return
        if address.startswith("@"):
            address = "\0" + address[1:]  # abstract namespace socket
        elif not address.startswith("/"):
            log.warning("NOTIFY_SOCKET %r is not a unix socket path; not notifying", address)
            return
        self._address = address
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, state: str) -> bool:
        if self._sock is None:
            return False
        try:
            self._sock.sendto(state.encode(), self._address)
            return True
        except OSError as exc:
            log.warning("sd_notify %r failed: %s", state.split("\n", 1)[0], exc)
            return False

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, status: str) -> bool:
        return self.notify(f"STATUS={status}")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def watchdog_period_s() -> float | None:
    """Half of ``$WATCHDOG_USEC`` (systemd's advice), if the watchdog applies to us."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        return int(usec) / 2e6
    except ValueError:
        return None
