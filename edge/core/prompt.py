"""Asking the person at the robot: a prompt that a Ctrl-C does not wait on.

``input`` run by ``asyncio.to_thread`` keeps the process after Ctrl-C until Enter:
``asyncio.run`` waits for the default executor's threads at shutdown. :func:`reply` runs the
prompt in a daemon thread instead, and :func:`read_line` reads the terminal's file
descriptor, holding no lock that the interpreter's exit needs.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import threading
from collections.abc import Callable
from typing import TypeVar

from edge.core.errors import EdgeError

Prompt = Callable[[str], object]
T = TypeVar("T")
# What to do about a closed standard input, for a command with --no-prompt.
NO_PROMPT = "run it in a terminal, or pass --no-prompt"


def read_line(message: str) -> str:
    """``input()`` that leaves no lock behind: it reads the terminal's file descriptor, so a
    Ctrl-C while it waits ends the process at once (the waiting thread is a daemon thread
    holding no Python lock that the exit needs)."""
    os.write(sys.stdout.fileno(), message.encode())
    line = bytearray()
    while not line.endswith(b"\n"):
        chunk = os.read(sys.stdin.fileno(), 1)
        if not chunk:
            raise EOFError
        line += chunk
    return line.decode(errors="replace").rstrip("\n")


async def in_daemon_thread(fn: Callable[..., T], *args: object) -> T:
    """``fn(*args)`` in a daemon thread, its result or its exception; cancelling the wait
    (Ctrl-C) does not wait for it, as a thread of the default executor would at the loop's
    shutdown."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[T] = loop.create_future()

    def settle(result: T | None, exc: BaseException | None) -> None:
        if not done.done():
            if exc is None:
                done.set_result(result)  # type: ignore[arg-type]
            else:
                done.set_exception(exc)

    def run() -> None:
        result, exc = None, None
        try:
            result = fn(*args)
        except BaseException as e:  # handed to the waiting task
            exc = e
        with contextlib.suppress(RuntimeError):  # the loop has closed: nobody waits
            loop.call_soon_threadsafe(settle, result, exc)

    threading.Thread(target=run, name="prompt", daemon=True).start()
    return await done


async def reply(prompt: Prompt, message: str) -> object:
    """The answer to ``prompt(message)`` (see :func:`in_daemon_thread`); EOFError where
    standard input is closed."""
    return await in_daemon_thread(prompt, message)


async def ask(prompt: Prompt, message: str,
              closed: str = "run it in a terminal, where Enter answers each step") -> None:
    """:func:`reply`, a closed standard input an EdgeError saying ``closed`` (what to do)."""
    try:
        await reply(prompt, message)
    except EOFError:
        raise EdgeError(f"no answer at the prompt (standard input is closed): {closed}") from None
