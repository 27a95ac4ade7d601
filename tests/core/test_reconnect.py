"""The one reconnect loop, on a virtual clock: its waits, its log once per outage, its state
and hooks."""

import logging

import pytest

from edge.core.backoff import Backoff
from edge.core.reconnect import Reconnect

log = logging.getLogger("test.reconnect")


class Clock:
    """Virtual time: ``sleep`` advances it and records the wait (nothing really waits)."""

    def __init__(self) -> None:
        self.t = 100.0
        self.waits: list[float] = []

    def __call__(self) -> float:
        return self.t

    async def sleep(self, s: float) -> None:
        self.waits.append(s)
        self.t += s


class Stop(Exception):
    """Ends the loop under test (not transient)."""


def script(link: Reconnect, clock: Clock, steps: list[str]):
    """An attempt playing ``steps``: "refused" fails to connect, "served" comes up and
    returns True, "silent" comes up and returns False, "broken" comes up then raises."""
    seen: list[tuple[str, bool, int]] = []

    async def attempt() -> bool:
        if not steps:
            raise Stop
        step = steps.pop(0)
        clock.t += 0.01  # the dial itself
        if step == "refused":
            raise ConnectionRefusedError("connection refused")
        link.up()
        seen.append((step, link.connected, link.connections))
        if step == "broken":
            raise OSError("connection reset")
        return step == "served"

    return attempt, seen


@pytest.mark.asyncio
async def test_waits_grow_while_refused_and_start_again_once_the_link_served(caplog):
    caplog.set_level(logging.DEBUG, logger=log.name)
    clock = Clock()
    events: list[str] = []
    link = Reconnect("peer ws://x", Backoff(0.05, 0.4), log, clock=clock, sleep=clock.sleep,
                     on_up=lambda: events.append("up"), on_loss=lambda: events.append("lost"))
    steps = ["refused"] * 5 + ["served", "refused", "refused", "silent", "silent"]
    attempt, seen = script(link, clock, steps)
    with pytest.raises(Stop):
        await link.run(attempt, (OSError,))
    print(f"waits {clock.waits}")
    assert clock.waits == [0.05, 0.1, 0.2, 0.4, 0.4,  # refused: doubling up to the cap
                           0.05,  # served: from the base again
                           0.1, 0.2,  # refused twice more
                           0.4,  # up but silent: no reset (a peer that serves nothing)
                           0.4]
    assert events == ["up", "lost"] * 3 and not link.connected
    assert link.connections == 3 and [s[1] for s in seen] == [True] * 3
    failed = [r for r in caplog.records if "failed" in r.getMessage()]
    # One warning per outage; the repeats are numbered, at DEBUG.
    assert [r.levelno for r in failed] == [logging.WARNING] + [logging.DEBUG] * 4 \
        + [logging.WARNING, logging.DEBUG]
    assert failed[3].getMessage() == ("peer ws://x: attempt 4 failed (connection refused); "
                                      "next try in 0.40 s")
    back = [r.getMessage() for r in caplog.records if "back after" in r.getMessage()]
    # Down from the first refusal to the sixth dial (5 dials of 0.01 s, 1.15 s waited).
    assert back[0] == "peer ws://x: back after 1.20 s and 6 tries"
    # Down from the loss (waits 0.05 + 0.1 + 0.2, 3 dials).
    assert back[1] == "peer ws://x: back after 0.38 s and 3 tries"
    assert len(back) == 2  # the silent link's redial needed no failed try


@pytest.mark.asyncio
async def test_a_broken_link_is_a_loss_then_a_failure_said_once():
    clock = Clock()
    events: list[str] = []
    link = Reconnect("peer", Backoff(0.1, 1.0), log, clock=clock, sleep=clock.sleep,
                     on_up=lambda: events.append("up"), on_loss=lambda: events.append("lost"))
    attempt, _ = script(link, clock, ["broken", "refused"])
    with pytest.raises(Stop):
        await link.run(attempt, (OSError,))
    assert events == ["up", "lost"] and clock.waits == [0.1, 0.2]
    assert link.tries == 2 and link.attempt == 3 and link.last_failure == "connection refused"


@pytest.mark.asyncio
async def test_an_error_fatal_or_not_transient_ends_the_loop_and_the_link():
    clock = Clock()
    lost: list[bool] = []
    link = Reconnect("peer", Backoff(0.1, 1.0), log, clock=clock, sleep=clock.sleep,
                     on_loss=lambda: lost.append(True))

    class LayoutError(OSError):
        """Transient by its kind, but retrying cannot mend it."""

    async def attempt() -> bool:
        link.up()
        raise LayoutError("a layout the configuration does not match")

    with pytest.raises(LayoutError, match="layout"):
        await link.run(attempt, (OSError,), fatal=(LayoutError,))
    assert lost == [True] and not link.connected and clock.waits == []
    with pytest.raises(Stop):
        await link.run(script(link, clock, [])[0], (OSError,))
    assert lost == [True] and link.connections == 1
