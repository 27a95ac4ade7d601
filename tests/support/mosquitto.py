"""A real MQTT broker for the tests: ``mosquitto`` on a free loopback port, its own config,
log and persistence in the test's temp directory. Tests that need it are skipped, saying
why, where the binary is absent (``.ci/run`` installs it)."""

from __future__ import annotations

import getpass
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from tests.support.waits import free_port

MOSQUITTO = shutil.which("mosquitto") or next(
    (p for p in ("/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto") if os.access(p, os.X_OK)),
    None)
requires_mosquitto = pytest.mark.needs_program(
    MOSQUITTO is not None, "the mosquitto MQTT broker is not installed (apt-get install "
    "mosquitto; .ci/run installs it)")
START_TIMEOUT_S = 5.0




class Mosquitto:
    """``with Mosquitto(tmp_path) as broker:``; :meth:`kill` and :meth:`start` again keep
    the port (and, with ``persistence``, the sessions saved by :meth:`save`)."""

    def __init__(self, directory: Path, persistence: bool = False) -> None:
        self.dir = Path(directory) / "mosquitto"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.persistence = persistence
        self.proc: subprocess.Popen | None = None
        self.conf = self.dir / "mosquitto.conf"
        self.conf.write_text(
            f"listener {self.port} 127.0.0.1\n"
            "allow_anonymous true\n"
            f"user {getpass.getuser()}\n"
            f"persistence {'true' if persistence else 'false'}\n"
            f"persistence_location {self.dir}/\n"
            "autosave_interval 0\n")
        self.log = self.dir / "mosquitto.log"

    @property
    def db(self) -> Path:
        return self.dir / "mosquitto.db"

    def start(self) -> Mosquitto:
        assert MOSQUITTO is not None
        with self.log.open("a") as log:
            self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=log,
                                         stderr=subprocess.STDOUT)
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return self
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"mosquitto did not start: {self.log.read_text()}") from None
                time.sleep(0.02)

    def save(self) -> None:
        """Write the persistence database now (SIGUSR1), and wait for it."""
        before = self.db.stat().st_mtime_ns if self.db.exists() else None
        assert self.proc is not None
        self.proc.send_signal(signal.SIGUSR1)
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self.db.exists() or self.db.stat().st_mtime_ns == before:
            assert time.monotonic() < deadline, "mosquitto did not save its database"
            time.sleep(0.02)

    def kill(self) -> None:
        """The broker dies (SIGKILL): no goodbye to anyone, no last save."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)

    def __enter__(self) -> Mosquitto:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
