"""Press recordings for tests, made by the dataset recorder (the daemon's press controller on
the virtual robot) and kept for the session."""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor

from edge.core.recording import Recording
from edge.lab.record import record_press


@functools.cache
def recording_of(name: str, seed: int = 0) -> Recording:
    """One press of ``name``; callable from an async test too (the virtual robot's own event
    loop runs in a thread of its own). Treat it as read-only: it is shared."""
    with ThreadPoolExecutor(1) as pool:
        return pool.submit(record_press, name, seed).result().recording
