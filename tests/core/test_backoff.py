"""The one backoff of the reconnect and retry loops."""

import random

from edge.core.backoff import Backoff, backoff_s
from edge.vlm.transport import BACKOFF_SPREAD


def test_waits_double_up_to_the_cap_and_start_again_after_a_success():
    b = Backoff(0.05, 0.3)
    assert [b.next_s() for _ in range(5)] == [0.05, 0.1, 0.2, 0.3, 0.3]
    assert b.failures == 5 and b.delay_s == 0.3
    b.reset()
    assert b.next_s() == 0.05
    assert backoff_s(10_000, 0.5, 8.0) == 8.0  # no overflow however long the outage


def test_jitter_draws_within_its_spread_of_the_backoff():
    b = Backoff(0.5, 8.0, BACKOFF_SPREAD, random.Random(1))
    for n in range(12):
        d = min(8.0, 0.5 * 2**n)
        assert b.delay_s == d
        draws = []
        for _ in range(50):
            draws.append(b.next_s())
            b.failures = n  # the same failure again: its spread
        assert all(d / 2 <= x <= d for x in draws) and len(set(draws)) > 1
        b.failures = n + 1
    mqtt = Backoff(1.0, 1.0, (0.8, 1.2), random.Random(2))
    waits = [mqtt.next_s() for _ in range(200)]
    print(f"mqtt-style waits: {min(waits):.3f}..{max(waits):.3f} s")
    assert all(0.8 <= w <= 1.2 for w in waits) and min(waits) < 0.9 and max(waits) > 1.1
