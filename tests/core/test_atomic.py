"""``swap_in``: a staged directory replaces another, the old one kept as ``.previous`` and put
back if the swap fails half-way."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from edge.core import atomic
from edge.core.atomic import PREVIOUS_SUFFIX, swap_in


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
