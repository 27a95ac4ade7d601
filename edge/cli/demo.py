"""``vt-edge demo``: recognitions on the emulated robot."""

from __future__ import annotations

import argparse

from edge.cli.options import config_option


def add_parsers(sub: argparse._SubParsersAction) -> None:
    demo = sub.add_parser("demo", help="the main job: recognitions on the emulated robot")
    config_option(demo, "configs/sim.toml")
    demo.set_defaults(func=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    from edge.lab.demo import run_demo

    return run_demo(args.config)
