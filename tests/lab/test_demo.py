"""``make run`` (``vt-edge demo``): with no endpoint the simulated VLM answers and every label
says so; with ``$VTZERO_VLM_URL`` set that endpoint answers and the stand-in is not started."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from edge.core import tomledit
from tests.support.vlm_thread import fake_in_thread
from tests.support.waits import free_port

ROOT = Path(__file__).resolve().parents[2]
DEMO = ("import sys; from edge.lab.demo import run_demo; "
        "sys.exit(run_demo(sys.argv[1], tuple(sys.argv[2:])))")


def run_demo(tmp_path: Path, objects: tuple[str, ...], **env: str) -> str:
    config = tmp_path / "sim.toml"
    tomledit.update(ROOT / "configs" / "sim.toml", config, {"api": {"port": free_port()}})
    clean = {k: v for k, v in os.environ.items() if not k.startswith("VTZERO_VLM")}
    out = subprocess.run([sys.executable, "-c", DEMO, str(config), *objects], cwd=ROOT,
                         env={**clean, **env}, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def test_without_an_endpoint_the_labels_come_from_the_simulated_vlm(tmp_path):
    out = run_demo(tmp_path, ("boiled_kiri_mochi",))
    print(out)
    assert "starting the simulated VLM" in out
    label_lines = [line for line in out.splitlines() if "label (" in line]
    assert len(label_lines) == 1
    assert label_lines[0].strip().startswith("label (simulated VLM): ")
    assert "simulated VLM: " in out and "not a real model" in out
    assert "VTZERO_VLM_URL=" in out  # how to use a real one


def test_with_an_endpoint_the_stand_in_is_not_involved(tmp_path):
    with fake_in_thread(model="some-vlm") as fake:
        out = run_demo(tmp_path, ("raw_kiri_mochi",), VTZERO_VLM_URL=fake.base_url,
                       VTZERO_VLM_MODEL="some-vlm")
        requests = fake.chat_requests
    print(out)
    assert len(requests) == 1 and requests[0].body["model"] == "some-vlm"
    assert "simulated VLM" not in out
    # The fake answers the first candidate of the Cube set.
    assert "label (VLM some-vlm): raw_kabocha_squash  (wrong)" in out
