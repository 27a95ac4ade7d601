"""The shipped systemd unit: its text for a configuration and user, and its installation."""

from __future__ import annotations

from collections.abc import Sequence
from importlib import resources
from pathlib import Path

from edge import SERVICE_NAME

UNIT_NAME = f"{SERVICE_NAME}.service"


# What a unit adds when the configuration asks for real-time scheduling ([runtime]
# realtime, edge/runtime/realtime.py): the right to SCHED_FIFO up to the priority, and the two
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
    template = resources.files("edge.deploy").joinpath("vtzero-edge.service").read_text()
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
