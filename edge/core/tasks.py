"""Ending a helper task without losing a cancellation meant for the caller."""

from __future__ import annotations

import asyncio


async def cancel_and_wait(task: asyncio.Task) -> None:
    """Cancel ``task`` and wait until it has ended (its own exception, if any, raised).

    ``task.cancel(); with suppress(CancelledError): await task`` also swallows a
    cancellation of the caller that arrives while it waits (a Ctrl-C handed to the main
    task by ``asyncio.run``): the caller then goes on as if nothing had been asked. Here the
    helper's CancelledError is dropped and one asked of the caller meanwhile is raised. A
    caller already unwinding from a cancellation (this in its ``finally``) goes on with its
    cleanup: only a request newer than the call counts.
    """
    current = asyncio.current_task()
    asked = current.cancelling() if current is not None else 0
    task.cancel()
    try:
        await task
    except asyncio.CancelledError:
        if current is not None and current.cancelling() > asked:
            raise
