"""``vt-edge bench``: the runtime measured on the emulated robot."""

from __future__ import annotations

import argparse


def add_parsers(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="measure the runtime on the emulated robot")
    bench.add_argument("--out", default="bench", help="directory for results.json/.md")
    bench.add_argument("--baseline", default=None,
                       help="an earlier results.json: results.md compares every figure")
    bench.add_argument("--quick", action="store_true",
                       help="short runs (a smoke test; figures are not representative)")
    bench.set_defaults(func=_cmd_bench)


def _cmd_bench(args: argparse.Namespace) -> int:
    from edge.bench import run_bench

    return run_bench(args)
