"""CPU time of processes and of the host, read from ``/proc`` (Linux).

For the benches (``vt-edge bench``, ``vt-train bench``): how busy the host was during a phase
and how much of that was their own work.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path


def clock_ticks() -> int:
    return os.sysconf("SC_CLK_TCK")


def process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants (e.g. the daemon, its forkserver and compute worker)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            # The command name may hold spaces and parentheses: the fields follow the last ')'.
            ppid = int(stat.read_text().rpartition(")")[2].split()[1])
            children.setdefault(ppid, []).append(int(stat.parent.name))
    tree, todo = [], [pid]
    while todo:
        p = todo.pop()
        tree.append(p)
        todo.extend(children.get(p, []))
    return tree


def proc_cpu_s(pid: int, reaped_children: bool = False) -> float:
    """User + system CPU seconds of ``pid`` (and of its children it has waited for)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = fields[11:15] if reaped_children else fields[11:13]
    return sum(int(v) for v in ticks) / clock_ticks()


def host_cpu_s() -> tuple[float, float]:
    """Busy and total CPU seconds of the whole host since boot (all cores)."""
    values = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = values[3] + values[4]
    return (sum(values) - idle) / clock_ticks(), sum(values) / clock_ticks()


def own_tree_cpu_s() -> float:
    """CPU seconds of this process and everything under it: its own, its reaped children's,
    and its live descendants' with their reaped children's (a compute worker is its
    forkserver's child, and the forkserver lives on)."""
    t = os.times()
    total = t.user + t.system + t.children_user + t.children_system
    for pid in process_tree(os.getpid())[1:]:
        with contextlib.suppress(OSError, ValueError, IndexError):
            total += proc_cpu_s(pid, reaped_children=True)
    return total
