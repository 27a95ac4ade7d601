"""onnxruntime's telemetry stays off: no device id or event cache is written under $HOME
when the daemon's model is loaded and run (and so nothing is there to upload)."""

import os
import subprocess
import sys

from tests.harness import ROOT

LOAD_AND_RUN = """
import numpy as np
from edge.model import load_model
model = load_model("models")
print(model.encode(np.zeros((25, 96), np.float32))[1])
"""


def _run(home, **env):
    clean = {k: v for k, v in os.environ.items() if k != "ORT_DISABLE_TELEMETRY"}
    out = subprocess.run([sys.executable, "-c", LOAD_AND_RUN], cwd=ROOT, timeout=120,
                         env={**clean, "HOME": str(home), **env}, capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr
    return sorted(str(p.relative_to(home)) for p in home.rglob("*"))


def test_loading_and_running_the_model_writes_nothing_under_home(tmp_path):
    written = _run(tmp_path)
    print("written under $HOME:", written)
    assert written == []


def test_an_explicit_choice_is_left_alone(tmp_path):
    # The check above can fail: with the variable set to 0, onnxruntime writes its files.
    written = _run(tmp_path, ORT_DISABLE_TELEMETRY="0")
    print("written under $HOME with ORT_DISABLE_TELEMETRY=0:", written)
    assert any("onnxruntime" in p for p in written)
