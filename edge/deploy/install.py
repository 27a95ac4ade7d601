"""What `vt-edge install-service` checks on the host before it writes the unit.

The unit runs the daemon as a system user with ``ProtectHome=yes`` and ``PrivateTmp=yes``:
the service sees an empty ``/home``, ``/root`` and ``/run/user`` and a /tmp of its own, and
``ProtectSystem=strict`` lets it write only its state directory. An interpreter, a package
or a file the configuration names in one of those places works from a shell and fails only
under systemd (status 203/EXEC, or a file "missing" that is there), so each is refused here
with where to put it instead. The user and the supplementary groups the unit names must
exist: systemd refuses to start a unit whose user or groups are unknown.
"""

from __future__ import annotations

import grp
import pwd
import shutil
import subprocess
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import edge
from edge.core.config import Config, load_config
from edge.core.errors import EdgeError

# What the unit hides (ProtectHome=yes, PrivateTmp=yes): the service sees these empty.
HIDDEN_DIRS = {
    "/home": "ProtectHome=yes", "/root": "ProtectHome=yes", "/run/user": "ProtectHome=yes",
    "/tmp": "PrivateTmp=yes", "/var/tmp": "PrivateTmp=yes",
}
# The unit's StateDirectory=vtzero: the only place the service may write.
STATE_DIR = PurePosixPath("/var/lib/vtzero")
VENV_HINT = ("install vtzero into a venv the service can see, made from the system's Python "
             "(a pyenv or user-installed one lives in a home directory): /usr/bin/python3 -m "
             "venv /opt/vtzero/venv && /opt/vtzero/venv/bin/pip install 'vtzero[edge]', then "
             "run /opt/vtzero/venv/bin/vt-edge install-service")
FILES_HINT = "keep the files it reads under /etc/vtzero or /opt/vtzero"
PYTHON_PARTS = ("the program", "the interpreter", "the Python installation", "the edge package")
# useradd/groupadd take a moment; a host whose account tools hang is not one to wait on.
ACCOUNT_TOOL_TIMEOUT_S = 30.0


def hidden_by(path: str | Path) -> str | None:
    """The unit setting that hides ``path`` from the service, or None if it can see it."""
    p = PurePosixPath(path)
    for top, setting in HIDDEN_DIRS.items():
        if p == PurePosixPath(top) or PurePosixPath(top) in p.parents:
            return setting
    return None


def interpreter_paths(exec_start: str) -> list[tuple[str, Path]]:
    """What running ``exec_start`` under the unit reads: the program, this interpreter as
    named and as resolved (a venv's python is a link to the base one), the base
    installation's standard library and the directory the ``edge`` package is imported from
    (an editable install points into its source tree)."""
    return [
        ("the program", Path(exec_start.split()[0])),
        ("the interpreter", Path(sys.executable)),
        ("the interpreter", Path(sys.executable).resolve()),
        ("the Python installation", Path(sys.base_prefix)),
        ("the edge package", Path(edge.__file__).resolve().parent),
    ]


Named = list[tuple[str, Path]]


def config_paths(cfg: Config, config: Path) -> tuple[Named, Named]:
    """(files the service reads, directories it writes) that the configuration names."""
    reads = [("the config file", config), ("[runtime] models_dir", Path(cfg.runtime.models_dir))]
    for name, value in (("[api] token_file", cfg.api.token_file),
                        ("[vlm] api_key_file", cfg.vlm.api_key_file),
                        ("[mqtt] password_file", cfg.mqtt.password_file)):
        if value:
            reads.append((name, Path(value)))
    writes = []
    if cfg.runtime.record_mcap_dir:
        writes.append(("[runtime] record_mcap_dir", Path(cfg.runtime.record_mcap_dir)))
    return reads, writes


def check_paths(reads: Iterable[tuple[str, Path]], writes: Iterable[tuple[str, Path]]) -> None:
    """Raise :class:`EdgeError` (one line) naming every path the service could not use."""
    if problem := path_problem(reads, writes):
        raise EdgeError(problem)


def path_problem(reads: Iterable[tuple[str, Path]],
                 writes: Iterable[tuple[str, Path]]) -> str | None:
    """One line naming every path the service could not use and what to do; None if it
    could use them all."""
    problems: dict[str, bool] = {}  # message -> is it part of the Python install
    for what, path in reads:
        if not path.is_absolute():
            problems[f"{what} {path} (relative, and the service runs in /: give an "
                     "absolute path)"] = False
        elif setting := hidden_by(path) or hidden_by(path.resolve()):  # a link into /home
            problems[f"{what} {path} (hidden by {setting})"] = what in PYTHON_PARTS
    for what, path in writes:
        if not path.is_absolute() or STATE_DIR not in (PurePosixPath(path), *path.parents):
            problems[f"{what} {path} (not writable under ProtectSystem=strict: put it "
                     f"under {STATE_DIR})"] = False
    if not problems:
        return None
    hint = VENV_HINT if any(problems.values()) else FILES_HINT
    return "the service could not use " + ", ".join(problems) + f"; {hint}"


def needed_groups(cfg: Config) -> list[str]:
    """The groups owning the devices the configuration uses (Debian/Raspberry Pi OS names):
    the serial ports (bus and serial button), a local camera, GPIO lines."""
    groups = ["dialout"]
    if cfg.camera.kind in ("command", "v4l2"):
        groups.append("video")
    if cfg.button.kind == "gpio":
        groups.append("gpio")
    return groups


def group_exists(name: str) -> bool:
    try:
        grp.getgrnam(name)
    except KeyError:
        return False
    return True


def primary_group(user: str) -> str | None:
    """``user``'s primary group, or None if there is no such user."""
    try:
        gid = pwd.getpwnam(user).pw_gid
    except KeyError:
        return None
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


def useradd_command(user: str) -> list[str]:
    """A system user with a group of its own, no login and no home of its own: the unit's
    StateDirectory creates /var/lib/vtzero for it."""
    return ["useradd", "--system", "--user-group", "--home-dir", str(STATE_DIR),
            "--no-create-home", "--shell", "/usr/sbin/nologin", user]


def groupadd_command(group: str) -> list[str]:
    return ["groupadd", "--system", group]


GROUP_DEVICES = {
    "gpio": "and give it the GPIO chips with `vt-edge install-udev --install` (which writes "
            "that rule once the group exists)",
}


@dataclass(frozen=True)
class Accounts:
    """The user and groups the unit will name, and what the host still lacks."""

    user: str
    group: str
    groups: tuple[str, ...]
    missing_user: bool
    missing_groups: tuple[str, ...]

    def todo(self) -> list[str]:
        """One line per account to create before the service can start."""
        lines = []
        if self.missing_user:
            lines.append(f"user {self.user} does not exist: create it with "
                         f"`{' '.join(useradd_command(self.user))}` "
                         "(or run install-service again with --create-user)")
        for g in self.missing_groups:
            extra = GROUP_DEVICES.get(g, "")
            lines.append(f"group {g} does not exist: create it with "
                         f"`{' '.join(groupadd_command(g))}`{' ' + extra if extra else ''}, "
                         "then run install-service again")
        return lines


def accounts(cfg: Config, user: str) -> Accounts:
    group = primary_group(user)
    needed = needed_groups(cfg)
    missing = tuple(g for g in needed if not group_exists(g))
    return Accounts(user=user, group=group or user,
                    groups=tuple(g for g in needed if g not in missing),
                    missing_user=group is None, missing_groups=missing)


def create_accounts(acc: Accounts) -> list[str]:
    """Create the missing groups and user; returns the commands run."""
    commands = [groupadd_command(g) for g in acc.missing_groups]
    if acc.missing_user:
        commands.append(useradd_command(acc.user))
    for command in commands:
        try:
            subprocess.run(command, check=True, capture_output=True, text=True,
                           timeout=ACCOUNT_TOOL_TIMEOUT_S)
        except FileNotFoundError:
            raise EdgeError(f"{command[0]} not found: create the account by hand") from None
        except subprocess.CalledProcessError as exc:
            why = (exc.stderr or exc.stdout or "").strip().splitlines()
            raise EdgeError(f"`{' '.join(command)}` failed (exit {exc.returncode}): "
                            f"{why[-1] if why else 'no message'}") from None
    return [" ".join(c) for c in commands]


def service_unit(cfg: Config, config: Path, exec_start: str, acc: Accounts) -> str:
    """The unit for this configuration: run as ``acc``'s user with the device groups that
    exist, allowed the real-time scheduling the configuration asks for."""
    from edge.deploy.unit import unit_text

    priority = cfg.runtime.realtime_priority if cfg.runtime.realtime else None
    return unit_text(exec_start, str(config), acc.user, realtime_priority=priority,
                     group=acc.group, groups=acc.groups)


def readable_note(path: Path, acc: Accounts) -> str | None:
    """A line when the service user could not read ``path`` (neither world-readable nor
    group-readable by the user's group); None when it can."""
    st = path.stat()
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    if st.st_mode & 0o004 or (st.st_mode & 0o040 and group == acc.group):
        return None
    return (f"{path} is not readable by {acc.user}: chgrp {acc.group} {path} && "
            f"chmod 0640 {path}")


def install_service(config_path: str | Path, user: str, *, create_user: bool = False,
                    write: bool = False) -> int:
    """`vt-edge install-service`: check the host, then print the unit or install it. A
    unit that could not start as it is (a path it could not see, a missing user) is
    refused for installing; printed, with a line on stderr for each problem."""
    from edge.deploy import unit as unit_file

    config = Path(config_path).resolve()
    if not config.is_file():
        raise EdgeError(f"config file {config} does not exist: write it first (start from "
                        "configs/robot.toml), then run install-service again")
    cfg = load_config(config)
    beside = Path(sys.executable).with_name("vt-edge")
    exe = str(beside) if beside.exists() else shutil.which("vt-edge") or f"{sys.executable} -m edge"
    reads, writes = config_paths(cfg, config)
    unseen = path_problem([*interpreter_paths(exe), *reads], writes)
    if unseen and write:
        raise EdgeError(unseen)
    acc = accounts(cfg, user)
    if create_user and (acc.missing_user or acc.missing_groups):
        for command in create_accounts(acc):
            print(f"ran: {command}", file=sys.stderr)
        acc = accounts(cfg, user)
    todo = acc.todo()
    if note := readable_note(config, acc):
        todo.append(note)
    if todo and write:
        raise EdgeError("before installing the unit: " + "; ".join(todo))
    unit = service_unit(cfg, config, exe, acc)
    if unseen:
        print(f"warning: as printed, the unit would not start: {unseen}", file=sys.stderr)
    for line in todo:
        print(f"note: {line}", file=sys.stderr)
    if not Path(cfg.runtime.models_dir, "manifest.json").is_file():
        print(f"note: no model in {cfg.runtime.models_dir}: put one there with `vt-edge models "
              f"install DIR --config {config}`", file=sys.stderr)
    if not write:
        print(unit, end="")
        return 0
    path = unit_file.install(unit)
    print(f"installed {path}; now: systemctl daemon-reload && systemctl enable --now "
          f"{unit_file.UNIT_NAME}")
    return 0
