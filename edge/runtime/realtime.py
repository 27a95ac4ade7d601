"""Real-time scheduling for the two threads the stop goes through: the event loop's and the
Dynamixel bus thread.

Off by default (``[runtime] realtime = false``). On, both run ``SCHED_FIFO`` at
``realtime_priority`` on one CPU (``realtime_cpu``; -1: the last CPU the daemon may use), so a
busy host (the compute worker, a browser, other services) neither delays their wake-ups nor
moves them between cores: a FIFO thread preempts every ordinary one the moment it is
runnable. The daemon's other threads keep every CPU, that one included, for when the two
sleep (most of the time): they share the interpreter's lock with the loop, and one that
holds it must get a core at once to let it go. Confined to the other, busier CPUs they did
not: under the bench's load the sampler missed 7 and 2 ticks in 75 s that way (longest gaps
45 and 24 ms), 1 and 0 this way (15 and 12 ms). Threads the loop starts later would inherit
its one CPU; the executor's give it back (:func:`unpin_thread`). ``SCHED_RESET_ON_FORK``: a
process or thread started from these two does not inherit the priority.

It needs the right to: root, ``CAP_SYS_NICE``, or an ``RLIMIT_RTPRIO`` of at least the
priority (``vt-edge install-service`` writes ``LimitRTPRIO=`` and lets the unit make the
calls when the configuration asks for it). Where it is refused, the daemon logs why and
runs as before. A CPU of its own in the strict sense (no other process on it either) is the
host's business: boot with ``isolcpus=N`` (or ``systemd.cpu_affinity=``) and set
``realtime_cpu = N``. Linux only (``os.sched_setscheduler``).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Sequence

log = logging.getLogger(__name__)

# While the real-time threads hold their CPU: every CPU the daemon may use, for threads
# started meanwhile (unpin_thread).
_all_cpus: frozenset[int] | None = None


def unpin_thread() -> None:
    """In a thread just started (the daemon's executor's initializer): every CPU the daemon
    may use, not only the one it inherited from the real-time loop thread that started it."""
    cpus = _all_cpus
    if cpus is not None:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, cpus)


class Realtime:
    """SCHED_FIFO and one CPU for the threads ``threads()`` names (kernel thread IDs), from
    :meth:`enable` until :meth:`disable` (which the daemon's exit also runs)."""

    def __init__(self, priority: int, cpu: int, threads: Callable[[], Sequence[int]]) -> None:
        self.priority = priority
        self.cpu = cpu
        self._threads = threads
        # What enable() changed, to put back: (tid, policy, priority, CPUs).
        self._saved: list[tuple[int, int, int, set[int]]] = []
        self.held_cpu: int | None = None

    @property
    def active(self) -> bool:
        return bool(self._saved)

    def enable(self) -> bool:
        """Apply; False (and a warning saying why) where the host refuses it."""
        global _all_cpus
        if self.active:
            return True
        allowed = os.sched_getaffinity(0)
        cpu = max(allowed) if self.cpu < 0 else self.cpu
        if cpu not in allowed:
            log.warning("real-time scheduling not applied: realtime_cpu %d is not one this "
                        "process may use (%s)", cpu, sorted(allowed))
            return False
        tids = [t for t in self._threads() if t]
        try:
            for tid in tids:
                self._saved.append((tid, os.sched_getscheduler(tid),
                                    os.sched_getparam(tid).sched_priority,
                                    os.sched_getaffinity(tid)))
                os.sched_setscheduler(tid, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                                      os.sched_param(self.priority))
                os.sched_setaffinity(tid, {cpu})
        except OSError as exc:
            self.disable()
            log.warning("real-time scheduling not applied (%s): run as root, with "
                        "CAP_SYS_NICE or an RLIMIT_RTPRIO of at least %d (systemd: "
                        "LimitRTPRIO=, which `vt-edge install-service` writes when the "
                        "configuration sets realtime = true)", exc, self.priority)
            return False
        _all_cpus = frozenset(allowed)
        self.held_cpu = cpu
        log.info("real-time scheduling: threads %s at SCHED_FIFO %d on CPU %d", tids,
                 self.priority, cpu)
        return True

    def disable(self) -> None:
        """Back to how :meth:`enable` found the threads (those still running)."""
        global _all_cpus
        _all_cpus = None
        self.held_cpu = None
        for tid, policy, priority, cpus in reversed(self._saved):
            with contextlib.suppress(OSError):
                os.sched_setscheduler(tid, policy, os.sched_param(priority))
                os.sched_setaffinity(tid, cpus)
        self._saved = []


def policy_of(tid: int) -> tuple[str, int, set[int]]:
    """A thread's scheduling as ``(policy name, priority, CPUs)``, for logs and tests."""
    policy = os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK
    names = {os.SCHED_OTHER: "other", os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr",
             os.SCHED_BATCH: "batch", os.SCHED_IDLE: "idle"}
    return (names.get(policy, str(policy)), os.sched_getparam(tid).sched_priority,
            os.sched_getaffinity(tid))
