"""What the interfaces (the HTTP API and its operator page, MQTT) need from the daemon: small
seams, not the runtime's internals. :class:`edge.runtime.lifecycle.Runtime` is each."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, TypeVar

from edge.runtime.domain import Episode, Health, TeachRun
from edge.runtime.recognition import Presses
from edge.runtime.references import Source, TaughtReference
from edge.runtime.taps import LiveTaps
from edge.runtime.teaching import PAUSE_S

T = TypeVar("T")


class Recognitions(Protocol):
    """Recognitions and their episodes, the abort, and the daemon's health and metrics."""

    async def recognize(self, candidates: list[str], image: bytes | None, wait: bool,
                        timeout_s: float | None, source: str, presses: Presses = 1,
                        pause_s: float = PAUSE_S) -> Episode:
        """``presses``: 1..MAX_FUSED_PRESSES presses of the object, ``pause_s`` apart, or
        "auto", fused into one question."""
        ...

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


class Teaching(Protocol):
    """Teaching the robot references (edge.runtime.teaching): presses of an object, or an
    episode's press, named; the taught references listed and removed."""

    async def teach(self, label: str, description: str | None, presses: int, append: bool,
                    source: Source, *, pause_s: float, wait: bool) -> TeachRun:
        """Refused before the arm moves (BadRequest, BusyError); with ``wait`` as ended."""
        ...

    async def teach_episode(self, episode_id: str, label: str, description: str | None,
                            source: Source) -> TaughtReference: ...

    def teaching(self) -> TeachRun | None:
        """The teaching under way, or the last one (None: none since the start)."""
        ...

    async def references(self) -> dict[str, Any]:
        """``{"directory", "references": [...]}``, each without its embedding."""
        ...

    async def remove_references(self, ref_id: str | None = None, label: str | None = None
                                ) -> list[TaughtReference]: ...


class Serving(Recognitions, Teaching, LiveTaps, Protocol):
    """The daemon as an interface serves it: its recognitions, teaching and live taps."""
