"""cancel_and_wait: a helper task ended, the caller's own cancellation never lost."""

from __future__ import annotations

import asyncio

import pytest

from edge.core.tasks import cancel_and_wait

pytestmark = pytest.mark.asyncio


async def slow_to_end(ended: list[str]) -> None:
    """A helper whose cleanup takes a while (as a press's gripper trace read does)."""
    try:
        await asyncio.sleep(10)
    finally:
        await asyncio.sleep(0.05)
        ended.append("helper")


async def test_the_helper_is_ended_and_its_cancellation_not_raised():
    ended: list[str] = []
    helper = asyncio.create_task(slow_to_end(ended))
    await asyncio.sleep(0)
    await cancel_and_wait(helper)
    assert helper.cancelled() and ended == ["helper"]


async def test_a_cancellation_of_the_caller_while_it_waits_is_not_swallowed():
    ended: list[str] = []
    went_on = []

    async def caller() -> None:
        helper = asyncio.create_task(slow_to_end(ended))
        await asyncio.sleep(0)
        await cancel_and_wait(helper)
        went_on.append("after")  # a swallowed Ctrl-C would get here
        await asyncio.sleep(10)

    task = asyncio.create_task(caller())
    await asyncio.sleep(0.01)  # the caller now waits for the helper's 50 ms cleanup
    task.cancel()  # as asyncio.run does on Ctrl-C
    with pytest.raises(asyncio.CancelledError):
        await task
    assert went_on == []  # (the helper's cleanup got the cancellation too: asyncio's way)


async def test_a_caller_already_unwinding_goes_on_with_its_cleanup():
    ended: list[str] = []
    cleaned = []

    async def caller() -> None:
        helper = asyncio.create_task(slow_to_end(ended))
        try:
            await asyncio.sleep(10)
        finally:
            await cancel_and_wait(helper)
            cleaned.append("after the helper")  # e.g. torque off, the port closed

    task = asyncio.create_task(caller())
    await asyncio.sleep(0.01)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert cleaned == ["after the helper"] and ended == ["helper"]
