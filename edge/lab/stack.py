"""The emulated robot and the daemon as processes, as a user runs them: ``vt-edge sim serve``
(the emulated arm and pads) and ``vt-edge run`` (the daemon, unchanged but for device
addresses), driven over HTTP."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 20.0


def http_json(method: str, url: str, body: dict | None = None, timeout: float = 10.0) -> dict:
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(url, data=data, method=method,
                                 headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            return json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        try:
            return {"http_status": exc.code, **json.loads(exc.read() or b"{}")}
        except ValueError:  # an error page that is not JSON
            return {"http_status": exc.code}


def wait_for(predicate, timeout_s: float, what: str, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"{what}: process exited with {proc.returncode}")
        try:
            if predicate():
                return
        except (OSError, ValueError):
            pass
        time.sleep(0.1)
    raise RuntimeError(f"{what}: not ready within {timeout_s} s")


def stop(proc: subprocess.Popen, name: str) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if proc.returncode not in (0, -signal.SIGTERM):
        print(f"warning: {name} exited with {proc.returncode}", file=sys.stderr)
    return proc.returncode


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@dataclass(frozen=True)
class Stack:
    api: str  # the daemon's HTTP API
    control: str  # the emulated robot's control endpoint (place an object)
    state: Path  # the daemon's state directory (its episodes)

    def place(self, name: str) -> None:
        http_json("POST", f"{self.control}/object", {"name": name})

    def world(self) -> dict:
        return http_json("GET", f"{self.control}/object")


@contextlib.contextmanager
def sim_stack(config: str | Path = "configs/sim.toml", first_object: str = "stainless_cube",
              env: dict[str, str] | None = None) -> Iterator[Stack]:
    """Start the emulated robot, then the daemon on it; both are stopped on the way out."""
    from edge.core import tomledit
    from edge.core.config import load_config

    env = dict(os.environ if env is None else env, PYTHONUNBUFFERED="1")
    env.setdefault("VTZERO_LOG_LEVEL", "WARNING")
    with tempfile.TemporaryDirectory(prefix="vtzero-sim-") as tmp:
        run_cfg = Path(tmp) / "sim-run.toml"
        state = Path(tmp) / "state"
        env["VTZERO_STATE_DIR"] = str(state)
        sim = subprocess.Popen([sys.executable, "-m", "edge", "sim", "serve", "--config",
                                str(config), "--write-config", str(run_cfg), "--object",
                                first_object], env=env, stdout=subprocess.DEVNULL)
        daemon = None
        try:
            wait_for(run_cfg.exists, START_TIMEOUT_S, "emulated robot", sim)
            # A port of its own: another daemon (or a test) may hold the configured one.
            tomledit.update(run_cfg, run_cfg, {"api": {"port": _free_port()}})
            cfg = load_config(run_cfg)
            api = f"http://{cfg.api.host}:{cfg.api.port}"
            daemon = subprocess.Popen([sys.executable, "-m", "edge", "run", "--config",
                                       str(run_cfg)], env=env)
            wait_for(lambda: http_json("GET", f"{api}/healthz").get("ok"), START_TIMEOUT_S,
                     "daemon", daemon)
            yield Stack(api, cfg.camera.url.rsplit("/", 1)[0], state)
        finally:
            if daemon is not None:
                stop(daemon, "daemon")
            stop(sim, "emulated robot")
