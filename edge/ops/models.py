"""``vt-edge models install SRC --to DIR``: put a model directory where the daemon reads it.

The source is verified the way the daemon verifies it at start (every file the manifest
lists against its sha256, the encoder loaded, the database read) before anything is copied,
and the copy is verified again. The copy goes into a temporary directory beside ``DIR``,
every file and directory fsynced, then renamed into place; the directory it replaces is
kept as ``DIR.previous`` (one generation) so a bad model is one rename away from undone.
The daemon reads the directory only at start and on SIGHUP, so the instant between the two
renames, when ``DIR`` does not exist, is never seen by it; a crash there leaves both
complete directories, the old one as ``DIR.previous``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
from pathlib import Path

from edge.core.atomic import swap_in
from edge.core.errors import ModelError
from edge.core.model import MANIFEST, load_model, manifest_origin, read_manifest, verified_files

log = logging.getLogger(__name__)
# Not secrets, and read by the service user: world-readable whatever the source's modes.
FILE_MODE = 0o644
DIR_MODE = 0o755


def _copy_tree(src: Path, dst: Path) -> None:
    """Copy ``src`` into the existing empty ``dst``, modes normalised."""
    for root, dirs, files in os.walk(src):
        rel = Path(root).relative_to(src)
        target = dst / rel
        target.mkdir(exist_ok=True)
        os.chmod(target, DIR_MODE)
        dirs.sort()
        for name in sorted(files):
            out = target / name
            shutil.copyfile(Path(root) / name, out, follow_symlinks=True)
            os.chmod(out, FILE_MODE)


def install_models(src: str | Path, dest: str | Path) -> tuple[dict, Path | None]:
    """Verify ``src``, install it as ``dest`` (the old ``dest`` kept as ``dest.previous``);
    returns the installed manifest and where the replaced directory went (None: none)."""
    src, dest = Path(src).resolve(), Path(dest).absolute()
    if not src.is_dir():
        raise ModelError(f"{src}: not a directory (give a model directory with a "
                         f"{MANIFEST})")
    if src == dest.resolve() or src in dest.resolve().parents:
        raise ModelError(f"{src}: is the destination {dest} (or holds it); nothing to install")
    load_model(src)  # hashes, encoder and database, as the daemon checks them at start
    manifest = read_manifest(src)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent))
    try:
        _copy_tree(src, tmp)
        verified_files(tmp, read_manifest(tmp))  # what landed on disk, read back
        previous = swap_in(tmp, dest)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            shutil.rmtree(tmp)
        raise
    log.info("installed %s from %s", dest, src)
    return manifest, previous


def describe(manifest: dict) -> str:
    """One line on the installed database: its classes and who pressed them."""
    db = manifest.get("database", {})
    emulated = manifest_origin(manifest).emulated
    line = (f"{db.get('classes', '?')} classes, {db.get('references', '?')} references, "
            f"pressed by the {'emulated robot' if emulated else 'robot'}")
    if emulated:
        line += ("; on a real robot replace it with the lab's own references "
                 "(vt-edge collect --plan, then vt-train build)")
    return line

