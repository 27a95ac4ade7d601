"""Progress of long commands on stderr: a tqdm bar on a terminal, whole lines anywhere else.

On a terminal the bar is redrawn in place (tqdm). In a CI log, journald or a pipe a redrawn
line piles up as ``1/8 presses  2/8 presses ...`` on one line, so there each update that is
due prints one whole line::

    record reference: 120/320 presses, 4.1 s
    train vq: 40/300 epochs, 12.3 s, val 0.0102 best 0.0101@38

at most every ``every_s`` seconds, and the last state is always printed when the task ends.
Used by ``vt-edge sim record``, ``vt-edge bench`` and ``vt-train`` (training, release,
eval-vlm).
"""

from __future__ import annotations

import sys
import time
from types import TracebackType
from typing import TextIO

# Plain lines: at most one per this many seconds (the final state is always printed).
PLAIN_EVERY_S = 5.0


class Progress:
    """Progress of one task of ``total`` steps (``None``: unknown); also a context manager."""

    def __init__(self, desc: str, total: int | None = None, unit: str = "", *,
                 stream: TextIO | None = None, every_s: float = PLAIN_EVERY_S,
                 enabled: bool = True, tty: bool | None = None, initial: int = 0) -> None:
        self.desc = desc
        self.total = total
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.every_s = every_s
        self.enabled = enabled
        self.tty = _isatty(self.stream) if tty is None else tty
        self.done = initial
        self.note = ""
        self.started = time.monotonic()
        self._last_line = self.started
        self._printed: tuple[int, str] | None = None
        self._closed = False
        self._bar = None
        if enabled and self.tty:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=desc, unit=f" {unit}" if unit else "it",
                             file=self.stream, initial=initial, dynamic_ncols=True,
                             leave=True)

    # --- updates -----------------------------------------------------------------------
    def update(self, n: int = 1, note: str | None = None) -> None:
        """``n`` more steps done; ``note`` (if given) replaces the text after the count."""
        self.set(self.done + n, note)

    def set(self, done: int, note: str | None = None) -> None:
        """The absolute number of steps done (a training epoch, an answer count)."""
        if self._closed:
            return
        step = done - self.done
        self.done = done
        if note is not None:
            self.note = note
        if not self.enabled:
            return
        if self._bar is not None:
            if note is not None:
                self._bar.set_postfix_str(note, refresh=False)
            self._bar.update(step)
            return
        now = time.monotonic()
        if now - self._last_line >= self.every_s:
            self._emit(now)

    def close(self, note: str | None = None) -> None:
        """The end: the final state is shown (once)."""
        if self._closed:
            return
        if note is not None:
            self.note = note
        self._closed = True
        if not self.enabled:
            return
        if self._bar is not None:
            if note is not None:
                self._bar.set_postfix_str(note, refresh=False)
            self._bar.close()
        elif self._printed != (self.done, self.note):
            self._emit(time.monotonic())

    # --- plain lines ---------------------------------------------------------------------
    def line(self, now: float | None = None) -> str:
        elapsed = (now if now is not None else time.monotonic()) - self.started
        count = f"{self.done}/{self.total}" if self.total is not None else f"{self.done}"
        text = f"{self.desc}: {count}{' ' + self.unit if self.unit else ''}, {elapsed:.1f} s"
        return f"{text}, {self.note}" if self.note else text

    def _emit(self, now: float) -> None:
        self._last_line = now
        self._printed = (self.done, self.note)
        print(self.line(now), file=self.stream, flush=True)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False
