"""The udev rules the robot computer needs (``edge/daemon/60-vtzero.rules``): the U2D2's
latency timer at 1 ms, a stable ``/dev/ttyDXL`` name, and the GPIO chips for the gpio
group."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from edge.core.atomic import atomic_write_text

RULES_NAME = "60-vtzero.rules"
RULES_DIR = Path("/etc/udev/rules.d")
RELOAD_COMMAND = "udevadm control --reload-rules && udevadm trigger --action=add " \
                 "--subsystem-match=usb-serial --subsystem-match=tty"


def rules_text() -> str:
    return resources.files("edge.daemon").joinpath(RULES_NAME).read_text()


def install(dest_dir: Path = RULES_DIR) -> Path:
    path = dest_dir / RULES_NAME
    atomic_write_text(path, rules_text())
    path.chmod(0o644)  # atomic writes are private (mkstemp); udev rules are world-readable
    return path
