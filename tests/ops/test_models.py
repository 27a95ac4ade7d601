"""`vt-edge models install`: verified, atomic, the replaced directory kept."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from edge.core.atomic import PREVIOUS_SUFFIX
from edge.core.errors import ModelError
from edge.core.model import load_model
from edge.ops import models
from edge.ops.models import install_models

SHIPPED = Path(__file__).resolve().parents[2] / "models"


def _copy(tmp_path, name="src"):
    dst = tmp_path / name
    shutil.copytree(SHIPPED, dst)
    return dst


def test_install_puts_a_verified_copy_in_place_and_keeps_the_previous(tmp_path):
    src = _copy(tmp_path)
    dest = tmp_path / "opt" / "models"
    manifest, previous = install_models(src, dest)
    assert previous is None
    assert manifest == json.loads((SHIPPED / "manifest.json").read_text())
    load_model(dest)  # the daemon's own check
    for name in manifest["files"]:
        assert (dest / name).read_bytes() == (SHIPPED / name).read_bytes()
        assert os.stat(dest / name).st_mode & 0o777 == 0o644
    assert (dest / "eval" / "eval.md").exists()  # the whole directory, reports included
    assert not (tmp_path / "opt" / f"models{PREVIOUS_SUFFIX}").exists()

    # A second install: the first one becomes models.previous, one generation kept.
    (src / "README.md").write_text("second\n")
    _, previous = install_models(src, dest)
    assert (dest / "README.md").read_text() == "second\n"
    assert previous == tmp_path / "opt" / f"models{PREVIOUS_SUFFIX}"
    assert (previous / "README.md").read_bytes() == (SHIPPED / "README.md").read_bytes()
    (src / "README.md").write_text("third\n")
    install_models(src, dest)
    assert (previous / "README.md").read_text() == "second\n"
    assert sorted(p.name for p in (tmp_path / "opt").iterdir()) == [
        "models", f"models{PREVIOUS_SUFFIX}"]  # no temporary directory left


def test_a_damaged_source_is_refused_and_the_installed_one_untouched(tmp_path):
    dest = tmp_path / "opt" / "models"
    install_models(_copy(tmp_path, "good"), dest)
    before = {p: p.read_bytes() for p in dest.rglob("*") if p.is_file()}
    bad = _copy(tmp_path, "bad")
    data = bytearray((bad / "database.npz").read_bytes())
    data[-100] ^= 0xFF
    (bad / "database.npz").write_bytes(bytes(data))
    with pytest.raises(ModelError, match=r"database.npz: sha256 .* does not match"):
        install_models(bad, dest)
    assert {p: p.read_bytes() for p in dest.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in (tmp_path / "opt").iterdir()) == ["models"]
    (bad / "manifest.json").unlink()
    with pytest.raises(ModelError, match=r"manifest.json: missing"):
        install_models(bad, dest)
    with pytest.raises(ModelError, match="not a directory"):
        install_models(tmp_path / "nowhere", dest)
    with pytest.raises(ModelError, match="nothing to install"):
        install_models(dest, dest)


def test_a_copy_that_lands_damaged_is_never_renamed_into_place(tmp_path, monkeypatch):
    """The copy is read back against the manifest before the rename."""
    real = shutil.copyfile

    def flaky(src, dst, **kw):
        out = real(src, dst, **kw)
        if Path(dst).name == "encoder.onnx":
            Path(dst).write_bytes(Path(dst).read_bytes()[:-1])
        return out

    src = _copy(tmp_path)
    monkeypatch.setattr(models.shutil, "copyfile", flaky)
    dest = tmp_path / "opt" / "models"
    with pytest.raises(ModelError, match=r"\.tmp/encoder.onnx: sha256"):
        install_models(src, dest)
    assert not dest.exists() and list((tmp_path / "opt").iterdir()) == []


def test_origin_says_who_pressed_the_database():
    shipped = json.loads((SHIPPED / "manifest.json").read_text())
    # The shipped release, one older than "origin", and "origin": null: the emulated robot.
    older = {k: v for k, v in shipped.items() if k != "origin"}
    for manifest in (shipped, older, {**shipped, "origin": None}):
        assert "by the emulated robot; on a real robot replace it with the lab's own " \
            "references" in models.describe(manifest)
    robot = {**shipped, "origin": {"kind": "robot", "recorder": "lab", "robot": "arm-3",
                                   "sensor": None}}
    assert "pressed by the robot" in models.describe(robot)
    assert "replace" not in models.describe(robot)


def test_cli_installs_to_the_configs_models_dir(tmp_path):
    dest = tmp_path / "m"
    config = tmp_path / "robot.toml"
    config.write_text(f'[runtime]\nmodels_dir = "{dest}"\n')
    out = subprocess.run([sys.executable, "-m", "edge", "models", "install", str(SHIPPED),
                          "--config", str(config)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert f"as {dest}" in out.stdout and "pressed by the emulated robot" in out.stdout
    assert "systemctl reload vtzero-edge" in out.stdout
    load_model(dest)
    out = subprocess.run([sys.executable, "-m", "edge", "models", "install",
                          str(tmp_path / "nowhere"), "--to", str(dest)],
                         capture_output=True, text=True)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
