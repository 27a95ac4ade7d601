"""``vt-edge episodes export --format rosbag2|lerobot`` and ``vt-edge dataset export``: where
the bag or dataset goes, and which writer makes it (:mod:`edge.recordings.rosbag`,
:mod:`edge.recordings.lerobot`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from edge.core.errors import StoreError

# What marks a directory as an earlier export of the same kind (replaced, not nested into).
MARKERS = {"rosbag2": "metadata.yaml", "lerobot": "meta/info.json"}


def output_dir(out: str | Path, name: str, fmt: str) -> Path:
    """``out`` itself unless it is an existing directory other than an earlier export of
    ``fmt``: then ``out/name``. Only an earlier export is ever replaced."""
    out = Path(out)
    if out.is_dir() and not (out / MARKERS[fmt]).exists():
        out = out / name
    if out.exists() and not (out / MARKERS[fmt]).exists():
        raise StoreError(f"{out} exists and is not a {fmt} export (no {MARKERS[fmt]}): "
                         "choose another --out")
    return out


def export_episodes(store: Any, episode_ids: list[str], fmt: str, out: str | Path) -> Path:
    ids = list(dict.fromkeys(episode_ids))
    name = ids[0] if len(ids) == 1 else f"{ids[0]}+{len(ids) - 1}"
    dest = output_dir(out, name, fmt)
    if fmt == "rosbag2":
        from edge.recordings.rosbag import export_episodes as write_bag

        return write_bag(store, ids, dest)
    from edge.recordings import lerobot

    lerobot.require_pyarrow()
    return lerobot.export_dataset(lerobot.from_episodes(store, ids), dest)


def export_collection(directory: str | Path, out: str | Path | None) -> Path:
    from edge.recordings import lerobot

    lerobot.require_pyarrow()
    directory = Path(directory)
    dest = Path(out) if out is not None else directory.with_name(f"{directory.name}.lerobot")
    return lerobot.export_dataset(lerobot.from_collection(directory),
                                  output_dir(dest, directory.name, "lerobot"))
