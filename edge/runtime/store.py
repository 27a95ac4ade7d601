"""The episode store: every recognition kept, written atomically.

One directory per episode under ``root``: ``episode.json`` (status, candidates, press
summary, top-k, description, prompt, VLM request/response, label, timings) plus data files
(the raw press window as a recording, the model input and embedding, the image). A new
episode is assembled in a hidden temp directory, every file fsynced, then renamed into place:
a reader, or a daemon restarted after ``kill -9``, sees the whole episode or none of it.
Updates of ``episode.json`` are atomic file replacements. Episodes whose VLM call could not
complete stay ``pending`` and are retried, also after a restart.

A store that cannot write (its filesystem went read-only, as an SD card does after an
error; or full) says so in :attr:`EpisodeStore.write_error` until a write works again. The
daemon presses only once the press's acceptance note is written (:meth:`accept`), so no
press starts without a place to keep it; an episode whose press ended meanwhile is held in
memory (up to ``HELD_MAX``), readable, and written by :meth:`flush` once the store can.

Retention (:meth:`retain`, after every new episode and now and then): past ``max_bytes``
(the episodes and the live recording's segments together) or under ``keep_free_bytes`` free
on the filesystem, the oldest finished episodes and segments go first; a pending episode
(its VLM question still due) is never removed.

All methods block (file I/O): the daemon calls them through ``asyncio.to_thread``.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import secrets
import shutil
import tarfile
import threading
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from edge.core.atomic import atomic_write_text, fsync_dir
from edge.core.errors import NotFoundError, StoreError
from edge.runtime.domain import Episode, Status

log = logging.getLogger(__name__)

EPISODE_FILE = "episode.json"
_ID_RE = re.compile(r"^\d{8}T\d{6}\d{3}Z-[0-9a-f]{6}$")
_TMP_PREFIX = ".tmp-"
# One small file per accepted press until its episode is kept: what a restart finds here
# was cut off by a crash, and is kept as an interrupted episode instead of forgotten.
_ACCEPTED = ".accepted"
INTERRUPTED = ("interrupted: the daemon stopped (a crash, kill or power loss) before this "
               "press was kept; its data is lost. Press again")
# Below this much free space (or 100 free inodes) the store counts as full: an episode
# takes a few hundred kB; keep room for the rest of the system too.
MIN_FREE_BYTES = 20 * 1024 * 1024
# Episodes held in memory while the store cannot write (each a few hundred kB with its
# photo). Presses are refused once a write fails, so only those under way then get here.
HELD_MAX = 20
# Written and fsynced (among the acceptance notes) to tell whether the store can write.
_PROBE = "probe"
# The live recording's completed segments (edge/recordings/mcap_live.py; an open one is hidden).
_SEGMENT_PREFIX = "vtzero-"
# The store's growth rate is taken over this many recent days.
RATE_DAYS = 7.0
_DAY_S = 86400.0


@dataclass(frozen=True)
class StoreUsage:
    """What the store takes and how fast it grows (``vt-edge doctor`` shows it)."""

    bytes: int  # episodes, acceptance notes and recording segments
    episodes: int
    free_bytes: int  # on its filesystem
    # Over the episodes and segments of the last RATE_DAYS days (at least one day's worth);
    # None when there were none.
    bytes_per_day: float | None
    # Until retention starts removing (store_max_mb reached, keep_free_mb left), or the
    # filesystem is full where retention is off, at that rate; None without a rate.
    days_left: float | None


# The last millisecond an id was made for: ids sort in the order they were made, which is the
# order the store lists episodes in, even for two made within one millisecond.
_last_ms = 0
_last_ms_lock = threading.Lock()


def new_id(now: float | None = None) -> str:
    """An episode's id: the UTC time it was made (``now``, a test's, as given) and 6 random
    hex digits."""
    global _last_ms
    if now is not None:
        ms = round(now * 1000)
    else:
        with _last_ms_lock:
            ms = _last_ms = max(round(time.time() * 1000), _last_ms + 1)
    ts = datetime.fromtimestamp(ms / 1000, UTC)
    return f"{ts:%Y%m%dT%H%M%S}{ms % 1000:03d}Z-{secrets.token_hex(3)}"


def valid_id(episode_id: str) -> bool:
    return bool(_ID_RE.match(episode_id))


class EpisodeStore:
    def __init__(self, root: str | Path, *, max_bytes: int = 0, keep_free_bytes: int = 0,
                 segments: str | Path | None = None) -> None:
        self.root = Path(root)
        # Retention (see the module's docstring); 0: off. ``segments``: the live recording's
        # directory, whose completed segments count and go too.
        self.max_bytes = max_bytes
        self.keep_free_bytes = keep_free_bytes
        self.segments = Path(segments) if segments else None
        self.removed_episodes = 0
        self.removed_segments = 0
        self.removed_bytes = 0
        self._retaining = threading.Lock()
        # Bytes of each episode and segment, measured once (a write into an episode drops
        # its entry): a pass over a store of thousands of episodes lists it, nothing more.
        self._sizes: dict[Path, int] = {}
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(f"episode store {self.root} cannot be created: {exc}") from None
        # Why the last write failed; None once one works (see the module's docstring).
        self.write_error: str | None = None
        self.write_failures = 0  # writes that failed
        self.lost = 0  # episodes neither written nor held (the memory's bound reached)
        # Episodes finished while the store could not write: id -> (episode, files).
        self._held: dict[str, tuple[Episode, dict[str, bytes]]] = {}
        self._held_lock = threading.Lock()  # the methods run in threads

    @property
    def held(self) -> int:
        """Episodes held in memory, waiting for the store to write again."""
        return len(self._held)

    def error(self) -> str | None:
        """Why a new episode cannot be kept now (a write failed, or the disk is full)."""
        return self.write_error or self.space_error()

    def _failed(self, error: StoreError) -> StoreError:
        if self.write_error is None:
            log.error("%s; presses are refused until the store can write again", error)
        self.write_error = str(error)
        self.write_failures += 1
        return error

    def _worked(self) -> None:
        if self.write_error is not None:
            log.info("episode store %s writes again", self.root)
            self.write_error = None

    def check_writable(self) -> None:
        """Write and fsync a small file: :class:`StoreError` saying why if the store cannot
        (the start checks this before torque goes on; the daemon again while it cannot)."""
        try:
            (self.root / _ACCEPTED).mkdir(exist_ok=True)
            atomic_write_text(self.root / _ACCEPTED / _PROBE, f"{time.time()}\n")
        except OSError as exc:
            raise self._failed(_store_error(f"episode store {self.root} cannot write",
                                            exc)) from None
        self._worked()

    def flush(self) -> int:
        """Write the episodes held in memory, oldest first (how many were written); stops at
        the first that fails (:class:`StoreError`)."""
        written = 0
        while self._held:
            with self._held_lock:
                episode_id = next(iter(self._held))
                episode, files = self._held[episode_id]
            episode = episode.with_(note=None)
            if (self.root / episode_id).is_dir():  # written before; its update was not
                self._rewrite(episode)
            else:
                self._write(episode, files)
            with self._held_lock:
                self._held.pop(episode_id, None)
            log.info("episode %s written (held in memory while the store could not write)",
                     episode_id)
            written += 1
        return written

    def recover(self) -> int:
        """After a crash: remove episodes that were never completed (returns how many), and
        keep each press accepted but never kept as a ``failed`` "interrupted" episode."""
        removed = 0
        for tmp in self.root.glob(f"{_TMP_PREFIX}*"):
            shutil.rmtree(tmp, ignore_errors=True)
            removed += 1
        for tmp in [*self.root.glob(f"*/.{EPISODE_FILE}.*.tmp"),
                    *self.root.glob(f"{_ACCEPTED}/.*.tmp")]:
            with contextlib.suppress(OSError):  # (a read-only store: left for next time)
                tmp.unlink(missing_ok=True)
        if removed:
            log.warning("discarded %d incomplete episode(s) left by an interrupted write",
                        removed)
        for note in sorted((self.root / _ACCEPTED).glob("*.json")):
            episode_id = note.stem
            if valid_id(episode_id) and not (self.root / episode_id).is_dir():
                try:
                    accepted = json.loads(note.read_bytes())
                except (OSError, ValueError):
                    accepted = {}
                if not isinstance(accepted, dict):
                    accepted = {}
                self.create(Episode(episode_id, Status.FAILED, error=INTERRUPTED,
                                    candidates=accepted.get("candidates"),
                                    source=accepted.get("source"),
                                    accepted=accepted.get("accepted")), {})
                log.warning("episode %s: %s", episode_id, INTERRUPTED)
            with contextlib.suppress(OSError):
                note.unlink(missing_ok=True)
        return removed

    def accept(self, episode_id: str, candidates: list[str], source: str) -> None:
        """Note a press as accepted (written and fsynced), before anything moves (see
        ``_ACCEPTED``): :class:`StoreError` if the store cannot write."""
        notes = self.root / _ACCEPTED
        try:
            notes.mkdir(exist_ok=True)
            atomic_write_text(notes / f"{episode_id}.json", json.dumps(
                {"candidates": candidates, "source": source, "accepted": time.time()}))
        except OSError as exc:
            raise self._failed(_store_error(f"episode store {self.root} cannot write",
                                            exc)) from None
        self._worked()

    def space_error(self) -> str | None:
        """Why a new episode cannot be kept (the filesystem is full), or None.

        One ``statvfs`` call: cheap enough for every /healthz and every press.
        """
        try:
            st = os.statvfs(self.root)
        except OSError as exc:
            return f"episode store {self.root}: cannot check free space: {exc}"
        free = st.f_bavail * st.f_frsize
        if free < MIN_FREE_BYTES or (st.f_files and st.f_favail < 100):
            return (f"episode store {self.root}: disk full ({free / 2**20:.1f} MiB, "
                    f"{st.f_favail} inodes free; at least {MIN_FREE_BYTES / 2**20:.0f} MiB "
                    "needed): free space on its filesystem; older episodes are intact")
        return None

    def _dir(self, episode_id: str) -> Path:
        if not valid_id(episode_id):
            raise NotFoundError(f"no episode {episode_id!r} (not an episode id)")
        return self.root / episode_id

    def create(self, episode: Episode, files: dict[str, bytes]) -> str:
        """Write a new episode with its data files; returns its id. Where the store cannot
        write, the episode is held in memory (readable, written by :meth:`flush`) unless
        ``HELD_MAX`` are already: then :class:`StoreError`."""
        now = time.time()
        # The monotonic clock at the same instant: exports map the press's times to wall time.
        episode = episode.with_(created=now, updated=now, extra={
            **episode.extra, "created_monotonic": time.monotonic()})
        try:
            self._write(episode, files)
        except StoreError as exc:
            self._hold(episode, files, exc)
        else:
            self.retain()
        return episode.id

    def _hold(self, episode: Episode, files: dict[str, bytes], exc: StoreError) -> None:
        """Keep ``episode`` in memory until :meth:`flush` (re-raises ``exc`` when full)."""
        with self._held_lock:
            if episode.id not in self._held and len(self._held) >= HELD_MAX:
                self.lost += 1
                raise exc
            self._held[episode.id] = (episode.with_(note=(
                f"held in memory, not yet written: {exc}; written once the store can "
                "write again")), files)
        log.warning("episode %s held in memory until the store can write: %s", episode.id,
                    exc)

    def _write(self, episode: Episode, files: dict[str, bytes]) -> None:
        episode_id = episode.id
        self._sizes.pop(self.root / episode_id, None)
        tmp = self.root / f"{_TMP_PREFIX}{episode_id}"
        try:
            tmp.mkdir()
            for name, data in {**files, EPISODE_FILE: _dumps(episode.to_json())}.items():
                if "/" in name or name.startswith("."):
                    raise ValueError(f"bad episode file name {name!r}")
                with open(tmp / name, "wb") as fh:
                    fh.write(data)
                    fh.flush()
                    os.fsync(fh.fileno())
            fsync_dir(tmp)
            os.rename(tmp, self.root / episode_id)
            fsync_dir(self.root)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise self._failed(_store_error(f"episode {episode_id} could not be written",
                                            exc)) from None
        self._worked()
        # Kept: the note is done with (one left by a crash here is removed by recover()).
        with contextlib.suppress(OSError):
            (self.root / _ACCEPTED / f"{episode_id}.json").unlink(missing_ok=True)

    def update(self, episode_id: str, **fields: Any) -> Episode:
        """Change ``fields`` of the episode (names of :class:`Episode` fields), atomically
        (in memory for one held there)."""
        with self._held_lock:
            held = self._held.get(episode_id)
            if held is not None:
                episode = held[0].with_(**fields, updated=time.time())
                self._held[episode_id] = (episode, held[1])
                return episode
        episode = self.get(episode_id).with_(**fields, updated=time.time())
        try:
            self._rewrite(episode)
        except StoreError as exc:
            self._hold(episode, {}, exc)
        return episode

    def _rewrite(self, episode: Episode) -> None:
        self._sizes.pop(self.root / episode.id, None)
        try:
            atomic_write_text(self._dir(episode.id) / EPISODE_FILE,
                              _dumps(episode.to_json()).decode())
        except OSError as exc:
            raise self._failed(_store_error(f"episode {episode.id} could not be updated",
                                            exc)) from None
        self._worked()

    def get(self, episode_id: str) -> Episode:
        held = self._held.get(episode_id)
        if held is not None:
            return held[0]
        path = self._dir(episode_id) / EPISODE_FILE
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise NotFoundError(f"no episode {episode_id}") from None
        except (OSError, ValueError) as exc:
            raise StoreError(f"episode {episode_id} cannot be read: {exc}") from None
        return Episode.from_json(data, f"episode {episode_id}")

    def file(self, episode_id: str, name: str) -> Path:
        path = self._dir(episode_id) / name
        if "/" in name or not path.is_file():
            raise NotFoundError(f"episode {episode_id} has no file {name!r}")
        return path

    def ids(self) -> list[str]:
        return sorted(p.name for p in self.root.iterdir() if valid_id(p.name) and p.is_dir())

    def list(self, status: Status | None = None, limit: int | None = None) -> list[Episode]:
        """Episodes, newest first; unreadable entries are skipped with a warning."""
        out = []
        for episode_id in reversed(self.ids()):
            try:
                episode = self.get(episode_id)
            except StoreError as exc:
                log.warning("%s", exc)
                continue
            if status is None or episode.status == status:
                out.append(episode)
                if limit is not None and len(out) >= limit:
                    break
        return out

    def pending(self) -> list[Episode]:
        return list(reversed(self.list(status=Status.PENDING)))

    # --- retention ------------------------------------------------------------------------
    def size(self) -> int:
        """Bytes the store takes: its episodes (and notes) and the recording's segments."""
        return sum(n for _, _, n in self._entries()) + _tree_bytes(self.root / _ACCEPTED)

    def usage(self, now: float | None = None) -> StoreUsage:
        """The store's size, its recent growth and the days that leaves (see
        :class:`StoreUsage`). Lists the store: run it off the event loop."""
        now = time.time() if now is None else now
        entries = self._entries()
        size = sum(n for _, _, n in entries) + _tree_bytes(self.root / _ACCEPTED)
        recent = [(t, n) for t, n in ((_key_time(k), n) for k, _, n in entries)
                  if t is not None and now - t <= RATE_DAYS * _DAY_S]
        free = self._free_bytes()
        if not recent:
            return StoreUsage(size, len(self.ids()), free, None, None)
        days = max(1.0, (now - min(t for t, _ in recent)) / _DAY_S)
        rate = sum(n for _, n in recent) / days
        room = free - self.keep_free_bytes
        if self.max_bytes:
            room = min(room, self.max_bytes - size)
        return StoreUsage(size, len(self.ids()), free, rate, max(room, 0) / rate)

    def retain(self) -> None:
        """Remove the oldest finished episodes and segments while the store is past
        ``max_bytes`` or its filesystem has less than ``keep_free_bytes`` free (logged and
        counted). One pass at a time; one already running is enough."""
        if not (self.max_bytes or self.keep_free_bytes) or not self._retaining.acquire(
                blocking=False):
            return
        try:
            self._retain()
        finally:
            self._retaining.release()

    def _retain(self) -> None:
        entries = sorted(self._entries())
        size = sum(n for _, _, n in entries) + _tree_bytes(self.root / _ACCEPTED)
        over = size - self.max_bytes if self.max_bytes else 0
        short = self.keep_free_bytes - self._free_bytes() if self.keep_free_bytes else 0
        if over <= 0 and short <= 0:
            return
        episodes = segments = freed = 0
        for _, path, nbytes in entries:
            if freed >= max(over, short):
                break
            if path.parent == self.root and not self._finished(path.name):
                continue  # pending (or unreadable): never removed
            try:
                if path.is_dir():
                    shutil.rmtree(path)
                else:
                    path.unlink()
            except OSError as exc:
                log.warning("retention: %s could not be removed: %s", path, exc)
                continue
            freed += nbytes
            self._sizes.pop(path, None)
            if path.parent == self.root:
                episodes += 1
            else:
                segments += 1
        self.removed_episodes += episodes
        self.removed_segments += segments
        self.removed_bytes += freed
        why = (f"{size / 1e6:.1f} MB, over store_max_mb = {self.max_bytes / 1e6:g}"
               if over > 0 else f"under keep_free_mb = {self.keep_free_bytes / 1e6:g} free")
        log.info("retention: removed the %d oldest finished episode(s) and %d recording "
                 "segment(s), %.1f MB (the store was %s)", episodes, segments,
                 freed / 1e6, why)
        if freed < max(over, short):
            log.warning("retention: the store is still %s: what is left is pending or "
                        "the newest", why)

    def _entries(self) -> list[tuple[str, Path, int]]:
        """(time key, path, bytes) of each episode and completed segment; the key sorts
        oldest first across both (their names start with their UTC time)."""
        out = [(p.name[:15], p, self._bytes(p)) for p in self.root.iterdir()
               if valid_id(p.name)]
        if self.segments is not None and self.segments.is_dir():
            start = len(_SEGMENT_PREFIX)
            out += [(p.name[start:start + 15], p, self._bytes(p))
                    for p in self.segments.iterdir() if p.name.startswith(_SEGMENT_PREFIX)]
        return out

    def _bytes(self, path: Path) -> int:
        nbytes = self._sizes.get(path)
        if nbytes is None:
            nbytes = self._sizes[path] = _tree_bytes(path)
        return nbytes

    def _finished(self, episode_id: str) -> bool:
        try:
            return self.get(episode_id).status.final
        except StoreError:
            return False

    def _free_bytes(self) -> int:
        try:
            st = os.statvfs(self.root)
        except OSError:
            return self.keep_free_bytes  # (space_error says why)
        return st.f_bavail * st.f_frsize

    def export(self, episode_id: str, dest: str | Path) -> Path:
        """A .tar.gz of the whole episode directory."""
        src = self._dir(episode_id)
        if not src.is_dir():
            raise NotFoundError(f"no episode {episode_id}")
        dest = Path(dest)
        if dest.is_dir():
            dest = dest / f"{episode_id}.tar.gz"
        tmp = dest.with_name(f".{dest.name}.tmp")
        try:
            with tarfile.open(tmp, "w:gz") as tar:
                tar.add(src, arcname=episode_id)
            os.replace(tmp, dest)
        except OSError as exc:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            raise _store_error(f"episode {episode_id} could not be exported", exc) from None
        return dest


def _key_time(key: str) -> float | None:
    """The UTC time an episode's or segment's name starts with (``_entries``' key)."""
    try:
        return datetime.strptime(key, "%Y%m%dT%H%M%S").replace(tzinfo=UTC).timestamp()
    except ValueError:
        return None


def _tree_bytes(path: Path) -> int:
    """Bytes of the file, or of the files under the directory, at ``path``."""
    try:
        if not path.is_dir():
            return path.stat().st_size
        return sum((Path(d) / f).stat().st_size for d, _, files in os.walk(path)
                   for f in files)
    except OSError:
        return 0  # removed meanwhile


def _dumps(obj: Any) -> bytes:
    return (json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n").encode()


def _store_error(what: str, exc: OSError) -> StoreError:
    if exc.errno == errno.ENOSPC:
        return StoreError(f"{what}: the disk is full; free space on the store's filesystem "
                          "(older episodes are intact)")
    if exc.errno == errno.EROFS:
        return StoreError(f"{what}: its filesystem is read-only (an SD card turns read-only "
                          "after an error: see dmesg, check it, remount it read-write); older "
                          "episodes are intact")
    return StoreError(f"{what}: {exc}")
