"""The daemon's event loop keeps timers to the microsecond (the 125 Hz sampler's deadlines)."""

import asyncio
import resource
import selectors

from edge.app import FD_SETSIZE, new_event_loop

DELAY_S = 0.0023  # 2.3 ms: epoll's whole-millisecond timeout makes it at least 3 ms


async def _lateness(n: int = 20) -> list[float]:
    """The lateness of n timers, sorted."""
    loop = asyncio.get_running_loop()
    late = []
    for _ in range(n):
        t0 = loop.time()
        await asyncio.sleep(DELAY_S)
        late.append(loop.time() - t0 - DELAY_S)
        await asyncio.sleep(0.0007)  # a fresh phase against the clock
    return sorted(late)


def test_timers_are_not_rounded_up_to_a_millisecond():
    limits = resource.getrlimit(resource.RLIMIT_NOFILE)
    try:
        loop = new_event_loop()
        assert isinstance(loop._selector, selectors.SelectSelector)  # type: ignore[attr-defined]
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        assert soft <= FD_SETSIZE  # select(2) never sees a descriptor it cannot take
        with asyncio.Runner(loop_factory=lambda: loop) as runner:
            ours_all = runner.run(_lateness())
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, limits)
    with asyncio.Runner(loop_factory=asyncio.new_event_loop) as runner:
        default_all = runner.run(_lateness())
    # The daemon's loop: its best timer (a busy host only ever adds to select's microsecond
    # wait). The default loop: its median, not its best: epoll rounds up the time left when
    # it is entered, so a timer whose loop was held back before the wait comes out less
    # late (a loaded run's best was 0.55 ms, where 0.7 is typical).
    ours, default = ours_all[0], default_all[len(default_all) // 2]
    print(f"\nlateness of a {DELAY_S * 1e3} ms timer: daemon loop {ours * 1e3:.3f} ms (best), "
          f"default (epoll) loop {default * 1e3:.3f} ms (median)")
    assert ours < 0.0005
    probe = asyncio.new_event_loop()
    epoll = isinstance(probe._selector, selectors.EpollSelector)  # type: ignore[attr-defined]
    probe.close()
    if epoll:
        assert default > 0.0006  # what the daemon's loop avoids
