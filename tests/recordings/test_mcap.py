"""MCAP: one episode from a real press exported, and the live stream recorded, both read
back with the mcap library."""

import asyncio
import base64
import contextlib
import json
import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from mcap.reader import make_reader

from edge.core import recording
from edge.recordings.mcaplog import EPISODE_TOPICS, export_episode
from edge.sim.fake_vlm import FakeVLM, Reply
from tests.support.daemon import CUBE, fast_config, sim_daemon
from tests.support.waits import wait_until


def read_mcap(path):
    """{topic: [decoded messages]}, the summary, and the file's metadata records."""
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        messages: dict[str, list] = {}
        for schema, channel, message in reader.iter_messages():
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            json.loads(schema.data)  # every schema is JSON
            body = json.loads(message.data)
            assert message.log_time == body["timestamp"]["sec"] * 10**9 \
                + body["timestamp"]["nsec"]
            messages.setdefault(channel.topic, []).append(body)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = {a.name: a.data for a in reader.iter_attachments()}
    return messages, summary, metadata, attachments


@pytest.mark.asyncio
async def test_episode_export_and_live_recording_read_back(tmp_path):
    live_dir = tmp_path / "live"
    async with FakeVLM(model="fake-vlm") as fake:
        fake.script(Reply(label="melon_pan"))
        cfg = fast_config(fake.base_url)
        cfg = replace(cfg, runtime=replace(cfg.runtime, record_mcap_dir=str(live_dir)))
        async with sim_daemon(tmp_path / "state", cfg=cfg) as (_robot, d):
            status, ep = await d.post("/v1/recognize", {"candidates": [*CUBE, "melon_pan"],
                                                        "wait": True})
            assert status == 200 and ep["status"] == "done", ep
            store = d.store
        # (the daemon has stopped: its live segment is complete)
    states = check_export(tmp_path, store.root / ep["id"], ep)
    check_live(live_dir, store.root / ep["id"], states)


def check_export(tmp_path, episode_dir, ep):
    """The export through the command line, read back."""
    rec = recording.load(episode_dir / "press.press.npz")
    out = tmp_path / "ep.mcap"
    env = {**os.environ, "VTZERO_STATE_DIR": str(tmp_path / "state")}
    run = subprocess.run([sys.executable, "-m", "edge", "episodes", "--config",
                          "configs/sim.toml", "export", ep["id"], "--format", "mcap", "--out",
                          str(out)], capture_output=True, text=True, timeout=60, env=env)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == str(out) and not list(tmp_path.glob(".*.tmp"))
    messages, summary, metadata, attachments = read_mcap(out)
    assert {c.topic for c in summary.channels.values()} == set(EPISODE_TOPICS)
    names = {s.name for s in summary.schemas.values()}
    assert {"foxglove.CompressedImage", "vtzero.TactileFrame", "vtzero.Result"} <= names
    n = len(rec.frames)
    expected = {"/tactile/raw": n, "/tactile/units": n, "/gripper": len(rec.gripper_time),
                "/press/state": len(ep["press"]["states"]), "/camera/image": 1,
                "/result": 1}
    assert {t: len(m) for t, m in messages.items()} == expected
    by_id = summary.statistics.channel_message_counts
    assert {summary.channels[i].topic: c for i, c in by_id.items()} == expected
    print(f"export: {n} frames, {expected['/gripper']} gripper states, "
          f"{os.path.getsize(out)} bytes")

    raw, units = messages["/tactile/raw"], messages["/tactile/units"]
    assert [m["seq"] for m in raw] == rec.seq.tolist()
    assert [m["recv_time"] for m in raw] == rec.recv_time.tolist()
    assert [m["sensor_time"] for m in units] == rec.sensor_time.tolist()
    i = int(np.argmin(np.abs(rec.recv_time - rec.t_stop)))
    assert [p["pad"] for p in raw[i]["pads"]] == [0, 1]
    frame = np.array([[p["x"], p["y"], p["z"]] for p in raw[i]["pads"]])  # (pad, axis, taxel)
    assert frame.shape == (2, 3, 16)
    assert np.array_equal(frame.transpose(0, 2, 1).reshape(-1), rec.frames[i])
    got = np.array([[p["x"], p["y"], p["z"]] for p in units[i]["pads"]])
    want = ((rec.frames[i] - rec.tare) / 65536).reshape(2, 16, 3).transpose(0, 2, 1)
    assert np.allclose(got, want, atol=1e-7)
    states = [m["state"] for m in messages["/press/state"]]
    assert states[0] == "above" and "closing" in states and states[-1] == "idle"
    image = messages["/camera/image"][0]
    assert image["format"] == "jpeg"
    assert base64.b64decode(image["data"]) == (episode_dir / "image.jpg").read_bytes()
    result = messages["/result"][0]
    assert result["label"] == "melon_pan" and result["status"] == "done"
    assert [t["label"] for t in result["topk"]] == [t["label"] for t in ep["topk"]]
    assert result["description"] == ep["description"]
    assert result["timings"]["vlm_s"] > 0 and result["press"]["t_stop"] == rec.t_stop
    assert metadata["vtzero"]["episode"] == ep["id"]
    assert json.loads(attachments["episode.json"])["label"] == "melon_pan"
    return states


def check_live(live_dir, episode_dir, states):
    """The live recording of the same press, read back."""
    rec = recording.load(episode_dir / "press.press.npz")
    segments = sorted(live_dir.iterdir())
    assert len(segments) == 1 and segments[0].suffix == ".mcap", segments
    live, summary, metadata, _ = read_mcap(segments[0])
    assert {c.topic for c in summary.channels.values()} == {"/tactile/raw", "/press/state",
                                                           "/events"}
    times = np.array([m["recv_time"] for m in live["/tactile/raw"]])
    seqs = [m["seq"] for m in live["/tactile/raw"]]
    assert np.all(np.diff(times) >= 0) and len(set(seqs)) == len(seqs)
    assert times[0] <= rec.recv_time[0] and times[-1] >= rec.recv_time[-1]  # covers it
    assert set(rec.seq.tolist()) <= set(seqs)  # every frame of the press is in the stream
    assert int(metadata["vtzero"]["frames"]) == len(times)
    assert int(metadata["vtzero"]["frames_lost"]) == 0
    assert [m["state"] for m in live["/press/state"]] == states
    kinds = [m["type"] for m in live["/events"]]
    assert "result" in kinds and "tactile" in kinds
    print(f"live: {len(times)} frames over {times[-1] - times[0]:.1f} s "
          f"({len(times) / (times[-1] - times[0]):.0f} Hz), {len(kinds)} events")


def test_a_failed_episode_exports_its_result_only(tmp_path):
    from edge.runtime.domain import Episode, PressResult, PressState, PressSummary, Status
    from edge.runtime.store import EpisodeStore, new_id

    store = EpisodeStore(tmp_path / "episodes")
    press = PressSummary(PressResult.NO_CONTACT, "no contact", False, None, None, None, 0.001,
                         0.0, None, ((PressState.ABOVE, 10.0), (PressState.IDLE, 12.5)))
    eid = store.create(Episode(new_id(), Status.FAILED, ["a"], error="no contact",
                               press=press), {})
    path = export_episode(store, eid, tmp_path)
    assert path == tmp_path / f"{eid}.mcap"
    messages, summary, _, _ = read_mcap(path)
    assert {t: len(m) for t, m in messages.items()} == {"/press/state": 2, "/result": 1}
    assert messages["/result"][0]["error"] == "no contact"
    assert summary.statistics.message_end_time == 12_500_000_000


@pytest.mark.asyncio
async def test_live_recording_rotates_segments_without_losing_a_frame(tmp_path):
    live_dir = tmp_path / "live"
    cfg = fast_config()
    cfg = replace(cfg, runtime=replace(cfg.runtime, record_mcap_dir=str(live_dir),
                                       record_mcap_segment_s=1.0))
    async with sim_daemon(tmp_path / "state", cfg=cfg):
        # Three segments rotated (and whatever was open closed at the exit): waited for,
        # not timed, as the writer (niced) can take seconds to start on a loaded host.
        await wait_until(lambda: len(list(live_dir.glob("*.mcap"))) >= 3, 60.0,
                         "three segments rotated")
    check_segments(live_dir)


def check_segments(live_dir):
    segments = sorted(live_dir.iterdir())
    assert all(p.suffix == ".mcap" and not p.name.startswith(".") for p in segments), segments
    assert len(segments) >= 3, segments
    seqs = []
    for path in segments:
        messages, summary, metadata, _ = read_mcap(path)
        assert summary is not None and int(metadata["vtzero"]["frames_lost"]) == 0
        seqs += [m["seq"] for m in messages["/tactile/raw"]]
    # One stream cut into files: every frame once, in order, none missing between files.
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "frames lost or repeated"


class _Runtime:
    """What the live recorder reads of the daemon (its live taps): its ring, its events and
    its settings."""

    def __init__(self):
        from edge.runtime.events import EventBus
        from edge.runtime.ring import FrameRing

        self.cfg = fast_config()
        self.ring = FrameRing(self.cfg.sensor.channels, 2000)
        self.bus = EventBus()
        self.seq = 0

    def subscribe(self):
        from edge.runtime.domain import Hello, PressState

        return self.bus.subscribe(Hello(PressState.IDLE, None))

    @property
    def frame_count(self):
        return self.ring.count

    def rows_since(self, after, limit=None):
        from edge.runtime.taps import rows_since

        return rows_since(self.ring, after, limit)

    def sensor_settings(self):
        return self.cfg.sensor

    def press_settings(self):
        return self.cfg.press

    def push(self, n):
        for _ in range(n):
            self.ring.push(np.full(self.cfg.sensor.channels, 100 + self.seq % 50, np.uint16),
                           self.seq / 125, self.seq / 125, self.seq)
            self.seq += 1


class _Writer:
    """The real writer process with a fault injected at one call: ``hold`` answers the call
    never (done in the writer, its reply held back, as when a cancellation meets it in
    flight); ``fail`` refuses it as a full disk does; ``late`` reaches the writer only
    after a while (queued behind other work)."""

    def __init__(self, worker, hold=None, fail=None, late=None):
        self.worker, self.hold, self.fail, self.late = worker, hold, fail, late
        self.held = asyncio.Event()
        self.queued = asyncio.Event()

    async def run(self, fn, *args):
        from edge.core.errors import EdgeError

        if fn is self.fail:
            self.fail = None
            raise EdgeError("live MCAP recording: cannot write: No space left on device")
        if fn is self.late:
            self.late = None
            self.queued.set()
            await asyncio.sleep(0.3)
        result = await self.worker.run(fn, *args)
        if fn is self.hold:
            self.held.set()
            await asyncio.Event().wait()
        return result


@pytest.mark.asyncio
async def test_live_recording_stopped_while_a_segment_opens_completes_it(tmp_path):
    from edge.recordings import mcap_live
    from edge.runtime.compute import ComputeWorker

    runtime = _Runtime()
    async with ComputeWorker() as worker:
        writer = _Writer(worker, hold=mcap_live.segment_open)
        recorder = mcap_live.McapRecorder(runtime, tmp_path, worker=writer)
        task = asyncio.create_task(recorder.run())
        await asyncio.wait_for(writer.held.wait(), 30)
        runtime.push(40)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    [path] = tmp_path.iterdir()  # whole, renamed: no .tmp left behind
    messages, _, metadata, _ = read_mcap(path)
    assert [m["seq"] for m in messages["/tactile/raw"]] == list(range(40))
    assert int(metadata["vtzero"]["frames_lost"]) == 0


@contextlib.asynccontextmanager
async def _recording(tmp_path):
    """A live recorder on a fake runtime, its writer the real process behind a
    :class:`_Writer`, running until the block ends (then stopped as the daemon stops it),
    once its first segment is open."""
    from edge.recordings import mcap_live
    from edge.runtime.compute import ComputeWorker

    runtime = _Runtime()
    async with ComputeWorker() as worker:
        writer = _Writer(worker)
        recorder = mcap_live.McapRecorder(runtime, tmp_path, worker=writer)
        task = asyncio.create_task(recorder.run())
        await wait_until(lambda: any(tmp_path.iterdir()), 30, "a segment opened")
        yield runtime, writer, recorder
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


@pytest.mark.asyncio
async def test_live_recording_stopped_before_a_write_began_keeps_its_frames(tmp_path):
    # The daemon stopping while a batch waits to reach the writer: it is written, not lost.
    from edge.recordings import mcap_live

    async with _recording(tmp_path) as (runtime, writer, _):
        writer.late = mcap_live.segment_append
        runtime.push(40)
        await asyncio.wait_for(writer.queued.wait(), 30)
        runtime.push(10)
    [path] = tmp_path.iterdir()
    messages, _, metadata, _ = read_mcap(path)
    assert [m["seq"] for m in messages["/tactile/raw"]] == list(range(50))
    assert int(metadata["vtzero"]["frames_lost"]) == 0


@pytest.mark.asyncio
async def test_live_recording_counts_the_frames_a_failed_write_lost(tmp_path, monkeypatch):
    from edge.recordings import mcap_live

    monkeypatch.setattr(mcap_live, "RETRY_S", 0.0)
    monkeypatch.setattr(mcap_live, "FLUSH_PERIOD_S", 0.01)
    async with _recording(tmp_path) as (runtime, writer, recorder):
        runtime.push(30)  # in the open segment, then that segment's next write fails
        await wait_until(lambda: recorder._in_segment >= 30, 30, "30 frames written")
        writer.fail = mcap_live.segment_append
        runtime.push(20)
        await wait_until(lambda: writer.fail is None, 30, "the write refused")
        runtime.push(10)
        await wait_until(lambda: recorder._in_segment >= 10, 30, "10 frames written")
    [path] = tmp_path.iterdir()  # the failed segment was abandoned (its .tmp removed)
    messages, _, metadata, _ = read_mcap(path)
    assert [m["seq"] for m in messages["/tactile/raw"]] == list(range(50, 60))
    assert int(metadata["vtzero"]["frames_lost"]) == 50 == recorder.lost
