"""The daemon's event loop keeps timers to the microsecond (the 125 Hz sampler's deadlines)."""

import asyncio
import resource
import selectors

from edge.daemon.serve import FD_SETSIZE, new_event_loop

DELAY_S = 0.0023  # 2.3 ms: epoll's whole-millisecond timeout makes it at least 3 ms


async def _best_lateness(n: int = 20) -> float:
    """The smallest lateness of n timers (noise on a shared box only ever adds to it)."""
    loop = asyncio.get_running_loop()
    best = float("inf")
    for _ in range(n):
        t0 = loop.time()
        await asyncio.sleep(DELAY_S)
        best = min(best, loop.time() - t0 - DELAY_S)
        await asyncio.sleep(0.0007)  # a fresh phase against the clock
    return best


def test_timers_are_not_rounded_up_to_a_millisecond():
    limits = resource.getrlimit(resource.RLIMIT_NOFILE)
    try:
        loop = new_event_loop()
        assert isinstance(loop._selector, selectors.SelectSelector)  # type: ignore[attr-defined]
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        assert soft <= FD_SETSIZE  # select(2) never sees a descriptor it cannot take
        with asyncio.Runner(loop_factory=lambda: loop) as runner:
            ours = runner.run(_best_lateness())
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, limits)
    with asyncio.Runner(loop_factory=asyncio.new_event_loop) as runner:
        default = runner.run(_best_lateness())
    print(f"\nbest lateness of a {DELAY_S * 1e3} ms timer: daemon loop {ours * 1e3:.3f} ms, "
          f"default (epoll) loop {default * 1e3:.3f} ms")
    assert ours < 0.0005
    probe = asyncio.new_event_loop()
    epoll = isinstance(probe._selector, selectors.EpollSelector)  # type: ignore[attr-defined]
    probe.close()
    if epoll:
        assert default > 0.0006  # what the daemon's loop avoids
