"""Logging set up once for every entry point."""

from __future__ import annotations

import logging
import os
import sys

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
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(fmt))
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(level)
    _configured = True
