"""Real-time scheduling of the loop and bus threads ([runtime] realtime)."""

from __future__ import annotations

import logging
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import pytest

from edge.core.config import config_from_dict
from edge.core.errors import ConfigError
from edge.runtime import realtime
from edge.runtime.realtime import Realtime, policy_of, unpin_thread


class _Parked:
    """Threads that wait until released: stand-ins for the loop and bus threads."""

    def __init__(self, n: int) -> None:
        self.release = threading.Event()
        ready = [threading.Event() for _ in range(n)]
        self.tids: list[int] = [0] * n

        def park(i: int) -> None:
            self.tids[i] = threading.get_native_id()
            ready[i].set()
            self.release.wait()

        self.threads = [threading.Thread(target=park, args=(i,), daemon=True)
                        for i in range(n)]
        for t in self.threads:
            t.start()
        for r in ready:
            r.wait(5)

    def close(self) -> None:
        self.release.set()
        for t in self.threads:
            t.join(5)


def test_fifo_on_one_cpu_and_back():
    parked = _Parked(2)
    rt = Realtime(15, -1, lambda: parked.tids)
    before = [policy_of(t) for t in parked.tids]
    last_cpu = max(os.sched_getaffinity(0))
    try:
        if not rt.enable():
            pytest.skip("this host refuses SCHED_FIFO to the tests (no CAP_SYS_NICE or "
                        "RLIMIT_RTPRIO)")
        cpu = rt.held_cpu
        assert cpu == last_cpu
        for tid in parked.tids:
            assert policy_of(tid) == ("fifo", 15, {cpu})
        everywhere = os.sched_getaffinity(0)  # the daemon's other threads keep every CPU
        assert cpu in everywhere
        # A thread the executor starts from a pinned thread gets every CPU back.
        with ThreadPoolExecutor(1, initializer=unpin_thread) as pool:
            os.sched_setaffinity(0, {cpu})  # as the loop's thread, pinned, would start it
            try:
                assert pool.submit(os.sched_getaffinity, 0).result() == everywhere
            finally:
                os.sched_setaffinity(0, everywhere)
        print(f"\nthreads {parked.tids}: SCHED_FIFO 15 on CPU {cpu}")
    finally:
        rt.disable()
        after = [policy_of(t) for t in parked.tids]
        parked.close()
    assert after == before
    assert realtime._all_cpus is None


def test_refused_leaves_everything_as_it_was(monkeypatch, caplog):
    parked = _Parked(1)
    before = policy_of(parked.tids[0])

    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    rt = Realtime(20, -1, lambda: parked.tids)
    try:
        with caplog.at_level(logging.WARNING, logger="edge.runtime.realtime"):
            assert not rt.enable()
        assert not rt.active and rt.held_cpu is None
        assert policy_of(parked.tids[0]) == before
        assert "LimitRTPRIO" in caplog.text and "Operation not permitted" in caplog.text
    finally:
        parked.close()


def test_a_cpu_the_daemon_may_not_use_is_refused(caplog):
    rt = Realtime(20, max(os.sched_getaffinity(0)) + 1, lambda: [threading.get_native_id()])
    with caplog.at_level(logging.WARNING, logger="edge.runtime.realtime"):
        assert not rt.enable()
    assert "realtime_cpu" in caplog.text


@pytest.mark.parametrize(("key", "value", "says"), [
    ("realtime_priority", 0, "1..99"),
    ("realtime_priority", 100, "1..99"),
    ("realtime_cpu", -2, "CPU number"),
    ("realtime", "yes", "true or false"),
])
def test_config_errors_name_the_field(key, value, says):
    with pytest.raises(ConfigError, match=f"runtime.{key}.*{says}"):
        config_from_dict({"runtime": {key: value}})
