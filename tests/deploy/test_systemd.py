import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from edge.core.config import load_config
from edge.deploy import install
from edge.deploy.unit import unit_text
from edge.runtime.systemd import Notifier

needs_systemd = pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                                   reason="systemd-analyze is not installed")
# What install-service builds for this interpreter (systemd-analyze verify wants the program
# to exist; whether the unit could run it is tests/deploy/test_install.py's part).
EXE = f"{sys.executable} -m edge"
CONFIG = Path("/etc/vtzero/robot.toml")


def _service_unit(config):
    cfg = load_config(config)
    return install.service_unit(cfg, CONFIG, EXE, install.accounts(cfg, "vtzero"))


def _unit(tmp_path):
    config = tmp_path / "robot.toml"
    config.write_text("")
    path = tmp_path / "vtzero-edge.service"
    path.write_text(_service_unit(config))
    return path


@needs_systemd
def test_unit_verifies(tmp_path):
    path = _unit(tmp_path)
    text = path.read_text()
    assert "Type=notify" in text and "WatchdogSec=" in text and "Restart=on-failure" in text
    assert "StateDirectory=vtzero" in text and "dialout" in text
    out = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr


@needs_systemd
def test_unit_hardening_exposure_is_ok(tmp_path):
    path = _unit(tmp_path)
    out = subprocess.run(["systemd-analyze", "security", "--offline=yes", str(path)],
                         capture_output=True, text=True)
    match = re.search(r"Overall exposure level for \S+: ([\d.]+) (\w+)", out.stdout)
    assert match, out.stdout[-500:] + out.stderr
    print(f"systemd-analyze security: {match.group(1)} {match.group(2)}")
    assert float(match.group(1)) <= 2.0  # systemd calls < 2.0 "OK"


def test_unit_text_fills_every_placeholder():
    text = unit_text("/usr/bin/vt-edge", "/etc/vtzero/robot.toml", "robot")
    assert not re.search(r"@[A-Z_]+@", text)
    assert "ExecStart=/usr/bin/vt-edge run --config /etc/vtzero/robot.toml" in text


def test_sd_notify_datagrams(tmp_path):
    path = tmp_path / "notify.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(path))
    server.settimeout(2)
    notifier = Notifier(str(path))
    assert notifier.enabled
    notifier.ready("up")
    notifier.watchdog()
    notifier.stopping()
    got = [server.recv(1024).decode() for _ in range(3)]
    assert got == ["READY=1\nSTATUS=up", "WATCHDOG=1", "STOPPING=1"]
    notifier.close()
    server.close()
    assert not Notifier("").enabled and not Notifier("").ready()


def test_realtime_unit_lets_the_daemon_ask_for_fifo(tmp_path):
    config = tmp_path / "robot.toml"
    config.write_text("[runtime]\nrealtime = true\nrealtime_priority = 30\n")
    text = _service_unit(config)
    assert "RestrictRealtime=no" in text and "RestrictRealtime=yes" not in text
    assert "LimitRTPRIO=30" in text
    deny = text.index("SystemCallFilter=~@privileged @resources")
    assert text.index("SystemCallFilter=sched_setscheduler sched_setaffinity") > deny
    # Without it the unit is the hardened default.
    assert "LimitRTPRIO" not in unit_text("/usr/bin/vt-edge", str(config))
    if shutil.which("systemd-analyze") is None:
        return
    path = tmp_path / "vtzero-edge.service"
    path.write_text(text)
    verify = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True,
                            text=True)
    assert verify.returncode == 0, verify.stderr
    security = subprocess.run(["systemd-analyze", "security", "--offline=yes", str(path)],
                              capture_output=True, text=True)
    match = re.search(r"Overall exposure level for \S+: ([\d.]+) (\w+)", security.stdout)
    assert match, security.stdout[-500:] + security.stderr
    print(f"systemd-analyze security, real-time unit: {match.group(1)} {match.group(2)}")
    assert float(match.group(1)) <= 2.0
