"""On an edge-only install (no torch, onnx, matplotlib) vt-train says which extra to install."""

import subprocess
import sys

import pytest

BLOCK = """
import importlib.abc, sys

class Missing(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name in {blocked!r} or name.split(".")[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None

sys.meta_path.insert(0, Missing())
from train.cli import main
sys.exit(main({argv!r}))
"""


def _vt_train(blocked, argv):
    code = BLOCK.format(blocked=set(blocked), argv=list(argv))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)


@pytest.mark.parametrize(("blocked", "argv", "module"), [
    (("torch", "onnx", "matplotlib"), ["train", "--recordings", "r", "--out", "o"], "torch"),
    (("onnx",), ["export", "--checkpoint", "c.pt", "--out", "o"], "onnx"),
])
def test_a_training_command_names_the_extra_in_one_line(blocked, argv, module):
    out = _vt_train(blocked, argv)
    print(out.stderr.strip())
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    assert f"vt-train {argv[0]} needs the training extra (no module '{module}')" in lines[0]
    assert "pip install 'vtzero[train]'" in lines[0]


def test_any_other_missing_module_keeps_its_traceback():
    out = _vt_train(("train.learn.data",), ["train", "--recordings", "r", "--out", "o"])
    assert out.returncode == 1 and "Traceback" in out.stderr
    assert "ModuleNotFoundError: No module named 'train.learn.data'" in out.stderr
