"""systemd integration without dependencies: sd_notify and the shipped unit file."""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Sequence
from importlib import resources
from pathlib import Path

from edge import SERVICE_NAME

log = logging.getLogger(__name__)

UNIT_NAME = f"{SERVICE_NAME}.service"


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


# What a unit adds when the configuration asks for real-time scheduling ([runtime]
# realtime, edge/daemon/realtime.py): the right to SCHED_FIFO up to the priority, and the two
# system calls that set it, which the hardening's @resources filter otherwise refuses.
_REALTIME_DENIED = "RestrictRealtime=yes\n"
_REALTIME_ALLOWED = """RestrictRealtime=no
# [runtime] realtime = true: the event loop and the bus thread ask for SCHED_FIFO and a CPU.
LimitRTPRIO={priority}
"""
_SYSCALLS_DENIED = "SystemCallFilter=~@privileged @resources"
_SYSCALLS_REALTIME = "SystemCallFilter=sched_setscheduler sched_setaffinity\n"


def unit_text(exec_start: str, config: str, user: str = "vtzero",
              realtime_priority: int | None = None, group: str | None = None,
              groups: Sequence[str] = ("dialout",)) -> str:
    """The unit for ``vt-edge run --config CONFIG`` as ``user`` (primary group ``group``,
    default the user's name) with supplementary ``groups``; with ``realtime_priority``,
    allowed to run its loop and bus threads at that SCHED_FIFO priority."""
    template = resources.files("edge.daemon").joinpath("vtzero-edge.service").read_text()
    text = (template.replace("@EXEC_START@", exec_start).replace("@CONFIG@", config)
            .replace("@USER@", user).replace("@GROUP@", group or user)
            .replace("@GROUPS@", " ".join(groups)))
    if realtime_priority is not None:
        text = text.replace(_REALTIME_DENIED,
                            _REALTIME_ALLOWED.format(priority=realtime_priority))
        lines = text.splitlines(keepends=True)
        at = next(i for i, line in enumerate(lines) if line.startswith(_SYSCALLS_DENIED))
        lines.insert(at + 1, _SYSCALLS_REALTIME)
        text = "".join(lines)
    return text


def install(unit: str, dest_dir: Path = Path("/etc/systemd/system")) -> Path:
    from edge.core.atomic import atomic_write_text

    path = dest_dir / UNIT_NAME
    atomic_write_text(path, unit)
    # Atomic writes are private (mkstemp); systemd warns about a world-inaccessible unit.
    path.chmod(0o644)
    return path
