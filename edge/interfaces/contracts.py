"""What the interfaces (the HTTP API and its operator page, MQTT) need from the daemon: two
small seams, not the runtime's internals. :class:`edge.runtime.lifecycle.Runtime` is both."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, TypeVar

from edge.runtime.domain import Episode, Health
from edge.runtime.taps import LiveTaps

T = TypeVar("T")


class Recognitions(Protocol):
    """Recognitions and their episodes, the abort, and the daemon's health and metrics."""

    async def recognize(self, candidates: list[str], image: bytes | None, wait: bool,
                        timeout_s: float | None, source: str) -> Episode: ...

    async def episode(self, episode_id: str) -> Episode: ...

    async def retry(self, episode_id: str) -> Episode: ...

    async def abort(self) -> bool: ...

    def episodes(self, limit: int) -> list[Episode]:
        """The newest ``limit`` episodes, newest first (blocks: file reads)."""
        ...

    def episode_file(self, episode_id: str, name: str) -> Path:
        """A file of an episode (``image.jpg``, ``press.press.npz``, ...);
        :class:`~edge.core.errors.NotFoundError` if it has none (blocks: file reads)."""
        ...

    def health(self) -> Health: ...

    def metrics_text(self) -> str: ...

    async def run_cpu(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in the compute process (CPU work off the event loop)."""
        ...


class Serving(Recognitions, LiveTaps, Protocol):
    """The daemon as an interface serves it: its recognitions and its live taps."""
