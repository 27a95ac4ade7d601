import errno
import json
import logging
import os
import subprocess
import sys
import tarfile

import pytest

from edge.core.errors import NotFoundError, StoreError
from edge.runtime.domain import Episode, Status
from edge.runtime.store import HELD_MAX, EpisodeStore, new_id, valid_id


def ep(status: str, episode_id: str | None = None, **fields) -> Episode:
    return Episode(episode_id or new_id(), Status(status), **fields)


def test_create_get_update_list(tmp_path):
    store = EpisodeStore(tmp_path)
    a = store.create(ep("pending", candidates=["x", "y"]), {"image.jpg": b"\xff\xd8"})
    b = store.create(ep("done", label="y"), {})
    assert valid_id(a) and valid_id(b)
    assert store.get(a).candidates == ["x", "y"]
    assert store.file(a, "image.jpg").read_bytes() == b"\xff\xd8"
    store.update(a, status="done", label="x")
    assert store.get(a).label == "x"
    assert [e.id for e in store.list()] == sorted([a, b], reverse=True)
    assert store.pending() == []
    assert not list(tmp_path.glob(".tmp-*")) and not list(tmp_path.glob("*/.*.tmp"))


def test_ids_cannot_escape_the_store(tmp_path):
    store = EpisodeStore(tmp_path)
    for bad in ("../etc", "..", "a/b", "", new_id() + "/x"):
        with pytest.raises(NotFoundError):
            store.get(bad)


def test_export_is_a_complete_tarball(tmp_path):
    store = EpisodeStore(tmp_path / "s")
    eid = store.create(ep("done"), {"press.press.npz": b"abc"})
    out = store.export(eid, tmp_path)
    with tarfile.open(out) as tar:
        names = tar.getnames()
    assert f"{eid}/episode.json" in names and f"{eid}/press.press.npz" in names


KILL_WHILE_WRITING = """
import os, sys
from edge.runtime.domain import Episode, Status
from edge.runtime.store import EpisodeStore, new_id
store = EpisodeStore(sys.argv[1])
orig = os.rename
def die(*a, **k):
    os.kill(os.getpid(), 9)  # killed after the files, before the rename
os.rename = die
store.create(Episode(new_id(), Status.PENDING), {"big.bin": b"x" * 1_000_000})
"""


def test_kill_9_mid_write_loses_nothing_committed(tmp_path):
    store = EpisodeStore(tmp_path)
    done = store.create(ep("done", label="a"), {})
    proc = subprocess.run([sys.executable, "-c", KILL_WHILE_WRITING, str(tmp_path)])
    assert proc.returncode == -9
    assert list(tmp_path.glob(".tmp-*")), "the interrupted episode left its temp dir"
    reopened = EpisodeStore(tmp_path)
    assert reopened.recover() == 1
    assert [e.id for e in reopened.list()] == [done]
    assert reopened.get(done).label == "a"


def test_disk_full_is_a_clear_error_and_keeps_older_episodes(tmp_path, monkeypatch):
    store = EpisodeStore(tmp_path)
    old = store.create(ep("done"), {})
    real_open = open

    def full(path, mode="r", *a, **k):
        if "w" in mode and ".tmp-" in str(path):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real_open(path, mode, *a, **k)

    monkeypatch.setattr("builtins.open", full)
    held = store.create(ep("pending"), {"x": b"1"})
    # Not written, held in memory and readable, saying why.
    assert "disk is full" in store.write_error and "disk is full" in store.error()
    assert store.held == 1 and store.get(held).note.startswith("held in memory")
    assert store.update(held, status="done").status == Status.DONE  # (in memory)
    assert [e.id for e in store.list()] == [old]
    assert not list(tmp_path.glob(".tmp-*"))
    assert json.loads((tmp_path / old / "episode.json").read_text())["status"] == "done"
    with pytest.raises(StoreError, match="disk is full"):
        store.flush()
    monkeypatch.undo()
    # Space again: written as it stands now, without the note.
    assert store.flush() == 1 and store.held == 0 and store.write_error is None
    assert [e.id for e in store.list()] == [held, old]
    back = json.loads((tmp_path / held / "episode.json").read_text())
    assert back["status"] == "done" and "note" not in back
    assert (tmp_path / held / "x").read_bytes() == b"1"


def test_memory_holds_a_bounded_number_of_episodes(tmp_path, monkeypatch):
    store = EpisodeStore(tmp_path)

    def erofs(*a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    # (EROFS where the store writes: root ignores file modes, see
    # tests/faults/test_read_only_store.py for a real read-only filesystem)
    monkeypatch.setattr("edge.runtime.store.open", erofs, raising=False)
    monkeypatch.setattr("edge.runtime.store.atomic_write_text", erofs)
    for _ in range(HELD_MAX):
        store.create(ep("done"), {})
    with pytest.raises(StoreError):
        store.create(ep("done"), {})
    with pytest.raises(StoreError, match="read-only"):
        store.accept(new_id(), ["a"], "api")
    with pytest.raises(StoreError, match="read-only"):
        store.check_writable()
    assert store.held == HELD_MAX and store.lost == 1 and store.write_failures >= HELD_MAX
    monkeypatch.undo()
    store.check_writable()
    assert store.write_error is None
    assert store.flush() == HELD_MAX and len(store.ids()) == HELD_MAX


def test_a_press_accepted_but_never_kept_comes_back_interrupted(tmp_path):
    store = EpisodeStore(tmp_path)
    kept, lost, garbled = new_id(), new_id(), new_id()
    for episode_id in (kept, lost, garbled):
        store.accept(episode_id, ["a", "b"], "button")
    store.create(ep("done", kept), {})
    (tmp_path / ".accepted" / f"{garbled}.json").write_bytes(b"\x00{not json")
    (tmp_path / ".accepted" / ".x.json.abc.tmp").write_text("half")  # a note cut off
    assert not (tmp_path / ".accepted" / f"{kept}.json").exists()  # kept: note gone
    assert store.recover() == 0  # (counts discarded half-written episodes only)
    assert store.ids() == sorted([kept, lost, garbled])
    assert store.get(kept).status == Status.DONE
    back = store.get(lost)
    assert back.status == Status.FAILED and back.error.startswith("interrupted")
    assert back.candidates == ["a", "b"] and back.source == "button"
    assert store.get(garbled).status == Status.FAILED and store.get(garbled).candidates is None
    assert list((tmp_path / ".accepted").iterdir()) == []
    store.recover()  # a second start changes nothing
    assert store.ids() == sorted([kept, lost, garbled])


def test_episodes_from_a_newer_version_keep_their_extra_keys(tmp_path):
    store = EpisodeStore(tmp_path)
    eid = store.create(ep("done", label="a", extra={"future_key": [1, 2]}), {})
    store.update(eid, attempts=2)
    raw = json.loads((tmp_path / eid / "episode.json").read_text())
    assert raw["future_key"] == [1, 2] and raw["attempts"] == 2 and raw["status"] == "done"


def test_a_malformed_episode_file_is_refused_by_name(tmp_path):
    store = EpisodeStore(tmp_path)
    eid = store.create(ep("done"), {})
    (tmp_path / eid / "episode.json").write_text(json.dumps({"id": eid, "status": "weird"}))
    with pytest.raises(StoreError, match=f"episode {eid}: unknown status 'weird'"):
        store.get(eid)
    assert store.list() == []  # skipped with a warning, not a crash


def test_retention_removes_the_oldest_finished_episodes_and_segments_first(
        tmp_path, monkeypatch, caplog):
    from types import SimpleNamespace

    caplog.set_level(logging.INFO)
    segments = tmp_path / "mcap"
    segments.mkdir()
    store = EpisodeStore(tmp_path / "episodes", segments=segments)
    t0 = 1_790_000_000.0
    made = []
    for i, status in enumerate(["pending", "done", "done", "failed", "pending", "done"]):
        made.append(store.create(ep(status, new_id(t0 + 100 * i)), {"data": b"x" * 10_000}))
        # A segment completed between each two episodes (and the open one, hidden).
        (segments / f"vtzero-{new_id(t0 + 100 * i + 50)[:15]}Z.mcap").write_bytes(b"m" * 10_000)
    (segments / ".vtzero-open.mcap.tmp").write_bytes(b"m" * 10_000)
    size = store.size()
    # 12 entries of about 10 kB: a bound 35 kB under the size removes the 4 oldest
    # finished ones (the pending first episode stays).
    store.max_bytes = size - 35_000
    store.retain()
    left = store.ids()
    assert left == [made[0], made[3], made[4], made[5]], caplog.text
    assert sorted(p.name for p in segments.iterdir())[0] == ".vtzero-open.mcap.tmp"
    assert store.removed_episodes == 2 and store.removed_segments == 2
    assert store.size() <= store.max_bytes and store.removed_bytes >= 35_000
    assert "retention: removed the 2 oldest finished episode(s) and 2" in caplog.text
    # Too little free space on the filesystem: everything finished goes, pending stays.
    store.max_bytes = 0
    store.keep_free_bytes = 10**15
    monkeypatch.setattr("edge.runtime.store.os.statvfs", lambda path: SimpleNamespace(
        f_bavail=1000, f_frsize=4096, f_files=1000, f_favail=1000))
    store.retain()
    assert store.ids() == [made[0], made[4]]
    assert [p.name for p in segments.iterdir()] == [".vtzero-open.mcap.tmp"]
    assert "still under keep_free_mb" in caplog.text


def test_usage_gives_the_size_the_recent_rate_and_the_days_left(tmp_path, monkeypatch):
    from types import SimpleNamespace

    now = 1_790_000_000.0
    store = EpisodeStore(tmp_path, keep_free_bytes=1_000_000)
    assert store.usage(now).bytes_per_day is None and store.usage(now).days_left is None
    # 10 episodes of about 100 kB over the last 2 days, and one from a month ago.
    store.create(ep("done", new_id(now - 30 * 86400)), {"data": b"x" * 100_000})
    for i in range(10):
        store.create(ep("done", new_id(now - 2 * 86400 + i * 3600)), {"data": b"x" * 100_000})
    monkeypatch.setattr("edge.runtime.store.os.statvfs", lambda path: SimpleNamespace(
        f_bavail=11_000_000 // 4096, f_frsize=4096, f_files=1000, f_favail=1000))
    usage = store.usage(now)
    print(usage)
    assert usage.episodes == 11 and 1_100_000 <= usage.bytes < 1_200_000
    assert 500_000 <= usage.bytes_per_day <= 520_000  # 10 x 100 kB in 2 days
    assert 19 <= usage.days_left <= 20  # (11 MB free - 1 MB kept free) / 0.5 MB a day
    store.max_bytes = usage.bytes + 1_000_000  # the bound comes first
    assert 1.9 <= store.usage(now).days_left <= 2.0
