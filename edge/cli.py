"""``vt-edge``: the on-robot command line."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from dataclasses import replace

from edge import __version__
from edge.errors import EdgeError
from edge.logs import setup_logging

log = logging.getLogger(__name__)


def _cmd_sim_record(args: argparse.Namespace) -> int:
    from edge.sim.press import PressParams
    from edge.sim.record import record_dataset

    def progress(done: int, total: int) -> None:
        if done == total or done % max(1, total // 20) == 0:
            print(f"\r  {done}/{total} presses", end="", file=sys.stderr, flush=True)

    params = replace(PressParams(), x_th=args.x_th, reaction_latency_s=args.latency_ms / 1e3)
    index = record_dataset(args.dataset, args.presses, args.out, seed=args.seed,
                           params=params, workers=args.workers,
                           progress=None if args.quiet else progress)
    if not args.quiet:
        print(file=sys.stderr)
    n = len(index["classes"]) * args.presses
    print(f"wrote {n} presses of {len(index['classes'])} classes ({args.dataset}) to {args.out}")
    if index["no_contact"]:
        print(f"warning: no contact in {len(index['no_contact'])} presses: "
              + ", ".join(index["no_contact"][:10]))
    return 0


def _cmd_sim_press(args: argparse.Namespace) -> int:
    from edge.sim.press import PressParams
    from edge.sim.summary import print_press_table

    params = replace(PressParams(), x_th=args.x_th, reaction_latency_s=args.latency_ms / 1e3)
    print_press_table(args.objects, seed=args.seed, params=params)
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from edge.sim.press import PressParams
    from edge.sim.summary import DEMO_OBJECTS, print_press_table

    print("vtzero demo: simulated presses (press physics, threshold stop, crop)\n")
    print_press_table(list(DEMO_OBJECTS), seed=args.seed, params=PressParams())
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vt-edge", description=__doc__)
    parser.add_argument("--version", action="version", version=f"vtzero {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="the main job: presses on the simulated robot")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_cmd_demo)

    sim = sub.add_parser("sim", help="the simulated robot")
    simsub = sim.add_subparsers(dest="sim_command", required=True)

    rec = simsub.add_parser("record", help="record a simulated dataset of presses")
    rec.add_argument("--dataset", required=True, choices=["reference", "foodreplica", "cube"])
    rec.add_argument("--presses", type=int, default=10, help="presses per class")
    rec.add_argument("--out", required=True, help="output directory")
    rec.add_argument("--seed", type=int, default=0)
    rec.add_argument("--workers", type=int, default=None, help="processes (default: cores)")
    rec.add_argument("--x-th", type=float, default=0.004, help="stop threshold")
    rec.add_argument("--latency-ms", type=float, default=2.0, help="controller reaction")
    rec.add_argument("-q", "--quiet", action="store_true")
    rec.set_defaults(func=_cmd_sim_record)

    press = simsub.add_parser("press", help="press objects once and print a summary")
    press.add_argument("objects", nargs="+", help="object class names")
    press.add_argument("--seed", type=int, default=0)
    press.add_argument("--x-th", type=float, default=0.004)
    press.add_argument("--latency-ms", type=float, default=2.0)
    press.set_defaults(func=_cmd_sim_press)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(logging.DEBUG if args.verbose else logging.INFO)
    try:
        return int(args.func(args) or 0)
    except EdgeError as exc:
        log.error("%s", exc)
        return 2
    except KeyboardInterrupt:
        return 130
