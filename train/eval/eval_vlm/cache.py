"""The answer cache: every answer appended as it arrives, so an interrupted run continues
where it stopped and never asks a cached question again."""

from __future__ import annotations

import json
import logging
import os
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


ANSWERS_FILE = "answers.jsonl"
CACHE_SCHEMA = 1


class AnswerCache:
    """``answers.jsonl``: one JSON record per line, keyed by ``record["key"]``.

    An append is one ``write`` of one whole line to a file opened with ``O_APPEND``, then an
    fsync: a crash leaves at most a torn last line, which :meth:`load` drops (and cuts off,
    so the next append starts a clean line). Thread-safe (appends come from worker threads).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self.records: dict[str, dict[str, Any]] = {}

    def load(self) -> dict[str, dict[str, Any]]:
        self.records = {}
        if not self.path.exists():
            return self.records
        data = self.path.read_bytes()
        end = data.rfind(b"\n") + 1
        if end < len(data):
            log.warning("%s: dropping a torn last line (%d bytes) left by an interrupted run",
                        self.path, len(data) - end)
            with open(self.path, "r+b") as fh:
                fh.truncate(end)
                fh.flush()
                os.fsync(fh.fileno())
        bad = 0
        for line in data[:end].splitlines():
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
                key = rec["key"]
                rec["answer"]["status"]
            except (ValueError, KeyError, TypeError):
                bad += 1
                continue
            self.records.setdefault(key, rec)  # the first answer of a key wins
        if bad:
            log.warning("%s: ignored %d unreadable line(s)", self.path, bad)
        return self.records

    def append(self, record: Mapping[str, Any]) -> None:
        line = (json.dumps(record, ensure_ascii=False, separators=(",", ":")) + "\n"
                ).encode("utf-8")
        with self._lock:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                view = memoryview(line)
                while view:
                    written = os.write(fd, view)
                    view = view[written:]
                os.fsync(fd)
            finally:
                os.close(fd)
            self.records.setdefault(record["key"], dict(record))
