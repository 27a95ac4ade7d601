"""The daemon's CPU work in one separate process: image decoding and re-encoding for the VLM,
the press analysis (crop, encoder, top-k, familiarity, the episode's arrays), and teaching a
press (the encoder again).

Why a process and not a thread: the event loop runs the 125 Hz sampler and sends the stop,
and a worker thread competes with it for the GIL. Pillow's decoders and encoders hold the
GIL for milliseconds at a time, and a Python loop around onnxruntime takes it back within
the 5 ms switch interval; measured with the bench's load, both showed up as 3-5 ms stalls
of the sampler (p99). In a process of its own they cost the loop only the pickling of
arguments and results. It also keeps a decoder crash on a hostile upload out of the
daemon: the worker dies, the request gets an error, the next call starts a new worker.

One worker (a robot computer has few cores, and one press is analysed at a time), forked
from a ``forkserver`` (never ``fork`` from the threaded daemon) that has imported this
module, so starting one costs a fork, not the imports. The worker ignores SIGINT and
SIGTERM: the daemon decides when it ends (a Ctrl-C in a terminal, or systemd signalling the
whole control group, must not kill an analysis the daemon is about to store).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import logging
import math
import os
import select
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from edge.core import preprocess, recording
from edge.core.config import RuntimeConfig
from edge.core.errors import ComputeError, ModelError
from edge.core.model import Model, ModelRef, load_model, nearest_code
from edge.runtime import forkserver
from edge.runtime.references import (
    Lookup,
    Overlay,
    ReferenceStore,
    Source,
    TaughtReference,
    signature,
)

log = logging.getLogger(__name__)

T = TypeVar("T")

TOPK = 3
# The worker's niceness relative to the daemon (raising it needs no privilege).
WORKER_NICE = 10
# How often a worker without pidfd support checks that the daemon still runs.
WATCH_PERIOD_S = 1.0
# Starting the worker (a fork of the preloaded server) and its first call.
START_TIMEOUT_S = 30.0
# Ending it: its current call finishes, then the pool is joined; past this it is killed.
STOP_TIMEOUT_S = 5.0


class ComputeWorker:
    """One worker process; :meth:`run` awaits a module-level function run there."""

    def __init__(self) -> None:
        self._pool: ProcessPoolExecutor | None = None
        self.restarts = 0

    async def __aenter__(self) -> ComputeWorker:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def start(self) -> None:
        """Start the worker and wait until it answers (so the first press pays nothing)."""
        self._pool = self._new_pool()
        await asyncio.wait_for(self.run(_ready), START_TIMEOUT_S)

    def _new_pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=1, mp_context=forkserver.context(),
                                   initializer=_init_worker,
                                   initargs=(os.getpid(),))

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in the worker; its :class:`EdgeError` arrives as raised there."""
        if self._pool is None:
            raise ComputeError("the compute worker is not running")
        pool = self._pool
        try:
            return await asyncio.get_running_loop().run_in_executor(pool, fn, *args)
        except BrokenProcessPool as exc:
            if self._pool is pool:  # the first caller to notice replaces it
                self.restarts += 1
                log.error("compute worker died during %s (%s); starting a new one",
                          getattr(fn, "__name__", fn), exc)
                pool.shutdown(wait=False, cancel_futures=True)
                self._pool = self._new_pool()
            raise ComputeError(
                f"the compute worker died during {getattr(fn, '__name__', fn)} "
                "(a crash or out of memory); a new one is started for the next call") from None

    async def stop(self) -> None:
        """End the worker: calls not begun are cancelled, the current one finishes, and the
        pool is joined (off the loop), or its process killed after ``STOP_TIMEOUT_S``.

        Joined, not left to end on its own: the pool's manager thread, still closing its
        wake-up pipe as the interpreter's exit hook wrote to that pipe, printed an
        "OSError: [Errno 9] Bad file descriptor" traceback after a clean exit (a race in
        Python 3.11's concurrent.futures, seen on a loaded host).
        """
        pool, self._pool = self._pool, None
        if pool is None:
            return
        pid = _pid_of(pool)
        joining = asyncio.ensure_future(
            asyncio.to_thread(pool.shutdown, wait=True, cancel_futures=True))
        try:
            await asyncio.wait_for(asyncio.shield(joining), STOP_TIMEOUT_S)
        except TimeoutError:
            log.warning("compute worker still busy %.1f s after it was asked to end: killed",
                        STOP_TIMEOUT_S)
            if pid is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            await joining

    def pid(self) -> int | None:
        """The worker's process ID once started (for CPU and memory accounting)."""
        return _pid_of(self._pool)


def _pid_of(pool: ProcessPoolExecutor | None) -> int | None:
    procs = getattr(pool, "_processes", None) or {}
    return next(iter(procs), None)


# --------------------------------------------------------------------------------------
# In the worker process


def _init_worker(daemon_pid: int) -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    # Behind the daemon for a CPU: its loop reads the sensor and sends the stop.
    try:
        os.nice(WORKER_NICE)
    except OSError as exc:
        log.warning("compute worker: cannot lower its priority (nice %+d): %s",
                    WORKER_NICE, exc)
    # The worker holds both ends of its task queue and keeps the forkserver alive, so
    # neither notices the daemon die: after a ``kill -9`` they would run forever.
    threading.Thread(target=_exit_with, args=(daemon_pid,), name="exit-with-daemon",
                     daemon=True).start()


def _exit_with(pid: int) -> None:
    """Exit the moment process ``pid`` does (a pidfd turns readable), else poll for it."""
    try:
        fd = os.pidfd_open(pid)
    except OSError:  # gone already, or a kernel before 5.3
        while _alive(pid):
            time.sleep(WATCH_PERIOD_S)
    else:
        select.select([fd], [], [])
    os._exit(0)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _ready() -> bool:
    return True


_model: Model | None = None
# The model's database merged with the taught references, and what it was made from: the
# model, the references' directory and its index's signature (a change on disk, by this
# process's teaching or anyone's, makes the next press merge again).
_lookup: Lookup | None = None
_lookup_of: tuple[Model, Any, Any] | None = None


def model_for(ref: ModelRef) -> Model:
    """The daemon's model, loaded here once per model (a reload gives a new digest)."""
    global _model
    if _model is None or _model.directory != ref.directory or _model.digest != ref.digest:
        _model = _loaded(ref)
    return _model


def lookup_for(ref: ModelRef) -> Lookup:
    """What a press is looked up in: the model's database and the references taught beside
    it (``ref.references``), merged here again whenever the references' index changed."""
    global _lookup, _lookup_of
    model = model_for(ref)
    key = (model, ref.references, signature(ref.references))
    if _lookup is None or _lookup_of != key:
        _lookup, _lookup_of = _merged(model, ref), key
    return _lookup


def _merged(model: Model, ref: ModelRef) -> Lookup:
    t = time.perf_counter()
    overlay = (Overlay(None, "") if ref.references is None
               else ReferenceStore(ref.references).load(model.digest))
    lookup = overlay.lookup(model)
    log.info("reference database: %d references of %d classes (%d taught) merged and ranked "
             "in %.0f ms", len(lookup.database), len(lookup.database.classes),
             len(lookup.overlay.current), (time.perf_counter() - t) * 1e3)
    return lookup


def _loaded(ref: ModelRef) -> Model:
    model = load_model(ref.directory)
    if model.digest != ref.digest:
        raise ModelError(
            f"{ref.directory}: the model files changed since the daemon loaded them; send "
            "SIGHUP (systemctl reload vtzero-edge) to load the new ones")
    return model


def warm_up(ref: ModelRef) -> None:
    """Load the model and the taught references here (refusing malformed ones, naming the
    file and field) and run the model once (onnxruntime allocates on its first run)."""
    model = model_for(ref)
    lookup_for(ref)
    model.encode(np.zeros((model.window.n_steps, model.encoder.channels), np.float32))


def reload_model(ref: ModelRef) -> None:
    """Load the model again from its files, every one re-hashed against the manifest even
    where the manifest is unchanged (one byte flipped in the encoder leaves its digest as it
    was), and the taught references with it, run it once, and make it the one that answers.
    :class:`ModelError` naming the file (and field) if one does not match or is malformed:
    the running model and references stay."""
    global _model, _lookup, _lookup_of
    model = _loaded(ref)
    lookup = _merged(model, ref)
    model.encode(np.zeros((model.window.n_steps, model.encoder.channels), np.float32))
    _model, _lookup = model, lookup
    _lookup_of = (model, ref.references, signature(ref.references))


@dataclass(frozen=True)
class Analysis:
    """What the compute process makes of one press's model window: what the VLM question
    needs, and the model's input and output for the episode."""

    z: list[float]
    code: int
    topk: list[tuple[str, float]]  # nearest distinct reference classes, nearest first
    description: str
    model_io_npz: bytes  # the crop, the model input and the embedding
    # How far the press lies from the references, as a percentile of the database's own
    # leave-one-out figures (edge.core.model.Familiarity: 0 = nearer than every reference
    # to the others, 100 = farther than all); None: a database of one class or one press.
    familiarity: float | None = None
    # At or past the configured percentile ([runtime] unfamiliar_percentile).
    unfamiliar: bool = False
    # The taught references' index the press was looked up with (its sha256; "": none).
    references: str = ""
    # The share of the database's subsampling offsets whose embedding of this press has the
    # same nearest class as the first offset's (1.0: the offsets agree; lower: the press's
    # nearest class depends on which frames are read, a second press is worth its time);
    # None where it was not asked for (a recognition of one press).
    agreement: float | None = None


def analyse_press(ref: ModelRef, rec: recording.Recording,
                  unfamiliar_percentile: float = RuntimeConfig.unfamiliar_percentile,
                  agreement: bool = True) -> Analysis:
    """The crop (the model's own window), the encoder, the nearest references (the model's
    and those taught beside it), the familiarity and the model's input and output serialised:
    the work between the window and the VLM question, kept to that (the photo is prepared
    while the press runs, the press serialised, with ``recording.to_bytes``, after the
    question has left). With ``agreement``, also whether the other subsampling offsets find
    the same nearest class (what a recognition that may press again decides by); a
    recognition of one press leaves it out: it was over half of this work (0.58 of 1.02 ms
    on the shipped model), between the window and the question."""
    model = model_for(ref)
    lookup = lookup_for(ref)
    window = _window(model, rec)
    x = preprocess.subsample(window, 0, model.window)
    z, code = model.encode(x)
    z = np.asarray(z).reshape(-1)
    code = int(np.asarray(code).reshape(-1)[0])
    topk = lookup.database.topk(z, TOPK)
    share = None
    if agreement:
        # The other offsets' nearest classes: do the frames read decide?
        nearest = [lookup.database.topk(zo, 1)[0][0]
                   for zo in _offset_embeddings(model, window, lookup.database.offsets[1:])]
        share = (1 + sum(label == topk[0][0] for label in nearest)) / (1 + len(nearest))
    buf = io.BytesIO()
    np.savez(buf, window=window, x=x, z=z, code=np.asarray(code))
    return _analysis(lookup, z, x.mean(axis=0), code, topk, buf.getvalue(),
                     unfamiliar_percentile, share)


def _window(model: Model, rec: recording.Recording) -> np.ndarray:
    """The press's model window (the crop around its stop, in the model's units)."""
    units = preprocess.recording_units(rec)
    return preprocess.crop(rec.recv_time, units, rec.t_stop, model.window)


def _offset_embeddings(model: Model, window: np.ndarray, offsets: list[int]
                       ) -> list[np.ndarray]:
    return [np.asarray(model.encode(preprocess.subsample(window, o, model.window))[0])
            .reshape(-1) for o in offsets]


def _analysis(lookup: Lookup, z: np.ndarray, feature: np.ndarray, code: int,
              topk: list[tuple[str, float]], model_io: bytes, unfamiliar_percentile: float,
              agreement: float | None) -> Analysis:
    familiarity = lookup.familiarity.percentile(z, feature)
    return Analysis([float(v) for v in z], code, [(label, float(d)) for label, d in topk],
                    lookup.database.describe([label for label, _ in topk]), model_io,
                    familiarity,
                    familiarity is not None and familiarity >= unfamiliar_percentile,
                    lookup.overlay.digest, agreement)


# How a recognition's presses are fused into one top-k ([runtime] fusion).
FUSIONS = ("votes", "mean")


def fuse_presses(ref: ModelRef, recs: list[recording.Recording], fusion: str,
                 unfamiliar_percentile: float = RuntimeConfig.unfamiliar_percentile
                 ) -> Analysis:
    """Several presses of one object as one analysis, every press read at each of the
    database's subsampling offsets (as its references were cut):

    - ``votes``: each (press, offset) embedding's top-k classes vote, the nearest
      ``TOPK`` points, the next one fewer (a Borda count); classes ranked by points, ties
      by their nearest distance; each class's distance is its nearest over the presses.
    - ``mean``: the mean of those embeddings, looked up once.

    ``z`` and ``code`` are the mean embedding's (its nearest codebook entry); ``agreement``
    the share of the (press, offset) embeddings whose nearest class is the fused first. The
    familiarity is the mean of the presses' features (or, on a database without them, the
    mean embedding's), with either fusion."""
    if fusion not in FUSIONS:
        raise ValueError(f"fusion {fusion!r}: one of {', '.join(FUSIONS)}")
    if not recs:
        raise ValueError("no presses to fuse")
    model = model_for(ref)
    lookup = lookup_for(ref)
    db = lookup.database
    windows = [_window(model, rec) for rec in recs]
    zs = np.stack([z for w in windows for z in _offset_embeddings(model, w, db.offsets)])
    mean = zs.mean(axis=0)
    code = int(np.asarray(nearest_code(mean[None, :], db.codebook)).reshape(-1)[0])
    ranked = [db.topk(z, TOPK) for z in zs]
    if fusion == "mean":
        topk = db.topk(mean, TOPK)
    else:
        points: dict[str, int] = {}
        nearest: dict[str, float] = {}
        for each in ranked:
            for rank, (label, d) in enumerate(each):
                points[label] = points.get(label, 0) + TOPK - rank
                nearest[label] = min(nearest.get(label, math.inf), d)
        order = sorted(points, key=lambda label: (-points[label], nearest[label]))
        topk = [(label, nearest[label]) for label in order[:TOPK]]
    agreement = sum(each[0][0] == topk[0][0] for each in ranked) / len(ranked)
    buf = io.BytesIO()
    np.savez(buf, windows=np.stack(windows), z=zs, mean=mean, code=np.asarray(code))
    feature = np.mean([preprocess.subsample(w, 0, model.window).mean(axis=0) for w in windows],
                      axis=0)
    return _analysis(lookup, mean, feature, code, topk, buf.getvalue(), unfamiliar_percentile,
                     agreement)


def teach_press(ref: ModelRef, rec: recording.Recording, label: str,
                description: str | None, source: Source, episode: str | None = None,
                append: bool = False) -> TaughtReference:
    """Teach the press ``rec`` as ``label`` into the references beside the model
    (:meth:`ReferenceStore.add`, embedded by the model loaded here); the next press is
    looked up with it. Positional, as :meth:`ComputeWorker.run` passes arguments."""
    if ref.references is None:
        raise ModelError(f"{ref.directory}: no directory for taught references is configured")
    return ReferenceStore(ref.references).add(model_for(ref), rec, label, description,
                                              source=source, episode=episode, append=append)


__all__ = ["FUSIONS", "Analysis", "ComputeError", "ComputeWorker", "analyse_press",
           "fuse_presses", "lookup_for", "model_for", "reload_model", "teach_press", "warm_up"]
