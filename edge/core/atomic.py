"""Atomic file writes: temp file in the same directory, fsync, rename, fsync the directory.

A reader sees either the old file or the complete new one, never a half-written file, even
if the process is killed or the machine loses power mid-write. A new file gets the mode a
plain ``open`` would (0666 less the umask: datasets, models and reports are for the lab's
people); a secret asks for ``SECRET_MODE``. A replaced file keeps its owner and mode.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

# A directory :func:`swap_in` replaces is kept beside it under this suffix.
PREVIOUS_SUFFIX = ".previous"
# A new file's mode before the umask (what ``open(path, "w")`` asks for), and a secret's.
FILE_MODE = 0o666
SECRET_MODE = 0o600
# Names tried for the temp file before giving up (each is random: a clash is a stale one).
TEMP_NAME_TRIES = 100


def _create_temp(path: Path, mode: int) -> tuple[int, str]:
    """A new temp file beside ``path`` with ``mode`` (the umask applies, as to any new
    file; mkstemp would force 0600)."""
    for _ in range(TEMP_NAME_TRIES):
        tmp = str(path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp"))
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, mode), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{path.parent}: no free temp file name for {path.name}")


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: int = FILE_MODE) -> Iterator[BinaryIO]:
    """Open a binary temp file that replaces ``path`` only if the block completes; a new
    file gets ``mode`` less the umask."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_temp(path, mode)
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        _keep_owner_and_mode(path, tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def atomic_write_bytes(path: str | Path, data: bytes, mode: int = FILE_MODE) -> None:
    with atomic_open(path, mode) as fh:
        fh.write(data)


def atomic_write_text(path: str | Path, text: str, mode: int = FILE_MODE) -> None:
    atomic_write_bytes(path, text.encode("utf-8"), mode)


@contextlib.contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """A directory that replaces ``path`` only if the block completes.

    Yields ``path``'s stand-in, not yet created, inside a hidden staging directory beside
    ``path`` (same name, so writers that name files after their directory name them right).
    A directory already at ``path`` is moved aside, the new one renamed in, the old removed:
    an interrupted or failed write leaves the old one in place.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield stage / path.name
        _fsync_tree(stage / path.name)
        _replace_dir(stage / path.name, path, stage / ".old" if path.exists() else None)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def swap_in(staged: str | Path, dest: str | Path) -> Path | None:
    """Rename the complete directory ``staged`` (beside ``dest``) to ``dest``, keeping a
    directory already there as ``dest.previous`` (one generation: an older one is removed).

    Every file is fsynced first and the parent after. If the second rename fails, the old
    directory is renamed back, so ``dest`` is absent only for the instant between the two
    renames. Returns where the replaced directory went (None: there was none).
    """
    staged, dest = Path(staged), Path(dest)
    _fsync_tree(staged)
    previous = dest.with_name(dest.name + PREVIOUS_SUFFIX) if dest.exists() else None
    if previous is not None and previous.exists():
        shutil.rmtree(previous)
    _replace_dir(staged, dest, previous)
    return previous


def _replace_dir(staged: Path, dest: Path, old: Path | None) -> None:
    """``dest`` (when ``old`` is given) becomes ``old``, then ``staged`` becomes ``dest``; a
    failure of the second rename puts ``old`` back."""
    if old is not None:
        os.rename(dest, old)
    try:
        os.rename(staged, dest)
    except BaseException:
        if old is not None:
            os.rename(old, dest)
        raise
    fsync_dir(dest.parent)


def _fsync_tree(root: Path) -> None:
    for directory, _, files in os.walk(root):
        for name in files:
            fd = os.open(os.path.join(directory, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        fsync_dir(Path(directory))


def _keep_owner_and_mode(path: Path, tmp: str) -> None:
    # A replaced file keeps its owner and permissions: a config the service user reads
    # stays readable to it after `sudo vt-edge pose teach` edits it.
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return
    with contextlib.suppress(PermissionError):
        os.chown(tmp, st.st_uid, st.st_gid)
    os.chmod(tmp, stat.S_IMODE(st.st_mode))


def fsync_dir(directory: Path) -> None:
    """Make a rename into ``directory`` durable; a no-op where the filesystem does not let a
    directory be opened or synced."""
    try:
        dfd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)
