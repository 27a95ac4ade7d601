"""The server the compute process is forked from, and its start ahead of the daemon's imports.

``vt-edge run`` starts it first thing: its imports (the compute module, onnxruntime, Pillow)
then run in a process of their own beside the daemon's (aiohttp, numpy) instead of after
them, which brings READY closer. Only the standard library here, so that starting it costs
nothing of what it is meant to overlap.
"""

from __future__ import annotations

import multiprocessing
from multiprocessing import forkserver
from multiprocessing.context import ForkServerContext

# Imported once by the server; each compute worker is a fork of it. The images module
# (Pillow): the photo is prepared in the worker too.
PRELOAD = ("edge.runtime.compute", "onnxruntime", "edge.vlm.images")


def context() -> ForkServerContext:
    """The forkserver context with its preload set (no effect once the server runs)."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))
    return ctx


def start() -> None:
    """Start the server now, not at the first worker (idempotent)."""
    context()
    forkserver.ensure_running()
