"""The daemon phase: ``vt-edge run`` as a process, against ``vt-edge sim serve``.

Time from process start to ``READY=1`` on a ``NOTIFY_SOCKET`` bound here; the memory of the
daemon's processes (the daemon, its forkserver, compute worker and resource tracker) at
steady state after a recognition; and whether torch is mapped into any of them.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from edge.bench.figures import figure, stats, target
from edge.bench.host import torch_mappings, tree_memory_mb
from edge.bench.proc import process_tree
from edge.bench.results import PhaseResult, progress
from edge.bench.settings import CUBE, HELPER_START_S, OBJECTS, ROOT, SIM_CONFIG, Settings
from edge.lab.stack import http_json


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def daemon_phase(s: Settings, tmp: Path) -> PhaseResult:
    from edge.core import tomledit
    from edge.core.config import load_config

    notes: list[str] = []
    env = dict(os.environ, VTZERO_STATE_DIR=str(tmp / "daemon-state"), PYTHONUNBUFFERED="1",
               VTZERO_LOG_LEVEL="WARNING")
    for key in ("VTZERO_VLM_URL", "VTZERO_VLM_MODEL", "NOTIFY_SOCKET", "WATCHDOG_USEC",
                "WATCHDOG_PID"):
        env.pop(key, None)
    run_cfg = tmp / "daemon.toml"
    progress("daemon process: starting `vt-edge sim serve`")
    sim = subprocess.Popen([sys.executable, "-m", "edge", "sim", "serve", "--config",
                            str(SIM_CONFIG), "--object", OBJECTS[0], "--write-config",
                            str(run_cfg)], cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
    startup, rss, hwm, pss, main_rss, torch_found = [], [], [], [], [], []
    try:
        deadline = time.monotonic() + HELPER_START_S
        while not run_cfg.exists():
            if sim.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("vt-edge sim serve did not write its configuration")
            time.sleep(0.05)
        port = _free_port()
        tomledit.update(run_cfg, run_cfg, {"api": {"port": port}})
        api = f"http://127.0.0.1:{port}"
        control = load_config(run_cfg).camera.url.rsplit("/", 1)[0]
        for i in range(s.daemon_runs):
            sock_path = tmp / f"notify-{i}.sock"
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
                sock.bind(str(sock_path))
                log_path = tmp / f"daemon-{i}.log"
                with log_path.open("w") as err:
                    t0 = time.monotonic()
                    proc = subprocess.Popen(
                        [sys.executable, "-m", "edge", "run", "--config", str(run_cfg)],
                        cwd=ROOT, env={**env, "NOTIFY_SOCKET": str(sock_path)},
                        stdout=subprocess.DEVNULL, stderr=err)
                    try:
                        t_ready = _wait_ready(sock, proc, 60.0)
                        startup.append(t_ready - t0)
                        progress(f"daemon process {i + 1}/{s.daemon_runs}: READY=1 after "
                                 f"{t_ready - t0:.2f} s; one recognition, then RSS")
                        http_json("POST", f"{control}/object", {"name": OBJECTS[i % 2]})
                        ep = http_json("POST", f"{api}/v1/recognize",
                                       {"candidates": CUBE, "wait": True, "timeout_s": 50},
                                       timeout=60)
                        if ep.get("status") not in ("not_configured", "done"):
                            notes.append(f"daemon process recognition: {ep.get('status')} "
                                         f"{ep.get('error', '')}")
                        for _ in range(s.rss_samples):
                            time.sleep(0.5)
                            http_json("GET", f"{api}/healthz", timeout=5)
                            now, peak, proportional, own = tree_memory_mb(proc.pid)
                            rss.append(now)
                            hwm.append(peak)
                            pss.append(proportional)
                            main_rss.append(own)
                        torch_found.append([m for p in process_tree(proc.pid)
                                            for m in torch_mappings(p)])
                    finally:
                        if proc.poll() is None:
                            proc.send_signal(signal.SIGTERM)
                        try:
                            rc = proc.wait(30)
                        except subprocess.TimeoutExpired:
                            proc.kill()
                            rc = proc.wait()
                    if rc != 0:
                        notes.append(f"daemon run {i + 1} exited with {rc}; log: "
                                     f"{log_path.read_text()[-500:]}")
    finally:
        sim.send_signal(signal.SIGTERM)
        try:
            sim.wait(20)
        except subprocess.TimeoutExpired:
            sim.kill()
    mapped = sorted({p for found in torch_found for p in found})
    figs = {
        "startup_to_ready_s": figure(startup, "s", target(("max", "<=", 3.0)),
                                     what="`vt-edge run` process start -> READY=1 received on "
                                          "NOTIFY_SOCKET"),
        "daemon_rss_mb": figure(pss, "MiB", target(("max", "<=", 150.0)),
                                rss_sum_mb=stats(rss), main_rss_mb=stats(main_rss),
                                peak_hwm_sum_mb=max(hwm) if hwm else None,
                                what="memory of the daemon's processes (the daemon, its "
                                     "forkserver, compute worker and resource tracker) at "
                                     "steady state after one recognition: their Pss summed "
                                     "(pages shared between them split, not counted in each; "
                                     "rss_sum_mb counts them in each, main_rss_mb is the "
                                     "event-loop process alone)"),
        "daemon_torch_mapped": figure([len(f) for f in torch_found], "files",
                                      target(("max", "==", 0)), mapped=mapped,
                                      what="torch libraries mapped into any of the daemon's "
                                           "processes (/proc/PID/maps) after a recognition"),
    }
    if mapped:
        notes.append(f"TORCH IS LOADED BY THE DAEMON: {mapped[:3]}")
    return PhaseResult(figs, notes)


def _wait_ready(sock: socket.socket, proc: subprocess.Popen, timeout_s: float) -> float:
    deadline = time.monotonic() + timeout_s
    while True:
        left = deadline - time.monotonic()
        if left <= 0 or proc.poll() is not None:
            raise RuntimeError(f"daemon sent no READY=1 (exit {proc.poll()})")
        sock.settimeout(min(left, 0.5))
        try:
            data = sock.recv(4096)
        except TimeoutError:
            continue
        t = time.monotonic()
        if b"READY=1" in data.split(b"\n"):
            return t
