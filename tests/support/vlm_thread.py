"""A fake VLM server on its own event loop in a thread, for synchronous code under test (a
CLI, a subprocess pointed at it)."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Iterator

from edge.sim.fake_vlm import FakeVLM


@contextlib.contextmanager
def fake_in_thread(**kwargs) -> Iterator[FakeVLM]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    fake = FakeVLM(**kwargs)
    asyncio.run_coroutine_threadsafe(fake.start(), loop).result(10)
    try:
        yield fake
    finally:
        asyncio.run_coroutine_threadsafe(fake.stop(), loop).result(10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()
