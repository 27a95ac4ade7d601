"""Logging set up once for every entry point."""

from __future__ import annotations

import logging
import os
import sys
from typing import TextIO

_configured = False


def setup_logging(level: int | str | None = None) -> None:
    """Configure the root logger once.

    Under systemd (``JOURNAL_STREAM`` is set) the journal adds its own timestamps, so lines
    are plain ``LEVEL name: message``; elsewhere they carry a timestamp.
    """
    global _configured
    if level is None:
        # $VTZERO_LOG_LEVEL (e.g. WARNING) lets a supervisor quieten the daemon.
        level = os.environ.get("VTZERO_LOG_LEVEL", "INFO").upper()
    if _configured:
        logging.getLogger().setLevel(level)
        return
    if os.environ.get("JOURNAL_STREAM"):
        fmt = "%(levelname)s %(name)s: %(message)s"
    else:
        fmt = "%(asctime)s %(levelname)s %(name)s: %(message)s"
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter(fmt))
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(level)
    _configured = True


class _StderrHandler(logging.StreamHandler):
    """Writes to ``sys.stderr`` as it is when a record is logged, not as it was when logging
    was configured: a caller that swaps it (a test capturing a command's output, a tool
    running a command in its own process) reads what the command said."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property  # type: ignore[override]
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, _value: TextIO) -> None:
        pass

