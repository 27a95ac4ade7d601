"""Where the bus's operations run: one owner, one operation at a time, stops first.

The SDK is blocking and not thread-safe, so exactly one thread (``dxl-bus``) ever calls it:
:class:`ThreadExecutor`. The asyncio side submits operations and awaits futures that the
thread resolves with ``loop.call_soon_threadsafe``; no SDK call ever runs on the event loop.
The thread sleeps in ``select()`` on an eventfd that every submission writes to. Operations
run one at a time in submission order, except urgent ones (stops): they go to a queue the
thread empties before taking anything else, so a stop waits at most for the one transaction
already on the wire (the bus is half duplex: a transaction in flight cannot be interrupted
without colliding with the replies).

The simulator runs the same bus on its virtual clock with an executor of its own
(``edge.sim.virtual.VirtualExecutor``); both satisfy :class:`Executor`.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import os
import select
import threading
from collections.abc import Callable
from typing import Any, Protocol

from edge.core.errors import EdgeError

_log = logging.getLogger(__name__)

THREAD_JOIN_TIMEOUT_S = 2.0
# How long the event loop waits, when it hands a stop over, for the stop's packet to be on
# the wire (normally the hand-over plus any transaction already in flight: tens of
# microseconds to a millisecond). Past it the loop goes on and the stop still goes out.
STOP_HANDOVER_MAX_S = 0.003


class Executor(Protocol):
    """Runs the bus's operations, one at a time, urgent ones first."""

    def start(self) -> None:
        """Ready to take operations."""

    async def submit(self, label: str, fn: Callable[[], Any], urgent: bool = False) -> Any:
        """Run ``fn`` on the owner once the ones before it (urgent first) have run; its value
        or exception."""

    async def stop(self, last: Callable[[], None]) -> None:
        """Run what is queued, then ``last`` (releasing the port), on the owner; then end."""

    @property
    def busy(self) -> bool:
        """An operation is running now (a stop submitted now waits for it)."""

    @property
    def thread_id(self) -> int | None:
        """``threading.get_ident()`` of the owner thread; None without one."""

    @property
    def native_thread_id(self) -> int | None:
        """The kernel's thread ID of the owner thread; None without one."""

    def on_wire(self) -> None:
        """Called by the owner when the running operation's packet is written."""


class _OnWire:
    """Set once, by the owner, when an operation's packet is written (or it ended); waited
    for once, by the thread that submitted it.

    A bare lock held until then, not a ``threading.Event``: the waiter goes from the
    eventfd write that wakes the owner straight into a blocking acquire, which releases the
    interpreter's lock for the owner a few microseconds sooner than the Python of
    ``Condition.wait`` would.
    """

    __slots__ = ("_done", "_lock")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()
        self._done = False

    def set(self) -> None:
        # Only ever called on the owner thread: no race on _done.
        if not self._done:
            self._done = True
            self._lock.release()

    def wait(self, timeout_s: float) -> None:
        self._lock.acquire(timeout=timeout_s)


class _Op:
    """One operation for the bus thread, and the future its caller awaits."""

    __slots__ = ("abandoned", "fn", "future", "label", "loop", "must_run", "on_wire")

    def __init__(self, label: str, fn: Callable[[], Any], loop: asyncio.AbstractEventLoop,
                 future: asyncio.Future[Any], must_run: bool) -> None:
        self.label, self.fn, self.loop, self.future = label, fn, loop, future
        self.must_run = must_run
        self.abandoned = False
        # Set once the operation's first packet is written (or it ended): what a caller
        # handing over a stop waits for.
        self.on_wire = _OnWire()

    def on_done(self, future: asyncio.Future[Any]) -> None:
        # Runs on the loop: a caller that gave up on a queued read needs no bus time. A stop
        # is sent even then.
        if future.cancelled() and not self.must_run:
            self.abandoned = True

    def settle(self, value: Any, exc: BaseException | None) -> None:
        try:
            self.loop.call_soon_threadsafe(_settle, self.future, value, exc)
        except RuntimeError:
            pass  # the loop is closed: nobody is waiting any more


def _settle(future: asyncio.Future[Any], value: Any, exc: BaseException | None) -> None:
    if future.done():
        return
    if exc is not None:
        future.set_exception(exc)
    else:
        future.set_result(value)


class ThreadExecutor:
    """The owner thread: operations run on it in order, urgent ones first."""

    def __init__(self, name: str = "dxl-bus") -> None:
        self._name = name
        self._lock = threading.Lock()
        self._urgent: collections.deque[_Op] = collections.deque()
        self._normal: collections.deque[_Op] = collections.deque()
        self._exit = False
        self._last: Callable[[], None] | None = None
        self._thread: threading.Thread | None = None
        # Written by every submission; the thread sleeps in select() on it.
        self._wake_fd = -1
        self._running: _Op | None = None

    @property
    def busy(self) -> bool:
        return self._running is not None

    @property
    def thread_id(self) -> int | None:
        """``threading.get_ident()`` of the owner thread (the only one calling the SDK)."""
        return self._thread.ident if self._thread is not None else None

    @property
    def native_thread_id(self) -> int | None:
        """The kernel's thread ID of the owner thread (for its scheduling policy and CPU)."""
        return self._thread.native_id if self._thread is not None else None

    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError(f"{self._name} thread is already running")
        self._exit = False
        self._last = None
        self._wake_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()

    async def submit(self, label: str, fn: Callable[[], Any], urgent: bool = False) -> Any:
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Any] = loop.create_future()
        op = _Op(label, fn, loop, future, must_run=urgent)
        future.add_done_callback(op.on_done)
        with self._lock:
            if self._thread is None or self._exit:
                raise RuntimeError(f"{self._name} thread is not running: {label} refused")
            (self._urgent if urgent else self._normal).append(op)
        os.eventfd_write(self._wake_fd, 1)
        if urgent:
            # Sleeping here hands the bus thread the GIL (and, on a busy host, this core)
            # at once; going on would leave it waiting until the loop next blocks, up to
            # the interpreter's 5 ms switch interval under load. Bounded: a stop behind a
            # transaction that hangs does not hold up the loop.
            op.on_wire.wait(STOP_HANDOVER_MAX_S)
        return await future

    def on_wire(self) -> None:
        op = self._running
        if op is not None:
            op.on_wire.set()

    async def stop(self, last: Callable[[], None]) -> None:
        thread = self._thread
        if thread is None:
            return
        with self._lock:
            self._exit = True
            self._last = last
        os.eventfd_write(self._wake_fd, 1)
        await asyncio.to_thread(thread.join, THREAD_JOIN_TIMEOUT_S)
        if thread.is_alive():
            _log.error("%s thread did not stop within %.1f s", self._name,
                       THREAD_JOIN_TIMEOUT_S)
        else:
            os.close(self._wake_fd)
            self._wake_fd = -1
        self._thread = None

    def _next_op(self) -> _Op | None:
        """The next operation (urgent first), sleeping in select() until there is one; None
        when the thread is to end."""
        while True:
            with self._lock:
                if self._urgent:
                    return self._urgent.popleft()
                if self._normal:
                    return self._normal.popleft()
                if self._exit:
                    return None
            # A submission after the check above has written the eventfd: select returns.
            select.select([self._wake_fd], [], [])
            with contextlib.suppress(BlockingIOError):
                os.eventfd_read(self._wake_fd)

    def _run(self) -> None:
        try:
            while (op := self._next_op()) is not None:
                if op.abandoned:
                    op.on_wire.set()
                    continue
                value, exc = None, None
                self._running = op
                try:
                    value = op.fn()
                except EdgeError as e:
                    exc = e
                except Exception as e:
                    _log.exception("unexpected error in bus operation %s", op.label)
                    exc = e
                finally:
                    self._running = None
                    op.on_wire.set()
                op.settle(value, exc)
        finally:
            if self._last is not None:
                self._last()
