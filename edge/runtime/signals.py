"""SIGHUP and SIGTERM sent to ``vt-edge run`` before its runtime handles them: held, never
fatal.

Their default action ends the process: a reload sent right after a start (a deployment
script) or a stop while the model loads would end the daemon with nothing made safe, or
leave torque on. ``vt-edge run`` holds them from its entry point's first instruction on
(``edge/__main__.py``, :func:`hold_if_daemon`): each is recorded, and the runtime takes them over
when it runs (:meth:`edge.runtime.lifecycle.Runtime.run`): a stop then stops it, a reload
follows once it serves. On its way out the runtime gives them back to this hold, so a signal
during the shutdown that makes the arm safe is not fatal either.

Stdlib only: imported by the entry point before anything else.
"""

from __future__ import annotations

import signal
from collections.abc import Sequence
from types import FrameType

HELD = (signal.SIGHUP, signal.SIGTERM)
_pending: set[int] = set()


def is_daemon(argv: Sequence[str]) -> bool:
    """Whether the arguments of ``vt-edge`` (``sys.argv[1:]``) ask for ``run`` (``--config
    FILE`` may come before it)."""
    args = list(argv)
    while args and args[0].startswith("-"):
        option = args.pop(0)
        if option == "--config" and args:
            args.pop(0)
    return bool(args) and args[0] == "run"


def hold_if_daemon(argv: Sequence[str]) -> None:
    if is_daemon(argv):
        hold()


def hold() -> None:
    """From now on, record SIGHUP and SIGTERM for :func:`take_pending`."""
    for sig in HELD:
        signal.signal(sig, _record)


def _record(signum: int, frame: FrameType | None) -> None:
    _pending.add(signum)


def take_pending() -> set[int]:
    """The signals recorded since the last call (held ones only)."""
    taken = set(_pending)
    _pending.difference_update(taken)
    return taken
