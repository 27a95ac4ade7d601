"""CPU and memory of the bench's processes, read from ``/proc`` (Linux): the cores each
process used during the load, how long the event loop's thread waited for a core, and the
memory of a process tree (the daemon and its compute processes)."""

from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path
from typing import Any

from edge.bench.proc import host_cpu_s, proc_cpu_s, process_tree


def thread_sched(tid: int) -> tuple[float, float, int]:
    """CPU time, run-queue wait (s) and involuntary switches of thread ``tid`` here."""
    run_ns, wait_ns, _ = Path(f"/proc/self/task/{tid}/schedstat").read_text().split()
    forced = 0
    for line in Path(f"/proc/self/task/{tid}/status").read_text().splitlines():
        if line.startswith("nonvoluntary_ctxt_switches"):
            forced = int(line.split(":")[1])
    return int(run_ns) / 1e9, int(wait_ns) / 1e9, forced


def cpu_snapshot(pids: dict[str, int]) -> dict[str, Any]:
    snap: dict[str, Any] = {"wall": time.monotonic(), "host": host_cpu_s(), "pids": pids}
    with contextlib.suppress(OSError):
        snap["loop"] = thread_sched(threading.get_native_id())
    for name, pid in pids.items():
        with contextlib.suppress(OSError):
            snap[name] = proc_cpu_s(pid)
    return snap


def cpu_times_since(snap: dict[str, Any]) -> dict[str, float]:
    """Cores used on average since ``snap``: the whole host and each process."""
    wall = time.monotonic() - snap["wall"]
    busy, _ = host_cpu_s()
    out = {"host_cores_busy": (busy - snap["host"][0]) / wall}
    for name, pid in snap["pids"].items():
        with contextlib.suppress(OSError, KeyError):
            out[name] = (proc_cpu_s(pid) - snap[name]) / wall
    with contextlib.suppress(OSError, KeyError):
        run, wait, forced = thread_sched(threading.get_native_id())
        # The event loop thread: its own CPU, and how long it sat runnable waiting for a core.
        out["loop_thread_cpu"] = (run - snap["loop"][0]) / wall
        out["loop_thread_runqueue_wait"] = (wait - snap["loop"][1]) / wall
        out["loop_thread_preempted_per_s"] = (forced - snap["loop"][2]) / wall
    return {k: round(v, 4) for k, v in out.items()}


def tree_memory_mb(pid: int) -> tuple[float, float, float, float]:
    """Over ``pid``'s process tree, in MiB: the sum of VmRSS (pages shared between the
    processes counted in each: an upper bound), of VmHWM (peaks), of Pss (shared pages
    split between their processes: the memory the tree really takes), and ``pid``'s own
    VmRSS."""
    rss = hwm = pss = own = 0.0
    for p in process_tree(pid):
        with contextlib.suppress(OSError):
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                key, _, value = line.partition(":")
                if key == "VmRSS":
                    rss += int(value.split()[0]) / 1024.0
                    if p == pid:
                        own = int(value.split()[0]) / 1024.0
                elif key == "VmHWM":
                    hwm += int(value.split()[0]) / 1024.0
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    pss += int(line.split()[1]) / 1024.0
    return rss, hwm, pss, own


def torch_mappings(pid: int) -> list[str]:
    """Mapped files of ``pid`` that belong to torch (libtorch*, .../torch/...)."""
    found = set()
    for line in Path(f"/proc/{pid}/maps").read_text().splitlines():
        parts = line.split(maxsplit=5)
        path = parts[5] if len(parts) == 6 else ""
        if "libtorch" in path or "/torch/" in path or "libc10" in path:
            found.add(path)
    return sorted(found)
