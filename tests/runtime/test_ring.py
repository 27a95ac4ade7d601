"""The frame ring's wait for a frame: woken by the push that brings it, not by polling."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from edge.runtime.ring import FrameRing

pytestmark = pytest.mark.asyncio
RAW = np.zeros(96, dtype=np.uint16)


async def test_a_waiter_is_woken_by_the_push_of_the_frame_at_or_past_its_time():
    ring = FrameRing(96, 16)
    ring.push(RAW, 1.0, 1.0, 1)
    assert await ring.wait_until(1.0, 0.0)  # already there: no wait at all
    waiting = asyncio.create_task(ring.wait_until(1.5, 10.0))
    await asyncio.sleep(0)
    ring.push(RAW, 1.4, 1.4, 2)
    await asyncio.sleep(0)
    assert not waiting.done()  # a frame before the time does not wake it
    ring.push(RAW, 1.5, 1.5, 3)
    assert await asyncio.wait_for(waiting, 1.0)  # woken by that push, long before 10 s
    assert ring._waiters == []


async def test_a_stream_that_never_reaches_the_time_ends_the_wait_false():
    ring = FrameRing(96, 16)
    ring.push(RAW, 1.0, 1.0, 1)
    assert not await ring.wait_until(2.0, 0.05)
    assert ring._waiters == []  # nothing left behind for a later push to touch
    ring.push(RAW, 2.0, 2.0, 2)
