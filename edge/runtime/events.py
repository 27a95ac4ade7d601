"""The daemon's event bus: what it publishes while it runs (the typed events of
:mod:`edge.runtime.domain`), for the API's server-sent events, MQTT, the live recording and the
operator page.

Publishing an event never waits: each subscriber has a bounded queue, and a slow one loses
its oldest events, never the daemon its pace.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterator

from edge.runtime.domain import Event, Hello

# Events a subscriber may fall behind by before it loses the oldest.
EVENT_QUEUE = 256


class Subscription:
    """One listener's queue. Waiting on it with a timeout (``asyncio.wait_for(sub.get(),
    t)``) is safe: a timeout cancels only that wait, never the subscription."""

    def __init__(self, first: Event, size: int = EVENT_QUEUE) -> None:
        self._queue: asyncio.Queue[Event] = asyncio.Queue(size)
        self._queue.put_nowait(first)

    def put(self, event: Event) -> None:
        if self._queue.full():
            with contextlib.suppress(asyncio.QueueEmpty):
                self._queue.get_nowait()  # a slow client loses the oldest event
        self._queue.put_nowait(event)

    async def get(self) -> Event:
        return await self._queue.get()

    def __aiter__(self) -> Subscription:
        return self

    async def __anext__(self) -> Event:
        return await self._queue.get()


class EventBus:
    def __init__(self) -> None:
        self._subscribers: set[Subscription] = set()

    def publish(self, event: Event) -> None:
        for sub in list(self._subscribers):
            sub.put(event)

    @contextlib.contextmanager
    def subscribe(self, hello: Hello) -> Iterator[Subscription]:
        """A subscription whose first event is ``hello`` (the state when it began)."""
        sub = Subscription(hello)
        self._subscribers.add(sub)
        try:
            yield sub
        finally:
            self._subscribers.discard(sub)
