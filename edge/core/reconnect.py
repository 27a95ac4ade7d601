"""One link kept up: the reconnect loop of the XELA client and the MQTT bridge.

:class:`Reconnect` calls an attempt (one connection, from dialling to its loss) again and
again, waiting a capped backoff (:mod:`edge.core.backoff`) between attempts. It keeps the
link's state (up or not, connections made, failed tries in a row and why the last one
failed) and says it in the log once per outage: the first failed try at WARNING, the
repeats at DEBUG with their number, and, when the link is back, how long it was away and
how many tries it took. Hooks run when the link comes up and when it is lost.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from typing import NoReturn

from edge.core.backoff import Backoff

Hook = Callable[[], None]


class Reconnect:
    """The state and the loop of one link to ``name`` (a peer in words, for the log).

    The attempt given to :meth:`run` calls :meth:`up` once its link is established and
    returns whether the link served (then the backoff starts again from its base); it
    raises one of ``transient`` when it could not connect or the link broke. ``clock`` and
    ``sleep`` are injectable (tests run the loop on a virtual clock).
    """

    def __init__(self, name: str, backoff: Backoff, logger: logging.Logger, *,
                 on_up: Hook | None = None, on_loss: Hook | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], Awaitable[None]] = asyncio.sleep) -> None:
        self.name = name
        self.backoff = backoff
        self.connected = False
        self.connections = 0  # links established so far
        self.tries = 0  # failed tries since the link was last up
        self.last_failure: str | None = None  # why the last try failed (None once up)
        self._log = logger
        self._on_up = on_up
        self._on_loss = on_loss
        self._clock = clock
        self._sleep = sleep
        self._down_since: float | None = None  # since when the link is wanted and not up

    @property
    def attempt(self) -> int:
        """The number of the attempt under way, counted from the last time the link was up."""
        return self.tries + 1

    def up(self) -> None:
        """The link is established: says how long it took when tries failed before it."""
        if self.tries and self._down_since is not None:
            self._log.info("%s: back after %.2f s and %d tries", self.name,
                           self._clock() - self._down_since, self.attempt)
        self.connected = True
        self.connections += 1
        self.tries = 0
        self.last_failure = None
        self._down_since = None
        if self._on_up is not None:
            self._on_up()

    def failed(self, why: str) -> float:
        """A try failed (``why`` in words): logs it and returns the wait before the next."""
        if self._down_since is None:
            self._down_since = self._clock()
        self.tries += 1
        self.last_failure = why
        wait_s = self.backoff.next_s()
        # Said once per outage: a peer that stays away must not flood the log.
        self._log.log(logging.WARNING if self.tries == 1 else logging.DEBUG,
                      "%s: attempt %d failed (%s); next try in %.2f s", self.name,
                      self.tries, why, wait_s)
        return wait_s

    def _lost(self) -> None:
        self.connected = False
        self._down_since = self._clock()
        if self._on_loss is not None:
            self._on_loss()

    async def run(self, attempt: Callable[[], Awaitable[bool]],
                  transient: tuple[type[BaseException], ...],
                  fatal: tuple[type[BaseException], ...] = ()) -> NoReturn:
        """Attempt, wait, attempt again, forever (until cancelled); an exception not in
        ``transient``, or in ``fatal`` (a kind of a transient one that retrying cannot
        mend), ends the loop and propagates."""
        while True:
            try:
                served = await attempt()
            except fatal:
                raise
            except transient as exc:
                wait_s = self.failed(str(exc) or type(exc).__name__)
            else:
                if served:
                    self.backoff.reset()
                wait_s = self.backoff.next_s()
            finally:
                if self.connected:
                    self._lost()
            await self._sleep(wait_s)
