"""The user's loop on the emulated robot, run as a user runs it (processes and commands):
collect presses of an object the database does not know, add it with ``vt-train db add``,
SIGHUP the daemon, recognise it; then retrain on collected presses and run the daemon on
the new model."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from edge.core import tomledit
from edge.core.config import load_config
from edge.lab.stack import http_json, stop, wait_for
from tests.support.daemon import LOADED_HOST_ERRORS, LOADED_HOST_TRIES, ROOT
from tests.support.waits import free_port

NEW = "boiled_kiri_mochi"  # a test-set object: not in the shipped reference database
OTHER = "wood_cube"
CUBE = ["raw_kiri_mochi", "boiled_kiri_mochi", "raw_kabocha_squash", "boiled_kabocha_squash"]
COMMAND_TIMEOUT_S = 300


def cli(*args: str, env: dict[str, str]) -> str:
    done = subprocess.run([sys.executable, "-m", *args], cwd=ROOT, env=env, text=True,
                          capture_output=True, timeout=COMMAND_TIMEOUT_S)
    assert done.returncode == 0, f"{' '.join(args)} failed:\n{done.stdout}\n{done.stderr}"
    return done.stdout


class Robot:
    """``vt-edge sim serve`` and, when started, ``vt-edge run`` on it."""

    def __init__(self, tmp: Path, models: Path) -> None:
        self.env = dict(os.environ, PYTHONUNBUFFERED="1", VTZERO_LOG_LEVEL="WARNING",
                        VTZERO_STATE_DIR=str(tmp / "state"))
        for key in ("VTZERO_VLM_URL", "VTZERO_VLM_MODEL", "NOTIFY_SOCKET"):
            self.env.pop(key, None)
        self.config = tmp / "run.toml"
        self.sim = subprocess.Popen(
            [sys.executable, "-m", "edge", "sim", "serve", "--config", "configs/sim.toml",
             "--object", NEW, "--write-config", str(self.config)], cwd=ROOT, env=self.env,
            stdout=subprocess.DEVNULL)
        wait_for(self.config.exists, 60, "emulated robot", self.sim)
        self.port = free_port()
        # A quicker arm: the tactile data do not depend on how fast it travels. A stream is
        # stale after 0.25 s, not 0.1: the test shares a loaded host with the emulated robot.
        tomledit.update(self.config, self.config, {
            "api": {"port": self.port}, "sensor": {"stale_timeout_s": 0.25},
            "runtime": {"models_dir": str(models), "move_time_s": 0.2}})
        self.api = f"http://127.0.0.1:{self.port}"
        self.daemon: subprocess.Popen | None = None

    def place(self, name: str) -> None:
        control = load_config(self.config).camera.url.rsplit("/", 1)[0]
        assert http_json("POST", f"{control}/object", {"name": name}).get("object") == name

    def use_models(self, models: Path) -> None:
        tomledit.update(self.config, self.config, {"runtime": {"models_dir": str(models)}})

    def start_daemon(self) -> dict:
        self.daemon = subprocess.Popen([sys.executable, "-m", "edge", "run", "--config",
                                        str(self.config)], cwd=ROOT, env=self.env)
        wait_for(lambda: http_json("GET", f"{self.api}/healthz").get("ok"), 60, "daemon",
                 self.daemon)
        return http_json("GET", f"{self.api}/healthz")

    def stop_daemon(self) -> int | None:
        daemon, self.daemon = self.daemon, None
        return None if daemon is None else stop(daemon, "daemon")

    def recognise(self) -> dict:
        """One recognition, the touch part only (no VLM here); a press that failed for a loaded
        host's reason is pressed again, as tests.support.daemon.recognize does."""
        for attempt in range(1, LOADED_HOST_TRIES + 1):
            ep = http_json("POST", f"{self.api}/v1/recognize",
                           {"candidates": CUBE, "wait": True, "timeout_s": 60}, timeout=70)
            error = ep.get("error") or ""
            if (ep.get("status") == "failed" and attempt < LOADED_HOST_TRIES
                    and any(e in error for e in LOADED_HOST_ERRORS)):
                print(f"  press {attempt} failed on a loaded host, pressed again: {error}")
                continue
            assert ep.get("status") == "not_configured", (ep.get("status"), error)
            return ep
        raise AssertionError("unreachable")

    def close(self) -> None:
        self.stop_daemon()
        stop(self.sim, "emulated robot")


@pytest.fixture
def robot(tmp_path):
    models = tmp_path / "models"
    shutil.copytree(ROOT / "models", models)
    r = Robot(tmp_path, models)
    yield r
    r.close()


def test_collect_add_reload_recognise_then_retrain(robot, tmp_path):
    env = robot.env
    rec = tmp_path / "recordings"
    models = tmp_path / "models"
    out = cli("edge", "collect", "--config", str(robot.config), "--label", NEW,
              "--presses", "10", "--out", str(rec), "--no-prompt", env=env)
    assert len(list((rec / NEW).glob("*.press.npz"))) == 10, out

    health = robot.start_daemon()
    before = robot.recognise()
    assert NEW not in [t["label"] for t in before["topk"]]

    cli("train", "db", "add", "--model", str(models), "--recordings", str(rec / NEW),
        "--label", NEW, "--description", "boiled kiri mochi (a Japanese rice cake)", env=env)
    robot.daemon.send_signal(signal.SIGHUP)
    deadline = time.monotonic() + 30
    while http_json("GET", f"{robot.api}/healthz").get("model_digest") == health["model_digest"]:
        assert time.monotonic() < deadline, "the daemon did not take the new database"
        time.sleep(0.2)
    # The reload took the new database (the digest wait above), and the added class comes
    # first for its own object: a fresh piece per press, as a person puts it back, against
    # ten references of fresh pieces. Two of up to three presses: on a loaded host a frame
    # held back at the crossing lets one press go deeper (its first frame over x_th 25 %
    # past it: a firmer object's touch), seen in about one run in ten.
    afters: list[dict] = []
    while sum(bool(a["topk"]) and a["topk"][0]["label"] == NEW for a in afters) < 2:
        assert len(afters) < 3, [a["topk"] for a in afters]
        afters.append(robot.recognise())
    print("top-k before:", before["topk"], "\ntop-k after:", [a["topk"] for a in afters])
    assert robot.stop_daemon() in (0, -signal.SIGTERM)

    # Retraining on collected presses only: the new object and one more.
    robot.place(OTHER)
    cli("edge", "collect", "--config", str(robot.config), "--label", OTHER, "--presses", "3",
        "--out", str(rec), "--no-prompt", env=env)
    splits = tmp_path / "splits.json"
    splits.write_text(json.dumps({"train": [NEW], "val": [OTHER], "descriptions": {
        NEW: "boiled kiri mochi (a Japanese rice cake)", OTHER: "wood cube"}}))
    cli("train", "train", "--recordings", str(rec), "--splits", str(splits), "--out",
        str(tmp_path / "run"), "--max-epochs", "2", "--patience", "2", "-q", env=env)
    retrained = tmp_path / "retrained"
    cli("train", "export", "--checkpoint", str(tmp_path / "run" / "checkpoint.pt"), "--out",
        str(retrained), "--recordings", str(rec), env=env)
    cli("train", "db", "build", "--model", str(retrained), "--recordings", str(rec),
        "--splits", str(splits), env=env)
    # The prompt templates travel with a model directory; a retrained model keeps ours.
    shutil.copytree(ROOT / "models" / "prompts", retrained / "prompts")
    robot.use_models(retrained)
    assert robot.start_daemon()["model_digest"] != health["model_digest"]
    ep = robot.recognise()
    assert {t["label"] for t in ep["topk"]} == {NEW, OTHER}
