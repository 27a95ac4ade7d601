"""``vt-edge bench``: the runtime's figures on the emulated robot, against their targets.

Writes ``OUT/results.json`` (one key per figure: p50, p99, max, n, unit, target, met; plus
``host``, ``run``, ``sections`` and ``notes``), ``OUT/results.md`` (rendered from it) and
``OUT/raw.json`` (every press); :mod:`edge.bench.results` holds the format. Phases, each
printed on stderr as it runs:

1. **runtime** (:mod:`.runtime`): the daemon's runtime in this process against the emulated
   robot, with and without load; presses alternate between the production controller and
   two comparison controllers (:mod:`.controllers`); helper processes in :mod:`.load`.
2. **label** (:mod:`.label`): trigger to label with the arm's real move time and a fake VLM
   at a fixed latency; how soon after the crop window the VLM request leaves.
3. **daemon** (:mod:`.daemon`): ``vt-edge run`` as a process: start to ``READY=1``, memory,
   torch never mapped.
4. **encode**, **retrieval** (:mod:`.encoder`): onnxruntime on one sequence; top-k on the
   shipped database and on 1,000,000 synthetic references against numpy brute force.

The training side adds its phases to the same files (``vt-train bench --merge-into
OUT/results.json``: the encoder in torch eager against onnxruntime, and training); ``make
bench`` runs both. How the figures read, and why a target is missed: :mod:`.report`.
``--baseline FILE`` (``make bench``: the results it replaces) adds a "Before and after"
table of every figure both runs have.

Timing is on ``time.monotonic`` (CLOCK_MONOTONIC), shared by every process on the host. This
package never imports torch or ``train``.
"""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

from edge.bench.report import FIGURES, WHY
from edge.bench.results import Results, progress
from edge.bench.settings import FULL, QUICK, Settings

__all__ = ["FIGURES", "FULL", "PHASES", "QUICK", "Settings", "bench", "run_bench"]

PHASES = ("runtime", "label", "daemon", "encode", "retrieval")


def run_bench(args: argparse.Namespace) -> int:
    s = QUICK if getattr(args, "quick", False) else FULL
    baseline = getattr(args, "baseline", None)
    return bench(Path(getattr(args, "out", "bench")), s,
                 baseline=Path(baseline) if baseline else None)


def bench(out: Path, s: Settings, phases: Sequence[str] = PHASES,
          baseline: Path | None = None) -> int:
    # Imported here, not above: the helper processes (python -m edge.bench.load) and
    # the compute worker (for the encoder load, load.encode_for) import this package and
    # need none of the phases.
    from edge.bench.daemon import daemon_phase
    from edge.bench.encoder import encode_phase, retrieval_phase
    from edge.bench.label import label_phase
    from edge.bench.runtime import runtime_phase

    results = Results.start("vt-edge bench" + (" --quick" if s.quick else ""), s.quick,
                            asdict(s))
    if baseline is not None:
        # Read before this run replaces it (make bench compares with the results it replaces).
        results.set_baseline(baseline)
    with tempfile.TemporaryDirectory(prefix="vtzero-bench-") as tmp_name:
        tmp = Path(tmp_name)
        measure = {
            "runtime": lambda: runtime_phase(s, tmp),
            "label": lambda: label_phase(s, tmp),
            "daemon": lambda: daemon_phase(s, tmp),
            "encode": lambda: encode_phase(s),
            "retrieval": lambda: retrieval_phase(s),
        }
        for phase in phases:
            results.run_phase(phase, measure[phase])
    results.order(FIGURES)
    md = results.write(out, WHY)
    print(md)
    progress(f"wrote {out / 'results.json'}, {out / 'results.md'}, {out / 'raw.json'} "
             f"in {results.run['duration_s']:.0f} s")
    return 0
