"""The project's commands as processes, run as a user runs them: the emulated robot
(``vt-edge sim serve``), a command's output read as it comes, and a person at the robot who
answers ``vt-edge collect``'s prompts (puts the named object between the fingers, presses
Enter)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from edge.core import tomledit
from edge.core.config import load_config
from edge.lab.stack import http_json, stop, wait_for
from tests.support.daemon import ROOT

# The command lines as a user runs them.
VT_EDGE = [sys.executable, "-m", "edge"]
VT_TRAIN = [sys.executable, "-m", "train"]
# Generous: the host may be a loaded two-core machine.
START_TIMEOUT_S = 60
COMMAND_TIMEOUT_S = 120
# How often the person looks at the terminal for a new prompt.
PROMPT_POLL_S = 0.02
# Collect's prompts end without a newline, with "then Enter "; the first of a class names it.
_PROMPT = re.compile(r"place the (\w+) .*?then Enter |then Enter ", re.S)


def clean_env(**extra: str) -> dict[str, str]:
    """This process's environment without the settings a developer's shell may carry into
    a command under test (a VLM, a systemd socket, a log level)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for key in ("VTZERO_VLM_URL", "VTZERO_VLM_MODEL", "NOTIFY_SOCKET", "VTZERO_LOG_LEVEL",
                "VTZERO_STATE_DIR"):
        env.pop(key, None)
    return env | extra


class Output:
    """A process's stdout as it comes (prompts end without a newline)."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.text = ""
        self._proc = proc
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while chunk := self._proc.stdout.read1(4096):  # type: ignore[union-attr]
            self.text += chunk.decode(errors="replace")

    def wait_for(self, needle: str, timeout_s: float = COMMAND_TIMEOUT_S) -> None:
        wait_for(lambda: needle in self.text, timeout_s, f"{needle!r} in the output\n"
                 f"{self.text}", self._proc)


def start(command: list[str], env: dict[str, str], *, stdin: bool = False
          ) -> tuple[subprocess.Popen, Output]:
    """``command`` (``[*VT_EDGE, ...]``) in the repository root, its stdout read as it comes;
    ``stdin``: a pipe to answer its prompts through."""
    proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL)
    return proc, Output(proc)


def interrupt(proc: subprocess.Popen, output: Output) -> tuple[int, float]:
    """Ctrl-C to ``proc``: its exit code and the seconds it took to exit (printed)."""
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    rc = proc.wait(30)
    took = time.monotonic() - t0
    print(f"exit {rc} {took:.2f} s after SIGINT\n{output.text}")
    return rc, took


def run(command: list[str], env: dict[str, str], timeout_s: float = COMMAND_TIMEOUT_S,
        ok: tuple[int, ...] = (0,)) -> subprocess.CompletedProcess:
    """``command`` to its end; its exit status must be one of ``ok``."""
    done = subprocess.run(command, cwd=ROOT, env=env, text=True, capture_output=True,
                          timeout=timeout_s)
    assert done.returncode in ok, (f"{' '.join(command[2:])}: exit {done.returncode}\n"
                                   f"{done.stdout}\n{done.stderr}")
    return done


@contextlib.contextmanager
def sim_serve(directory: Path, object_name: str, env: dict[str, str],
              changes: dict[str, dict[str, Any]] | None = None) -> Iterator[Path]:
    """``vt-edge sim serve --write-config``: yields the runtime configuration it wrote
    (``directory/run.toml``) with ``changes`` applied; the emulated robot stops after."""
    config = directory / "run.toml"
    sim = subprocess.Popen([*VT_EDGE, "sim", "serve", "--config", "configs/sim.toml",
                            "--object", object_name, "--write-config", str(config)],
                           cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
    try:
        wait_for(config.exists, START_TIMEOUT_S, "emulated robot", sim)
        if changes:
            tomledit.update(config, config, changes)
        yield config
    finally:
        stop(sim, "emulated robot")


def control_url(config: Path) -> str:
    """The emulated robot's control endpoint (beside its camera's snapshot URL)."""
    return load_config(config).camera.url.rsplit("/", 1)[0]


def place(config: Path, name: str) -> None:
    """Put a piece of ``name`` between the emulated robot's fingers."""
    reply = http_json("POST", f"{control_url(config)}/object", {"name": name})
    assert reply.get("object") == name, reply


class Person:
    """Someone at the emulated robot answering a running ``vt-edge collect``: at "place the
    OBJECT ... then Enter" they put OBJECT between the fingers, then press Enter; at "move it
    slightly ... then Enter" they press Enter (the emulated robot puts a fresh piece back)."""

    def __init__(self, config: Path, proc: subprocess.Popen, output: Output) -> None:
        self.placed: list[str] = []
        self._config, self._proc, self._output = config, proc, output
        self._thread = threading.Thread(target=self._answer, daemon=True)
        self._thread.start()

    def _answer(self) -> None:
        seen = 0
        while self._proc.poll() is None:
            m = _PROMPT.search(self._output.text, seen)
            if m is None:
                threading.Event().wait(PROMPT_POLL_S)
                continue
            seen = m.end()
            if m.group(1):
                place(self._config, m.group(1))
                self.placed.append(m.group(1))
            try:
                self._proc.stdin.write(b"\n")  # type: ignore[union-attr]
                self._proc.stdin.flush()  # type: ignore[union-attr]
            except OSError:  # it has ended (Ctrl-C) while we answered
                return


def collect(config: Path, env: dict[str, str], *args: str
            ) -> tuple[subprocess.Popen, Output, Person]:
    """``vt-edge collect --config CONFIG ARGS`` with a person answering its prompts."""
    proc, output = start([*VT_EDGE, "collect", "--config", str(config), *args], env,
                         stdin=True)
    return proc, output, Person(config, proc, output)
