"""``vt-edge run``: the daemon."""

from __future__ import annotations

import argparse

from edge.cli.options import config_option


def add_parsers(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser("run", help="run the daemon")
    config_option(run, required=True)
    run.set_defaults(func=_cmd_run)


def _cmd_run(args: argparse.Namespace) -> int:
    from edge.runtime import forkserver

    forkserver.start()  # its imports beside the daemon's below (edge/runtime/forkserver.py)
    from edge.app import run

    return run(args.config)
