"""install-service's host checks, the unit it builds from them, and the udev rules."""

import os
import re
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from edge.core.config import Config, load_config
from edge.core.errors import EdgeError
from edge.deploy import install, udev
from edge.deploy.unit import unit_text
from edge.hw.dynamixel import LATENCY_TIMER_UDEV_RULE

# A user no host has: the checks must say it is missing.
NO_USER = "vtzero-no-such-user"
# systemd-analyze verify wants the program to exist: this interpreter (which the unit could
# not run where it lies under /root or /home: the CLI checks that, not this).
EXE = f"{sys.executable} -m edge"


def _cli(*args, check=False):
    return subprocess.run([sys.executable, "-m", "edge", *args], capture_output=True,
                          text=True, check=check)


def _config(tmp_path, body=""):
    path = tmp_path / "robot.toml"
    path.write_text('[runtime]\nmodels_dir = "/opt/vtzero/models"\n' + body)
    return path


def _verify(tmp_path, text):
    path = tmp_path / "vtzero-edge.service"
    path.write_text(text)
    out = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr


def test_missing_config_is_refused_in_one_line(tmp_path):
    out = _cli("install-service", "--config", str(tmp_path / "nonexistent.toml"))
    assert out.returncode == 2 and out.stdout == ""
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "nonexistent.toml does not exist" in lines[0], out.stderr


def test_invalid_config_is_refused(tmp_path):
    path = tmp_path / "robot.toml"
    path.write_text("[runtime]\nmodles_dir = 1\n")
    out = _cli("install-service", "--config", str(path))
    assert out.returncode == 2 and out.stdout == "" and "modles_dir" in out.stderr


@pytest.mark.parametrize(("path", "setting"), [
    ("/root/venv/bin/python", "ProtectHome=yes"),
    ("/home/lab/vtzero/.venv", "ProtectHome=yes"),
    ("/home", "ProtectHome=yes"),
    ("/run/user/1000/x", "ProtectHome=yes"),
    ("/tmp/venv", "PrivateTmp=yes"),
    ("/var/tmp/m", "PrivateTmp=yes"),
    ("/opt/vtzero/venv/bin/python", None),
    ("/usr/bin/python3.11", None),
    ("/homestead/venv", None),
    ("/etc/vtzero/robot.toml", None),
])
def test_hidden_by(path, setting):
    assert install.hidden_by(path) == setting


def test_a_venv_under_root_or_home_is_refused_with_where_to_put_it():
    with pytest.raises(EdgeError) as err:
        install.check_paths([("the interpreter", Path("/root/.venv/bin/python")),
                             ("the edge package", Path("/home/lab/vtzero/edge"))], [])
    message = str(err.value)
    assert "/root/.venv/bin/python (hidden by ProtectHome=yes)" in message
    assert "/home/lab/vtzero/edge (hidden by ProtectHome=yes)" in message
    assert "/opt/vtzero/venv" in message and "\n" not in message


def test_files_the_config_names_must_be_visible_absolute_and_writable(tmp_path):
    path = _config(tmp_path, '[api]\ntoken_file = "/home/lab/token"\n')
    cfg = load_config(path)
    reads, writes = install.config_paths(cfg, Path("/etc/vtzero/robot.toml"))
    install.check_paths(reads[:2], writes)  # the config and /opt/vtzero/models: fine
    with pytest.raises(EdgeError, match=r"\[api\] token_file /home/lab/token \(hidden by "
                                        r"ProtectHome=yes\); keep the files"):
        install.check_paths(reads, writes)
    cfg = Config()  # models_dir "models", relative
    reads, writes = install.config_paths(cfg, Path("/etc/vtzero/robot.toml"))
    with pytest.raises(EdgeError, match=r"models_dir models \(relative"):
        install.check_paths(reads, writes)
    cfg = replace(cfg, runtime=replace(cfg.runtime, models_dir="/opt/vtzero/models",
                                       record_mcap_dir="/srv/mcap"))
    reads, writes = install.config_paths(cfg, Path("/etc/vtzero/robot.toml"))
    with pytest.raises(EdgeError, match=r"record_mcap_dir /srv/mcap \(not writable under "
                                        r"ProtectSystem=strict: put it under /var/lib/vtzero"):
        install.check_paths(reads, writes)
    cfg = replace(cfg, runtime=replace(cfg.runtime, record_mcap_dir="/var/lib/vtzero/mcap"))
    install.check_paths(*install.config_paths(cfg, Path("/etc/vtzero/robot.toml")))


def test_the_cli_refuses_a_models_dir_under_home(tmp_path):
    path = tmp_path / "robot.toml"
    path.write_text('[runtime]\nmodels_dir = "/home/lab/vtzero/models"\n')
    out = _cli("install-service", "--config", str(path), "--install")
    assert out.returncode == 2 and out.stdout == ""
    assert len(out.stderr.strip().splitlines()) == 1
    assert "models_dir /home/lab/vtzero/models (hidden by ProtectHome=yes)" in out.stderr
    assert f"the config file {path} (hidden by PrivateTmp=yes)" in out.stderr


def test_groups_follow_the_devices_the_config_uses(tmp_path):
    cfg = load_config(_config(tmp_path))
    assert install.needed_groups(cfg) == ["dialout"]
    cfg = load_config(_config(tmp_path, '[camera]\nkind = "v4l2"\n[button]\nkind = "gpio"\n'
                                        'chip = "/dev/gpiochip0"\nline = "17"\n'))
    assert install.needed_groups(cfg) == ["dialout", "video", "gpio"]


def test_missing_user_and_group_are_named_with_the_commands(tmp_path, monkeypatch):
    cfg = load_config(_config(tmp_path, '[camera]\nkind = "v4l2"\n'))
    real = install.group_exists
    monkeypatch.setattr(install, "group_exists", lambda g: g != "video" and real(g))
    acc = install.accounts(cfg, NO_USER)
    assert acc.missing_user and acc.group == NO_USER and "video" in acc.missing_groups
    assert "video" not in acc.groups
    todo = acc.todo()
    assert any(f"user {NO_USER} does not exist" in line and "useradd --system --user-group"
               in line and "--create-user" in line for line in todo), todo
    assert any("group video does not exist" in line and "groupadd --system video" in line
               for line in todo), todo


def test_existing_user_gets_its_primary_group():
    acc = install.accounts(Config(), "root")
    assert not acc.missing_user and acc.group == "root"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed")
def test_unit_names_only_existing_groups_and_verifies(tmp_path):
    cfg = load_config(_config(tmp_path, '[button]\nkind = "gpio"\nchip = "/dev/gpiochip0"\n'
                                        'line = "17"\n'))
    acc = install.accounts(cfg, NO_USER)
    text = install.service_unit(cfg, Path("/etc/vtzero/robot.toml"), EXE, acc)
    groups = re.search(r"^SupplementaryGroups=(.*)$", text, re.M).group(1).split()
    assert groups and all(install.group_exists(g) for g in groups), groups
    assert set(groups) | set(acc.missing_groups) == {"dialout", "gpio"}
    assert f"User={NO_USER}\nGroup={NO_USER}\n" in text
    assert "ExecReload=/bin/kill -HUP $MAINPID" in text
    _verify(tmp_path, text)


def test_the_cli_names_a_hidden_config_and_interpreter(tmp_path):
    # Printed from anywhere (a checkout, a config under /tmp), with a warning naming what
    # the unit could not see; installing it is refused with the same line.
    config = str(_config(tmp_path))
    out = _cli("install-service", "--config", config, "--user", NO_USER, "--print")
    assert out.returncode == 0 and out.stdout.startswith("# vtzero")
    assert f"run --config {config}\n" in out.stdout and "Documentation=" not in out.stdout
    (warning,) = [line for line in out.stderr.splitlines() if line.startswith("warning: ")]
    assert "as printed, the unit would not start" in warning
    out = _cli("install-service", "--config", config, "--user", NO_USER, "--install")
    assert out.returncode == 2 and out.stdout == ""
    assert len(out.stderr.strip().splitlines()) == 1
    assert warning.split("would not start: ")[1] in out.stderr
    assert "(hidden by PrivateTmp=yes)" in out.stderr  # the config, under pytest's /tmp
    hidden = [p for _, p in install.interpreter_paths(sys.executable) if install.hidden_by(p)]
    for path in hidden:  # a dev venv from pyenv, or a checkout in a home directory
        assert f"{path} (hidden by " in out.stderr
    if hidden:
        assert "/usr/bin/python3 -m venv /opt/vtzero/venv" in out.stderr


def test_print_notes_what_to_create_and_install_refuses(monkeypatch, capsys, caplog):
    """The rest of install-service, whatever interpreter runs the tests (its own check is
    the test above's)."""
    from edge.cli import main

    config = Path("configs/robot.toml").resolve()
    if install.hidden_by(config):
        pytest.skip(f"the checkout lies under {config.parents[1]}, hidden from a unit")
    monkeypatch.setattr(install, "interpreter_paths", lambda exe: [])
    assert main(["install-service", "--config", str(config), "--user", NO_USER]) == 0
    out = capsys.readouterr()
    assert f"note: user {NO_USER} does not exist" in out.err
    if not Path("/opt/vtzero/models/manifest.json").exists():
        assert "note: no model in /opt/vtzero/models" in out.err
    assert out.out.startswith("# vtzero") and f"User={NO_USER}\n" in out.out
    assert "ExecStart=" in out.out and f"run --config {config}\n" in out.out
    assert main(["install-service", "--config", str(config), "--user", NO_USER,
                 "--install"]) == 2
    out = capsys.readouterr()
    # The refusal is logged: where an earlier test set up logging, its handler writes to the
    # stream it was given then, not to this test's captured stderr.
    assert out.out == "" and "before installing the unit" in out.err + caplog.text


# --------------------------------------------------------------------------------------
# udev

RULE_KEYS = {"ACTION", "SUBSYSTEM", "DRIVER", "KERNEL", "ATTR", "ATTRS", "ENV", "SYMLINK",
             "GROUP", "MODE"}
RULE_PAIR = re.compile(r'^(?P<key>[A-Z]+)(?:\{(?P<attr>[A-Za-z_]+)\})?'
                       r'(?P<op>==|!=|\+=|=)"(?P<value>[^"]*)"$')


def _rules(text):
    return [line for line in text.splitlines() if line.strip() and not line.startswith("#")]


def _check_rule(rule):
    pairs = [p.strip() for p in rule.split(",")]
    parsed = [RULE_PAIR.match(p) for p in pairs]
    assert all(parsed), [p for p, m in zip(pairs, parsed, strict=True) if not m]
    assert {m["key"] for m in parsed} <= RULE_KEYS
    ops = [m["op"] in ("==", "!=") for m in parsed]
    assert ops == sorted(ops, reverse=True), f"a match after an assignment: {rule}"


def test_udev_rules_parse_and_cover_latency_and_name():
    """The shape udev accepts (udevadm verify needs systemd >= 254 and udev, neither of which
    every build host has): KEY[{attr}]OP"value" pairs, comma separated, matches then
    assignments, only keys udev knows."""
    text = udev.rules_text(gpio=False)
    rules = _rules(text)
    assert len(rules) == 2
    for rule in rules:
        _check_rule(rule)
    latency, name = rules
    assert 'ATTR{latency_timer}="1"' in latency and 'DRIVER=="ftdi_sio"' in latency
    assert latency == LATENCY_TIMER_UDEV_RULE  # the rule the driver's warning prints
    assert 'SYMLINK+="ttyDXL"' in name and 'ATTRS{idVendor}=="0403"' in name
    # Without the gpio group its rule stays a comment: udev warns on an unknown group.
    assert sum("gpiochip" in line and "GROUP" in line for line in text.splitlines()) == 1
    gpio = _rules(udev.rules_text(gpio=True))
    assert len(gpio) == 3 and 'GROUP="gpio"' in gpio[2] and gpio[:2] == rules
    _check_rule(gpio[2])
    assert udev.rules_text() == udev.rules_text(gpio=install.group_exists("gpio"))


def test_install_udev_prints_and_installs(tmp_path):
    out = _cli("install-udev", check=True)
    assert out.stdout == udev.rules_text()
    path = udev.install(tmp_path)
    assert path.name == "60-vtzero.rules" and path.read_text() == udev.rules_text()
    assert os.stat(path).st_mode & 0o777 == 0o644


def test_unit_text_defaults_name_dialout_only():
    text = unit_text(EXE, "/etc/vtzero/robot.toml", "robot")
    assert "SupplementaryGroups=dialout\n" in text and "Group=robot\n" in text


def test_a_config_the_service_user_cannot_read_is_named(tmp_path):
    path = tmp_path / "robot.toml"
    path.write_text("")
    group = install.primary_group("root")
    acc = install.Accounts(user=NO_USER, group=group, groups=(), missing_user=True,
                           missing_groups=())
    path.chmod(0o600)
    note = install.readable_note(path, acc)
    assert note and f"chgrp {group} {path} && chmod 0640 {path}" in note
    path.chmod(0o644)
    assert install.readable_note(path, acc) is None
    path.chmod(0o640)  # readable by the file's group, here the user's own
    acc = replace(acc, group=install.grp.getgrgid(os.getgid()).gr_name)
    assert install.readable_note(path, acc) is None


def test_a_link_into_a_home_directory_is_hidden_too():
    link = Path("/dev/shm") / f"vtzero-test-{os.getpid()}"
    if not link.parent.is_dir():
        pytest.skip("no /dev/shm")
    link.symlink_to("/root")
    try:
        with pytest.raises(EdgeError, match=rf"models_dir {link} \(hidden by ProtectHome"):
            install.check_paths([("[runtime] models_dir", link)], [])
    finally:
        link.unlink()
