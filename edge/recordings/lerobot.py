"""LeRobotDataset v3.0 of presses: stored episodes, or a collection directory, as one dataset.

The layout follows lerobot's own definitions (``src/lerobot/datasets/``: ``utils.py``
``DatasetInfo`` and paths, ``dataset_metadata.py`` episodes and tasks, ``feature_utils.py``
the parquet types of each feature, ``compute_stats.py`` the statistics)::

    DIR/meta/info.json                          codebase_version "v3.0", fps, features, totals
    DIR/meta/stats.json                         min, max, mean, std, count, q01..q99 per feature
    DIR/meta/tasks.parquet                      task (the index) -> task_index
    DIR/meta/episodes/chunk-000/file-000.parquet  one row per episode: length, tasks, ranges
    DIR/data/chunk-000/file-NNN.parquet         one row per tactile frame

One episode per press, one frame per tactile frame at the sensor's 125 Hz (``timestamp`` =
``frame_index`` / 125, as lerobot's readers index frames by it). Features::

    observation.tactile      float32 (C,)   (raw - tare) / 65536, both pads, taxel x axis
    observation.tactile_raw  float32 (C,)   raw counts (exact in float32)
    observation.state        float32 (2,)   gripper width (m), squeeze current (mA)
    action                   float32 (1,)   the gripper's goal width (m)
    observation.image        image          the photo (every frame of a press: one photo)

``C`` = pads x taxels x 3 (96 on two XR1944 pads; a recording of other pads names its layout).
``names`` of the tactile features are ``pad{p}_taxel{tt}_{axis}``. The gripper is read every
20 ms: each frame carries the last reading at or before it (the first before that). The
action is the goal the press wrote: the closed limit while closing (before ``t_stop``), the
width at the stop while holding, the open width from the opening on (``t_open``; a
recording made before these were kept holds to its end). The task is the press's label
("press" when it has none); the recognition's result goes into the episode's row
(``vtzero/...`` columns). The photo is a feature only when every press has one, all the
same size.

Needs only pyarrow (the ``export`` extra), not lerobot. The dataset is written to a staging
directory beside ``DIR`` and renamed into place complete.
"""

from __future__ import annotations

import io
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from edge import __version__
from edge.core import preprocess, recording
from edge.core.atomic import atomic_dir
from edge.core.errors import EdgeError, StoreError
from edge.core.layout import PadLayout
from edge.hw.arm import GRIPPER_CLOSED_WIDTH_M, GRIPPER_OPEN_WIDTH_M

log = logging.getLogger(__name__)

EXTRA_HINT = "pip install 'vtzero[export]'"
CODEBASE_VERSION = "v3.0"
FPS = int(preprocess.DEFAULT_WINDOW.rate_hz)
ROBOT_TYPE = "openmanipulator_x"
UNLABELLED_TASK = "press"
CHUNKS_SIZE = 1000  # files per chunk directory (lerobot's DEFAULT_CHUNK_SIZE)
DATA_FILE_MB = 100  # lerobot's DEFAULT_DATA_FILE_SIZE_IN_MB
VIDEO_FILE_MB = 200
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}"
DATA_PATH = "data/" + CHUNK_FILE + ".parquet"
EPISODES_PATH = "meta/episodes/" + CHUNK_FILE + ".parquet"
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)  # lerobot's DEFAULT_QUANTILES


def require_pyarrow() -> None:
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        raise EdgeError(f"LeRobot export needs the pyarrow package: {EXTRA_HINT}") from None


@dataclass(frozen=True)
class Press:
    """One press to export: its recording, photo, task and what else is known of it."""

    rec: recording.Recording
    task: str
    image: bytes | None = None
    meta: dict[str, Any] = field(default_factory=dict)  # vtzero/* columns (strings)


# --------------------------------------------------------------------------------------
# Sources


def from_episodes(store: Any, episode_ids: list[str]) -> list[Press]:
    """Stored episodes with a press recording (one without, a failed press, is refused)."""
    from edge.recordings.mcaplog import episode_files, result_message

    presses = []
    for eid in episode_ids:
        item = episode_files(store, eid)
        episode = item.episode
        if item.rec is None:
            raise StoreError(f"episode {eid} has no press recording ({episode.status}"
                             f": {episode.error or 'no press'}): leave it out")
        label = episode.label
        presses.append(Press(item.rec, label or UNLABELLED_TASK, item.image, {
            "vtzero/source": f"episode {eid}", "vtzero/label": label or "",
            "vtzero/status": episode.status.value,
            "vtzero/result": json.dumps(result_message(item.episode), sort_keys=True,
                                        default=str)}))
    return presses


def from_collection(directory: str | Path) -> list[Press]:
    """The presses of a collection directory (``vt-edge collect``): DIR/dataset.json, and
    DIR/<label>/<label>_NNN.press.npz each with its photo DIR/<label>/<label>_NNN.jpg."""
    directory = Path(directory)
    index_path = directory / "dataset.json"
    try:
        index = json.loads(index_path.read_text())
        classes = index["classes"]
    except OSError as exc:
        raise StoreError(f"{index_path}: cannot read the collection's index: "
                         f"{exc.strerror or exc}") from None
    except (ValueError, KeyError, TypeError):
        raise StoreError(f"{index_path}: not a collection index (JSON with 'classes')") from None
    presses = []
    for cls in classes:
        label = str(cls["label"])
        for npz in sorted((directory / label).glob(f"{label}_*{recording.SUFFIX}")):
            photo = npz.with_name(npz.name.removesuffix(recording.SUFFIX) + ".jpg")
            presses.append(Press(recording.load(npz), label,
                                 photo.read_bytes() if photo.exists() else None, {
                "vtzero/source": str(npz.relative_to(directory)), "vtzero/label": label,
                "vtzero/status": "reference", "vtzero/result": json.dumps(
                    {"split": cls.get("split"), "description": cls.get("description"),
                     "x_th": cls.get("x_th")}, sort_keys=True)}))
    if not presses:
        raise StoreError(f"{directory}: no presses (<label>/<label>_NNN{recording.SUFFIX}) "
                         "of the classes in dataset.json")
    return presses


# --------------------------------------------------------------------------------------
# Frames


def _hold(t_src: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``values`` (sampled at ``t_src``) as last known at each of ``t``; the first before."""
    if len(t_src) == 0:
        return np.full(len(t), np.nan)
    i = np.searchsorted(t_src, t, side="right") - 1
    return values[np.clip(i, 0, len(t_src) - 1)]


def gripper_goal(rec: recording.Recording) -> np.ndarray:
    """The goal width the press had written at each frame (see the module's doc)."""
    goals = rec.extra.get("gripper_goal_m") or {}
    closed = float(goals.get("closed", GRIPPER_CLOSED_WIDTH_M))
    opened = float(goals.get("open", GRIPPER_OPEN_WIDTH_M))
    held = float(np.interp(rec.t_stop, rec.gripper_time, rec.gripper_width_m)) \
        if len(rec.gripper_time) else closed
    t = rec.recv_time
    goal = np.where(t < rec.t_stop, closed, held)
    t_open = rec.extra.get("t_open")
    if t_open is not None:
        goal = np.where(t >= float(t_open), opened, goal)
    return goal.astype(np.float32)


def frames(press: Press) -> dict[str, np.ndarray]:
    """The per-frame features of one press, (N, ...) float32."""
    rec = press.rec
    t = rec.recv_time
    return {
        "observation.tactile": preprocess.recording_units(rec).astype(np.float32),
        "observation.tactile_raw": rec.frames.astype(np.float32),
        "observation.state": np.stack([
            _hold(rec.gripper_time, rec.gripper_width_m, t),
            _hold(rec.gripper_time, rec.gripper_current_ma, t)], axis=1).astype(np.float32),
        "action": gripper_goal(rec),
    }


def _image_shape(data: bytes) -> tuple[int, int, int]:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        return im.height, im.width, 3


def _image_pixels(data: bytes) -> np.ndarray:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im.convert("RGB"), dtype=np.float32).reshape(-1, 3) / 255.0


def features(layout: PadLayout, image_shape: tuple[int, int, int] | None) -> dict[str, Any]:
    names, channels = layout.names(), layout.channels
    out: dict[str, Any] = {
        "observation.tactile": {"dtype": "float32", "shape": [channels], "names": names},
        "observation.tactile_raw": {"dtype": "float32", "shape": [channels], "names": names},
        "observation.state": {"dtype": "float32", "shape": [2],
                              "names": ["gripper_width_m", "gripper_current_ma"]},
        "action": {"dtype": "float32", "shape": [1], "names": ["gripper_goal_width_m"]},
    }
    if image_shape is not None:
        out["observation.image"] = {"dtype": "image", "shape": list(image_shape),
                                    "names": ["height", "width", "channels"]}
    return {**out,
            "timestamp": {"dtype": "float32", "shape": [1], "names": None},
            "frame_index": {"dtype": "int64", "shape": [1], "names": None},
            "episode_index": {"dtype": "int64", "shape": [1], "names": None},
            "index": {"dtype": "int64", "shape": [1], "names": None},
            "task_index": {"dtype": "int64", "shape": [1], "names": None}}


def arrow_type(feature: dict[str, Any]) -> Any:
    """The parquet column type lerobot's readers expect (feature_utils.py: a (1,) shape is a
    scalar, a 1-D shape a fixed-length list, an image a {bytes, path} struct)."""
    import pyarrow as pa

    if feature["dtype"] == "image":
        return pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    scalar = pa.from_numpy_dtype(np.dtype(feature["dtype"]))
    return scalar if feature["shape"] == [1] else pa.list_(scalar, feature["shape"][0])


def _stats(values: np.ndarray) -> dict[str, list]:
    """lerobot's statistics of (N, D) values: per dimension, over frames."""
    v = values.astype(np.float64).reshape(len(values), -1)
    out = {"min": v.min(0), "max": v.max(0), "mean": v.mean(0), "std": v.std(0),
           "count": np.array([len(v)])}
    for q in QUANTILES:
        out[f"q{round(q * 100):02d}"] = np.quantile(v, q, axis=0)
    return {k: a.tolist() for k, a in out.items()}


def _image_stats(pixels: list[tuple[np.ndarray, int]]) -> dict[str, list]:
    """Per channel over the frames (each photo counted once per frame it is in), (3, 1, 1)
    in [0, 1] as lerobot keeps image statistics."""
    stacked = np.concatenate([p for p, _ in pixels])
    weights = np.concatenate([np.full(len(p), n, dtype=np.float64) for p, n in pixels])
    mean = np.average(stacked, axis=0, weights=weights)
    std = np.sqrt(np.average((stacked - mean) ** 2, axis=0, weights=weights))
    out = {"min": stacked.min(0), "max": stacked.max(0), "mean": mean, "std": std}
    for q in QUANTILES:
        out[f"q{round(q * 100):02d}"] = np.quantile(stacked, q, axis=0)
    stats = {k: a.reshape(3, 1, 1).tolist() for k, a in out.items()}
    stats["count"] = [int(sum(n for _, n in pixels))]
    return stats


# --------------------------------------------------------------------------------------
# The dataset


def export_dataset(presses: list[Press], dest: str | Path) -> Path:
    """Write ``presses`` as one LeRobotDataset v3.0 in directory ``dest``; returns it."""
    require_pyarrow()
    if not presses:
        raise StoreError("nothing to export: no presses")
    layouts = {PadLayout.of_recording(p.rec.extra, p.rec.channels) for p in presses}
    if len(layouts) != 1:
        which = "; ".join(sorted(f"{lay.channels} channels, {lay.text()}" for lay in layouts))
        raise StoreError(f"presses of different sensors ({which}) cannot share a dataset")
    layout = layouts.pop()
    shapes = {_image_shape(p.image) if p.image is not None else None for p in presses}
    image_shape = shapes.pop() if len(shapes) == 1 else None
    if image_shape is None and any(p.image is not None for p in presses):
        log.warning("the photo is left out: not every press has one of the same size")
    feats = features(layout, image_shape)
    tasks = list(dict.fromkeys(p.task for p in presses))
    dest = Path(dest)
    try:
        with atomic_dir(dest) as root:
            total = _write(root, presses, feats, tasks, image_shape is not None)
    except OSError as exc:
        raise StoreError(f"cannot write the dataset {dest}: {exc}") from None
    log.info("LeRobot dataset %s: %d episodes, %d frames", dest, len(presses), total)
    return dest


def _write(root: Path, presses: list[Press], feats: dict[str, Any], tasks: list[str],
           with_image: bool) -> int:
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = pa.schema([(k, arrow_type(f)) for k, f in feats.items()])
    task_index = {t: i for i, t in enumerate(tasks)}
    episodes: list[dict[str, Any]] = []
    columns: dict[str, list[np.ndarray]] = {k: [] for k in feats if k != "observation.image"}
    pixels: list[tuple[np.ndarray, int]] = []
    writer, file_index, file_bytes, start = None, -1, DATA_FILE_MB * 2**20, 0
    try:
        for ep, press in enumerate(presses):
            values = frames(press)
            n = len(press.rec.frames)
            est = sum(a.nbytes for a in values.values()) + len(press.image or b"")
            if writer is None or file_bytes + est > DATA_FILE_MB * 2**20:
                if writer is not None:
                    writer.close()
                file_index, file_bytes = file_index + 1, 0
                path = root / DATA_PATH.format(chunk_index=file_index // CHUNKS_SIZE,
                                               file_index=file_index % CHUNKS_SIZE)
                path.parent.mkdir(parents=True, exist_ok=True)
                writer = pq.ParquetWriter(path, schema, compression="snappy")
            file_bytes += est
            per_frame = {
                **values,
                "timestamp": (np.arange(n) / FPS).astype(np.float32),
                "frame_index": np.arange(n, dtype=np.int64),
                "episode_index": np.full(n, ep, dtype=np.int64),
                "index": np.arange(start, start + n, dtype=np.int64),
                "task_index": np.full(n, task_index[press.task], dtype=np.int64),
            }
            arrays = {k: _column(v, schema.field(k).type) for k, v in per_frame.items()}
            if with_image:
                arrays["observation.image"] = pa.array(
                    [{"bytes": press.image, "path": None}] * n, schema.field(
                        "observation.image").type)
                pixels.append((_image_pixels(press.image), n))
            writer.write_table(pa.table([arrays[k] for k in schema.names], schema=schema))
            ep_stats = {k: _stats(v.reshape(n, -1)) for k, v in per_frame.items()}
            if with_image:
                ep_stats["observation.image"] = _image_stats(pixels[-1:])
            for k, v in per_frame.items():
                columns[k].append(v)
            episodes.append({
                "episode_index": ep, "tasks": [press.task], "length": n,
                "data/chunk_index": file_index // CHUNKS_SIZE,
                "data/file_index": file_index % CHUNKS_SIZE,
                "dataset_from_index": start, "dataset_to_index": start + n,
                "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
                **{f"stats/{k}/{s}": v for k, st in ep_stats.items() for s, v in st.items()},
                **press.meta})
            start += n
    finally:
        if writer is not None:
            writer.close()
    _write_episodes(root, episodes)
    _write_tasks(root, tasks)
    stats = {k: _stats(np.concatenate(v).reshape(start, -1)) for k, v in columns.items()}
    if with_image:
        stats["observation.image"] = _image_stats(pixels)
    (root / "meta").mkdir(parents=True, exist_ok=True)
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=2))
    info = {
        "codebase_version": CODEBASE_VERSION, "robot_type": ROBOT_TYPE, "fps": FPS,
        "total_episodes": len(presses), "total_frames": start, "total_tasks": len(tasks),
        "chunks_size": CHUNKS_SIZE, "data_files_size_in_mb": DATA_FILE_MB,
        "video_files_size_in_mb": VIDEO_FILE_MB, "data_path": DATA_PATH, "video_path": None,
        "splits": {"train": f"0:{len(presses)}"}, "features": feats,
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    return start


def _column(values: np.ndarray, typ: Any) -> Any:
    import pyarrow as pa

    if pa.types.is_fixed_size_list(typ):
        flat = pa.array(values.reshape(-1), typ.value_type)
        return pa.FixedSizeListArray.from_arrays(flat, typ.list_size)
    return pa.array(values.reshape(-1), typ)


def _write_episodes(root: Path, episodes: list[dict[str, Any]]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = list(dict.fromkeys(k for e in episodes for k in e))
    pq.write_table(pa.Table.from_pydict({k: [e.get(k) for e in episodes] for k in keys}), path)


def _write_tasks(root: Path, tasks: list[str]) -> None:
    """meta/tasks.parquet as pandas writes a frame indexed by ``task`` (lerobot reads it
    with ``pd.read_parquet`` and looks tasks up in the index)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode",
                            "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
             "numpy_type": "int64", "metadata": None},
            {"name": "task", "field_name": "task", "pandas_type": "unicode",
             "numpy_type": "object", "metadata": None}],
        "creator": {"library": "vtzero", "version": __version__},
        "pandas_version": "2.2.0",
    }
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()),
                      "task": pa.array(tasks, pa.string())})
    table = table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})
    pq.write_table(table, root / "meta" / "tasks.parquet")

