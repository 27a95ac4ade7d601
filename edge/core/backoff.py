"""Capped exponential backoff: the one wait policy of every reconnect and retry loop (the
XELA client and the MQTT bridge through :mod:`edge.core.reconnect`, the bus's port reopening,
the VLM client, the episodes' VLM retries, the consistency measurement's failed presses).

The wait after the n-th failure in a row (n = 0, 1, ...) is ``base_s * 2**n``, at most
``cap_s``. A loop whose peer many clients share (a broker, a VLM server) spreads its waits
with jitter: each is that wait times a factor drawn uniformly from ``spread``, so clients
that failed together do not come back together.
"""

from __future__ import annotations

import random

# No jitter: every wait is exactly the backoff.
EXACT = (1.0, 1.0)
# Past this many doublings every wait is its cap (and 2.0**n stays a float).
_MAX_DOUBLINGS = 60


def backoff_s(n: int, base_s: float, cap_s: float) -> float:
    """The wait after the ``n``-th failure in a row (0: the first), before any jitter."""
    return min(cap_s, base_s * 2.0 ** min(n, _MAX_DOUBLINGS))


class Backoff:
    """One loop's waits: :meth:`next_s` gives the next and counts the failure, :meth:`reset`
    (after a success) starts again from ``base_s``."""

    def __init__(self, base_s: float, cap_s: float, spread: tuple[float, float] = EXACT,
                 rng: random.Random | None = None) -> None:
        self.base_s = base_s
        self.cap_s = cap_s
        self.spread = spread
        self.failures = 0
        self._rng = rng or random.Random()

    @property
    def delay_s(self) -> float:
        """The next wait before jitter (what a log line announces)."""
        return backoff_s(self.failures, self.base_s, self.cap_s)

    def next_s(self) -> float:
        delay = self.delay_s
        self.failures += 1
        return delay if self.spread == EXACT else delay * self._rng.uniform(*self.spread)

    def reset(self) -> None:
        self.failures = 0
