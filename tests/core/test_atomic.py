"""Atomic writes: a new file's mode follows the umask (a secret's is 0600), a replaced file
keeps its own; ``swap_in``: a staged directory replaces another, the old one kept as
``.previous`` and put back if the swap fails half-way."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from edge.core import atomic
from edge.core.atomic import PREVIOUS_SUFFIX, SECRET_MODE, atomic_write_text, swap_in


@pytest.fixture
def umask():
    """Sets the process's umask for one test (restored after)."""
    old = os.umask(0o022)
    os.umask(old)
    yield os.umask
    os.umask(old)


def _mode(path: Path) -> int:
    return path.stat().st_mode & 0o777


@pytest.mark.parametrize(("mask", "expected"), [(0o022, 0o644), (0o027, 0o640),
                                                 (0o077, 0o600), (0o002, 0o664)])
def test_a_new_file_follows_the_umask(tmp_path, umask, mask, expected):
    umask(mask)
    atomic_write_text(tmp_path / "dataset.json", "{}")
    assert _mode(tmp_path / "dataset.json") == expected
    assert [p.name for p in tmp_path.iterdir()] == ["dataset.json"]  # no temp file left


def test_a_secret_is_0600_whatever_the_umask(tmp_path, umask):
    umask(0o002)
    atomic_write_text(tmp_path / "token", "s3cret", SECRET_MODE)
    assert _mode(tmp_path / "token") == 0o600


def test_a_replaced_file_keeps_its_mode(tmp_path, umask):
    path = tmp_path / "robot.toml"
    path.write_text("a")
    path.chmod(0o640)
    umask(0o022)
    atomic_write_text(path, "b")
    assert _mode(path) == 0o640 and path.read_text() == "b"


def _dir(path: Path, text: str) -> Path:
    path.mkdir()
    (path / "manifest.json").write_text(text)
    return path


def test_swap_in_keeps_one_previous_generation(tmp_path):
    dest = tmp_path / "models"
    assert swap_in(_dir(tmp_path / ".a", "1"), dest) is None
    assert swap_in(_dir(tmp_path / ".b", "2"), dest) == tmp_path / f"models{PREVIOUS_SUFFIX}"
    assert swap_in(_dir(tmp_path / ".c", "3"), dest) == tmp_path / f"models{PREVIOUS_SUFFIX}"
    assert (dest / "manifest.json").read_text() == "3"
    assert (tmp_path / f"models{PREVIOUS_SUFFIX}" / "manifest.json").read_text() == "2"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["models", f"models{PREVIOUS_SUFFIX}"]


def test_a_failed_second_rename_puts_the_old_directory_back(tmp_path, monkeypatch):
    dest = _dir(tmp_path / "models", "old")
    staged = _dir(tmp_path / ".new", "new")
    real = os.rename

    def rename(src, dst):
        if Path(src) == staged:
            raise OSError(28, "No space left on device")
        real(src, dst)

    monkeypatch.setattr(atomic.os, "rename", rename)
    with pytest.raises(OSError, match="No space left"):
        swap_in(staged, dest)
    assert (dest / "manifest.json").read_text() == "old"
    assert not (tmp_path / f"models{PREVIOUS_SUFFIX}").exists()
    assert (staged / "manifest.json").read_text() == "new"  # the caller's to remove or retry
