"""The udev rules the robot computer needs (``edge/deploy/60-vtzero.rules``): the U2D2's
latency timer at 1 ms, a stable ``/dev/ttyDXL`` name, and the GPIO chips for the gpio
group."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from edge.core.atomic import atomic_write_text
from edge.deploy.install import group_exists

RULES_NAME = "60-vtzero.rules"
RULES_DIR = Path("/etc/udev/rules.d")
RELOAD_COMMAND = "udevadm control --reload-rules && udevadm trigger --action=add " \
                 "--subsystem-match=usb-serial --subsystem-match=tty"


GPIO_RULE = '#SUBSYSTEM=="gpio"'


def rules_text(gpio: bool | None = None) -> str:
    """The rules; the gpio group's rule is enabled when ``gpio`` (default: when the host
    has that group)."""
    text = resources.files("edge.deploy").joinpath(RULES_NAME).read_text()
    if gpio if gpio is not None else group_exists("gpio"):
        text = text.replace(GPIO_RULE, GPIO_RULE[1:])
    return text


def install(dest_dir: Path = RULES_DIR) -> Path:
    path = dest_dir / RULES_NAME
    atomic_write_text(path, rules_text())
    path.chmod(0o644)  # udev rules are world-readable whatever the installing shell's umask
    return path
