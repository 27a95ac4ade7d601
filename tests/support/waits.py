"""Waiting in tests: a free loopback port, and polling until a condition holds (with a
bound, and a message naming what was awaited)."""

from __future__ import annotations

import asyncio
import inspect
import socket
import time
from collections.abc import Awaitable, Callable
from typing import Any

POLL_S = 0.01


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


async def wait_until(predicate: Callable[[], Any | Awaitable[Any]], timeout_s: float,
                     what: str = "the condition", interval_s: float = POLL_S) -> Any:
    """Poll ``predicate`` (plain or async) until it returns something truthy; returns that.
    ``AssertionError`` naming ``what`` past ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not met within {timeout_s} s")
        await asyncio.sleep(interval_s)


def wait_until_sync(predicate: Callable[[], Any], timeout_s: float,
                    what: str = "the condition", interval_s: float = POLL_S) -> Any:
    """:func:`wait_until` for code without an event loop (threads, subprocesses)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not met within {timeout_s} s")
        time.sleep(interval_s)
