"""Waiting in tests: a free loopback port, and polling until a condition holds (with a
bound, and a message naming what was awaited)."""

from __future__ import annotations

import asyncio
import inspect
import itertools
import os
import random
import socket
import time
from collections.abc import Awaitable, Callable
from typing import Any

POLL_S = 0.01
# Ports handed out lie below Linux's ephemeral range (32768-60999), so no outgoing connection
# takes one between the check and the bind, in a block of their own per pytest-xdist worker,
# so that two workers never hand out the same one.
PORT_BASE = 20000
PORT_BLOCK = 1000
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
_BLOCK_START = PORT_BASE + PORT_BLOCK * (int(_WORKER) % 12 if _WORKER.isdigit() else 0)
# A random start: concurrent runs on one host do not walk the same ports in step.
_next = itertools.count(random.randrange(PORT_BLOCK))


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, from this worker's own block."""
    for _ in range(PORT_BLOCK):
        port = _BLOCK_START + next(_next) % PORT_BLOCK
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise OSError(f"no free port in {_BLOCK_START}-{_BLOCK_START + PORT_BLOCK - 1}")


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
