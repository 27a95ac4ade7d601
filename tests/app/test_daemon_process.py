"""The daemon as a process, as systemd runs it: SIGTERM in the middle of a press; a start
that cannot succeed."""

import functools
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from edge.core import tomledit
from edge.core.config import load_config
from edge.lab.stack import http_json
from edge.lab.stack import wait_for as _wait_for
from edge.runtime.store import EpisodeStore
from tests.support.waits import free_port, wait_until_sync

ROOT = Path(__file__).resolve().parents[2]


def test_sigterm_mid_press_opens_the_gripper_and_exits_cleanly(tmp_path):
    env = dict(os.environ, VTZERO_STATE_DIR=str(tmp_path / "state"), PYTHONUNBUFFERED="1")
    env.pop("VTZERO_VLM_URL", None)
    run_cfg = tmp_path / "run.toml"
    sim = subprocess.Popen([sys.executable, "-m", "edge", "sim", "serve", "--config",
                            str(ROOT / "configs" / "sim.toml"), "--object", "gelatin_soft",
                            "--write-config", str(run_cfg)], env=env, cwd=ROOT)
    daemon = None
    try:
        _wait_for(run_cfg.exists, 30, "sim", sim)
        port = free_port()
        tomledit.update(run_cfg, run_cfg, {"api": {"port": port}})
        api = f"http://127.0.0.1:{port}"
        control = load_config(run_cfg).camera.url.rsplit("/", 1)[0]
        daemon = subprocess.Popen([sys.executable, "-m", "edge", "run", "--config",
                                   str(run_cfg)], env=env, cwd=ROOT, stderr=subprocess.PIPE,
                                  text=True)
        _wait_for(lambda: http_json("GET", f"{api}/healthz").get("ok"), 60, "daemon", daemon)
        ep = http_json("POST", f"{api}/v1/recognize", {"candidates": ["a", "b"]})
        wait_until_sync(lambda: http_json("GET", f"{api}/healthz")["state"]
                        in ("closing", "holding"), 30, "the press closing")
        daemon.send_signal(signal.SIGTERM)
        _, err = daemon.communicate(timeout=30)
        print(err[-2000:])
        assert daemon.returncode == 0, err[-2000:]
        world = http_json("GET", f"{control}/object")
        assert world["force_n"] == 0.0 and world["gap_m"] > 0.025, world  # gripper open
        store = EpisodeStore(tmp_path / "state" / "episodes")
        assert store.recover() == 0  # nothing half-written
        stored = store.get(ep["id"])
        assert stored.status == "failed" and "abort" in stored.error
        assert stored.press is not None
        print(json.dumps(stored.press.to_json()["states"]))
    finally:
        if daemon is not None and daemon.poll() is None:
            daemon.kill()
        sim.send_signal(signal.SIGTERM)
        sim.wait(20)


def test_a_start_that_cannot_listen_says_why_in_one_line_and_exits_2(tmp_path):
    """Nothing else is needed to see it: the port is bound before any device is opened."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        run_cfg = tmp_path / "run.toml"
        tomledit.update(ROOT / "configs" / "sim.toml", run_cfg, {"api": {"port": port}})
        env = dict(os.environ, VTZERO_STATE_DIR=str(tmp_path / "state"))
        proc = subprocess.run([sys.executable, "-m", "edge", "run", "--config", str(run_cfg)],
                              env=env, cwd=ROOT, capture_output=True, text=True, timeout=120)
    print(proc.stderr[-1500:])
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        f"vt-edge: cannot listen on 127.0.0.1:{port}: address already in use")


def test_sighup_and_sigterm_while_the_daemon_starts_are_never_fatal(tmp_path):
    """`systemctl reload` or a deployment script's reload right after a start: the daemon
    reaches ready (the reload follows); a stop during the start is a clean exit."""
    env = dict(os.environ, VTZERO_STATE_DIR=str(tmp_path / "state"), PYTHONUNBUFFERED="1")
    env.pop("VTZERO_VLM_URL", None)
    run_cfg = tmp_path / "run.toml"
    sim = subprocess.Popen([sys.executable, "-m", "edge", "sim", "serve", "--config",
                            str(ROOT / "configs" / "sim.toml"), "--write-config", str(run_cfg)],
                           env=env, cwd=ROOT)
    daemon = None
    try:
        _wait_for(run_cfg.exists, 30, "sim", sim)
        port = free_port()
        tomledit.update(run_cfg, run_cfg, {"api": {"port": port}})
        api = f"http://127.0.0.1:{port}"
        for sig, after_s in ((signal.SIGHUP, 0.1), (signal.SIGHUP, 0.3), (signal.SIGHUP, 0.6),
                             (signal.SIGTERM, 0.1), (signal.SIGTERM, 0.6)):
            started = time.monotonic()
            daemon = subprocess.Popen([sys.executable, "-m", "edge", "run", "--config",
                                       str(run_cfg)], env=env, cwd=ROOT,
                                      stderr=subprocess.PIPE, text=True)
            # Held from the package's first instruction: before it, the interpreter's own
            # start (about 25 ms on an idle host, 100 ms or more beside a two-core hog) runs
            # no code of ours. A signal goes at after_s, or once that start is over.
            held = wait_until_sync(functools.partial(_catches, daemon.pid, sig), 30,
                                   "the interpreter's start") - started
            time.sleep(max(0.0, started + after_s - time.monotonic()))
            daemon.send_signal(sig)
            if sig == signal.SIGHUP:
                _wait_for(lambda: http_json("GET", f"{api}/healthz").get("ready"), 60,
                          "daemon", daemon)
                daemon.send_signal(signal.SIGTERM)
            _, err = daemon.communicate(timeout=60)
            print(f"{sig.name} at {after_s} s (held after {held:.3f} s): exit "
                  f"{daemon.returncode}")
            assert daemon.returncode == 0, err[-2000:]
            if sig == signal.SIGHUP:
                assert "reloaded configuration, model, database" in err, err[-2000:]
    finally:
        if daemon is not None and daemon.poll() is None:
            daemon.kill()
        sim.send_signal(signal.SIGTERM)
        sim.wait(20)


def _catches(pid: int, sig: signal.Signals) -> float | None:
    """Whether process ``pid`` has a handler for ``sig`` (its SigCgt mask): a time, for
    wait_until_sync, once it does."""
    status = Path(f"/proc/{pid}/status").read_text()
    caught = int(next(line.split()[1] for line in status.splitlines()
                      if line.startswith("SigCgt:")), 16)
    return time.monotonic() if caught >> (sig - 1) & 1 else None
