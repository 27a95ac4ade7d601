"""rosbag2 and LeRobotDataset v3.0 exports of presses on the emulated robot, read back by the
readers those communities use: rosbags for the bag (with the definitions stored in it), and
lerobot's format definitions for the dataset (lerobot itself does not install beside the
pinned torch on this Python: see the README)."""

import asyncio
import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from ruamel.yaml import YAML

from edge.core import preprocess, recording
from edge.core.config import Config
from edge.core.errors import ConfigError
from edge.recordings import lerobot, rosbag
from edge.runtime.store import EpisodeStore
from edge.sim.fake_vlm import FakeVLM, Reply
from tests.support.daemon import CUBE, fast_config, sim_daemon
from tests.support.presses import recording_of

ROOT = Path(__file__).resolve().parents[2]
LABELS = ("melon_pan", "melon_pan", "sponge_cube")


@pytest.fixture(scope="module")
def pressed(tmp_path_factory):
    """Three presses on the emulated robot through the daemon (one VLM answer each), and a
    live recording in rosbag2 form of the same session."""
    state = tmp_path_factory.mktemp("state")
    live = tmp_path_factory.mktemp("live")

    async def press_three():
        async with FakeVLM(model="fake-vlm") as fake:
            for label in LABELS:
                fake.script(Reply(label=label))
            cfg = fast_config(fake.base_url)
            cfg = replace(cfg, runtime=replace(cfg.runtime, record_mcap_dir=str(live),
                                               record_format="rosbag2"))
            eps = []
            async with sim_daemon(state, cfg=cfg) as (_robot, d):
                for _ in LABELS:
                    status, ep = await d.post("/v1/recognize", {
                        "candidates": sorted({*CUBE, "melon_pan", "sponge_cube"}), "wait": True})
                    assert status == 200 and ep["status"] == "done", ep
                    eps.append(ep)
            return eps

    t0 = time.monotonic()
    eps = asyncio.run(press_three())
    print(f"3 presses in {time.monotonic() - t0:.1f} s")
    return state, EpisodeStore(state / "episodes"), eps, live


def cli(state, *args):
    env = {**os.environ, "VTZERO_STATE_DIR": str(state)}
    return subprocess.run([sys.executable, "-m", "edge", *args], capture_output=True,
                          text=True, timeout=120, env=env, cwd=ROOT)


def read_bag(path):
    """{topic: [(log time ns, message)]}, each deserialised with a typestore built only from
    the definitions stored in the bag; and the bag's metadata."""
    messages: dict[str, list] = {}
    with Reader(path) as reader:
        store = get_typestore(Stores.EMPTY)
        for conn in reader.connections:
            assert conn.ext.serialization_format == "cdr" and conn.msgdef.data
            store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
        for conn, t, raw in reader.messages():
            messages.setdefault(conn.topic, []).append(
                (t, store.deserialize_cdr(raw, conn.msgtype)))
    meta = YAML(typ="safe").load(Path(path) / "metadata.yaml")["rosbag2_bagfile_information"]
    return messages, meta


def stamp_ns(header):
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def test_rosbag2_export_reads_back_in_rosbags(pressed, tmp_path, monkeypatch):
    state, store, eps, _ = pressed
    ep = eps[0]
    rec = recording.load(store.file(ep["id"], "press.press.npz"))
    out = tmp_path / "bag"
    run = cli(state, "episodes", "--config", "configs/sim.toml", "export", ep["id"],
              "--format", "rosbag2", "--out", str(out))
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == str(out)
    assert sorted(p.name for p in out.iterdir()) == ["bag.mcap", "metadata.yaml"]
    assert not list(tmp_path.glob(".*"))  # no staging left
    messages, meta = read_bag(out)
    stored = store.get(ep["id"]).to_json()
    n = len(rec.frames)
    counts = {t: len(m) for t, m in messages.items()}
    assert counts == {"/xServTopic": n, "/tactile/units": n, "/gripper": len(rec.gripper_time),
                      "/press/state": len(ep["press"]["states"]),
                      "/camera/image/compressed": 1, "/result": 1}
    print(f"rosbag2: {n} frames, {sum(counts.values())} messages, "
          f"{(out / 'bag.mcap').stat().st_size} bytes")

    # The clock: monotonic + the offset taken when the episode was stored.
    offset = stored["created"] - stored["created_monotonic"]
    assert float(meta["custom_data"]["vtzero.clock_offset_s"]) == pytest.approx(offset)
    raw = messages["/xServTopic"]
    assert [t for t, _ in raw] == [round((x + offset) * 1e9) for x in rec.recv_time]
    for i in (0, n - 1):
        sensors = raw[i][1].sensors
        assert [s.sensor_pos for s in sensors] == [1, 2]
        assert sensors[0].message == rec.seq[i] and sensors[0].time == rec.sensor_time[i]
        assert sensors[0].model == rec.sensor_model
        got = np.array([[(tx.x, tx.y, tx.z) for tx in s.taxels] for s in sensors])
        assert np.array_equal(got.reshape(-1), rec.frames[i])
        units = messages["/tactile/units"][i][1]
        assert [d.label for d in units.layout.dim] == ["pad", "taxel", "axis"]
        assert np.allclose(units.data, preprocess.recording_units(rec)[i], atol=1e-7)
    joint = messages["/gripper"][-1][1]
    assert joint.name == ["gripper"] and joint.position[0] == rec.gripper_width_m[-1]
    assert joint.effort[0] == rec.gripper_current_ma[-1]
    assert stamp_ns(joint.header) == messages["/gripper"][-1][0]
    states = [m.state for _, m in messages["/press/state"]]
    assert states == [s for s, _ in ep["press"]["states"]]
    image = messages["/camera/image/compressed"][0][1]
    assert image.format == "jpeg"
    assert bytes(image.data) == store.file(ep["id"], "image.jpg").read_bytes()
    result = messages["/result"][0][1]
    assert result.label == "melon_pan" and result.status == "done"
    assert result.episode == ep["id"] and result.press_result == "ok"
    assert list(result.topk_labels) == [t["label"] for t in ep["topk"]]
    assert json.loads(result.json)["description"] == ep["description"]

    # Killed half-way through a new export over it: the good bag stays, no staging left.
    good = {p.name: p.read_bytes() for p in out.iterdir()}

    def killed(*_args):
        raise KeyboardInterrupt

    monkeypatch.setattr(rosbag.RosbagLog, "result", killed)
    with pytest.raises(KeyboardInterrupt):
        rosbag.export_episodes(store, [ep["id"]], out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == good
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]


def test_rosbag2_export_of_several_episodes_is_one_bag(pressed, tmp_path):
    _, store, eps, _ = pressed
    path = rosbag.export_episodes(store, [ep["id"] for ep in eps], tmp_path / "all")
    messages, meta = read_bag(path)
    recs = [recording.load(store.file(ep["id"], "press.press.npz")) for ep in eps]
    assert len(messages["/xServTopic"]) == sum(len(r.frames) for r in recs)
    assert [m.label for _, m in messages["/result"]] == list(LABELS)
    assert meta["custom_data"]["vtzero.episodes"] == ",".join(ep["id"] for ep in eps)


def test_record_format_is_checked():
    with pytest.raises(ConfigError, match="record_format"):
        replace(Config().runtime, record_format="bag").validate("robot.toml")


def test_rosbag2_live_recording(pressed):
    _, store, eps, live = pressed
    bags = sorted(live.iterdir())
    assert len(bags) == 1 and (bags[0] / "metadata.yaml").exists(), bags
    messages, meta = read_bag(bags[0])
    seqs = [m.sensors[0].message for _, m in messages["/xServTopic"]]
    assert len(set(seqs)) == len(seqs)
    for ep in eps:  # every frame of every press is in the stream
        rec = recording.load(store.file(ep["id"], "press.press.npz"))
        assert set(rec.seq.tolist()) <= set(seqs)
    states = [m.state for _, m in messages["/press/state"]]
    assert states == [s for ep in eps for s, _ in ep["press"]["states"]]
    kinds = [json.loads(m.data)["type"] for _, m in messages["/events"]]
    assert "result" in kinds and meta["custom_data"]["vtzero.frames_lost"] == "0"
    print(f"live rosbag2: {len(seqs)} frames, {len(kinds)} events")


def check_lerobot(root: Path, presses: list[tuple[recording.Recording, str]],
                  image: bytes | None):
    """The dataset against lerobot's v3.0 definitions (src/lerobot/datasets/: DatasetInfo,
    DEFAULT_FEATURES, get_hf_features_from_features, the episodes and tasks files), and the
    values against the presses."""
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 125
    assert {"codebase_version", "fps", "features", "total_episodes", "total_frames",
            "total_tasks", "chunks_size", "data_files_size_in_mb", "video_files_size_in_mb",
            "data_path", "video_path", "robot_type", "splits"} <= set(info)
    feats = info["features"]
    for key, dtype in (("timestamp", "float32"), ("frame_index", "int64"),
                       ("episode_index", "int64"), ("index", "int64"), ("task_index", "int64")):
        assert feats[key] == {"dtype": dtype, "shape": [1], "names": None}
    assert feats["observation.tactile"]["shape"] == [96]
    assert feats["observation.tactile"]["names"][:4] == [
        "pad0_taxel00_x", "pad0_taxel00_y", "pad0_taxel00_z", "pad0_taxel01_x"]
    assert feats["observation.tactile"]["names"][-1] == "pad1_taxel15_z"
    assert info["total_episodes"] == len(presses)
    assert info["total_frames"] == sum(len(r.frames) for r, _ in presses)
    assert info["splits"] == {"train": f"0:{len(presses)}"}

    # Data files: the parquet type of every feature as lerobot's reader casts it.
    paths = sorted(root.glob("data/*/*.parquet"))
    assert paths and all(p.relative_to(root).as_posix() == info["data_path"].format(
        chunk_index=0, file_index=i) for i, p in enumerate(paths))
    tables = [pq.read_table(p) for p in paths]
    for table in tables:
        assert table.schema.names == list(feats)
        for name, ft in feats.items():
            typ = table.schema.field(name).type
            if ft["dtype"] == "image":
                assert str(typ) == "struct<bytes: binary, path: string>"
            elif ft["shape"] == [1]:
                assert str(typ) == ft["dtype"].replace("float32", "float")
            else:
                assert typ.list_size == ft["shape"][0]
    rows = {k: np.concatenate([t.column(k).to_numpy() for t in tables])
            for k in ("index", "episode_index", "frame_index", "timestamp", "task_index")}
    assert np.array_equal(rows["index"], np.arange(info["total_frames"]))

    # Episodes, tasks, stats.
    episodes = pq.read_table(next(root.glob("meta/episodes/*/*.parquet"))).to_pylist()
    tasks = pq.read_table(root / "meta/tasks.parquet")
    pandas_meta = json.loads(tasks.schema.metadata[b"pandas"])
    assert pandas_meta["index_columns"] == ["task"]
    task_of = dict(zip(tasks.column("task_index").to_pylist(), tasks.column("task").to_pylist(),
                       strict=True))
    assert info["total_tasks"] == len(task_of)
    stats = json.loads((root / "meta/stats.json").read_text())
    assert set(stats) == set(feats)
    assert stats["observation.tactile"]["count"] == [info["total_frames"]]
    tactile = np.concatenate([np.stack(t.column("observation.tactile").to_numpy(
        zero_copy_only=False)) for t in tables])
    assert np.allclose(stats["observation.tactile"]["max"], tactile.max(0))
    for ep, ((rec, task), row) in enumerate(zip(presses, episodes, strict=True)):
        n = len(rec.frames)
        lo, hi = row["dataset_from_index"], row["dataset_to_index"]
        assert row["episode_index"] == ep and row["length"] == n == hi - lo
        assert row["tasks"] == [task]
        assert np.all(rows["episode_index"][lo:hi] == ep)
        assert np.array_equal(rows["frame_index"][lo:hi], np.arange(n))
        assert np.allclose(rows["timestamp"][lo:hi], np.arange(n) / 125)
        assert {task_of[i] for i in rows["task_index"][lo:hi]} == {task}
        units = preprocess.recording_units(rec)
        assert np.array_equal(tactile[lo], units[0]) and np.array_equal(tactile[hi - 1], units[-1])
        table = tables[row["data/file_index"]]
        first = lo - int(table.column("index")[0].as_py())
        raw = table.column("observation.tactile_raw")[first].as_py()
        assert raw == rec.frames[0].astype(float).tolist()
        state = table.column("observation.state")[first + n - 1].as_py()
        assert state[0] == pytest.approx(rec.gripper_width_m[-1], abs=1e-6)
        if image is not None:
            assert table.column("observation.image")[first].as_py()["bytes"] == image
    return episodes


def test_lerobot_export_of_three_episodes(pressed, tmp_path):
    state, store, eps, _ = pressed
    out = tmp_path / "ds"
    ids = [ep["id"] for ep in eps]
    run = cli(state, "episodes", "--config", "configs/sim.toml", "export", *ids,
              "--format", "lerobot", "--out", str(out))
    assert run.returncode == 0, run.stderr
    recs = [recording.load(store.file(i, "press.press.npz")) for i in ids]
    episodes = check_lerobot(out, list(zip(recs, LABELS, strict=True)),
                             store.file(ids[0], "image.jpg").read_bytes())
    assert [e["vtzero/label"] for e in episodes] == list(LABELS)
    assert json.loads(episodes[2]["vtzero/result"])["label"] == "sponge_cube"
    action = pq.read_table(next(out.glob("data/*/*.parquet"))).column("action").to_numpy()
    # The goal: the closed limit while closing, held at the stop, open from the opening.
    lo = episodes[0]["dataset_from_index"]
    t = recs[0].recv_time
    closing = action[lo:lo + len(t)][t < recs[0].t_stop]
    assert len(closing) and np.all(closing == np.float32(-0.010))
    print(f"lerobot: {len(ids)} episodes, {sum(len(r.frames) for r in recs)} frames, "
          f"{sum(p.stat().st_size for p in out.rglob('*') if p.is_file())} bytes")


def make_collection(directory: Path) -> list[tuple[recording.Recording, str]]:
    presses = [(recording_of(label, 0), label) for label in ("melon_pan", "sponge_cube")]
    classes = []
    for rec, label in presses:
        recording.save(rec, directory / label / f"{label}_000{recording.SUFFIX}")
        (directory / label / f"{label}_000.jpg").write_bytes(_jpeg())
        classes.append({"label": label, "split": "train", "description": label, "x_th": 0.01})
    (directory / "dataset.json").write_text(json.dumps({"dataset": "lab", "classes": classes}))
    return presses


def _jpeg() -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (64, 48), (200, 120, 40)).save(buf, "JPEG")
    return buf.getvalue()


def test_collection_export_and_atomic_replacement(tmp_path, monkeypatch):
    col = tmp_path / "lab"
    presses = make_collection(col)
    run = cli(tmp_path, "dataset", "export", str(col), "--format", "lerobot")
    assert run.returncode == 0, run.stderr
    out = tmp_path / "lab.lerobot"
    assert run.stdout.strip() == str(out)
    photo = (col / "melon_pan" / "melon_pan_000.jpg").read_bytes()
    episodes = check_lerobot(out, presses, photo)
    assert json.loads(episodes[1]["vtzero/result"])["split"] == "train"
    # Only an earlier export is replaced: a file (or any other directory) is refused.
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    run = cli(tmp_path, "dataset", "export", str(col), "--out", str(notes))
    assert run.returncode == 2 and "is not a lerobot export" in run.stderr, run.stderr
    assert notes.read_text() == "mine"
    notes.unlink()
    good = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}

    # A corrupt press file: one line naming it, the good dataset as it was.
    bad = col / "sponge_cube" / f"sponge_cube_001{recording.SUFFIX}"
    bad.write_bytes(b"PK\x03\x04 truncated")
    run = cli(tmp_path, "dataset", "export", str(col), "--out", str(out))
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "sponge_cube_001" in run.stderr
    bad.unlink()
    # Killed half-way (every file written, not yet renamed): the good dataset as it was,
    # and no staging left behind.
    real = lerobot._write

    def interrupted(root, *args):
        real(root, *args)
        raise KeyboardInterrupt  # killed after the files, before the rename

    monkeypatch.setattr(lerobot, "_write", interrupted)
    with pytest.raises(KeyboardInterrupt):
        lerobot.export_dataset(lerobot.from_collection(col), out)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lab", "lab.lerobot"]


def test_missing_extra_is_one_line(tmp_path):
    """Without the export extra, one line names what to install (exit 2)."""
    code = ("import sys; sys.modules['pyarrow'] = None; sys.modules['rosbags'] = None; "
            "from edge.cli import main; sys.exit(main(sys.argv[1:]))")
    (tmp_path / "lab").mkdir()
    run = subprocess.run([sys.executable, "-c", code, "dataset", "export", str(tmp_path / "lab")],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert run.returncode == 2
    assert run.stderr.strip().splitlines()[-1].endswith("pip install 'vtzero[export]'")
