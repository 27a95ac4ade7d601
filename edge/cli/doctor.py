"""``vt-edge doctor``: every part of the setup checked before the first press."""

from __future__ import annotations

import argparse

from edge.cli.options import config_option


def add_parsers(sub: argparse._SubParsersAction) -> None:
    doc = sub.add_parser("doctor", help="check every part of the setup before the first "
                         "press, without moving the arm (exit 1 on any FAIL)")
    config_option(doc, required=True)
    doc.add_argument("--json", action="store_true", help="the checks as JSON")
    doc.set_defaults(func=_cmd_doctor)


def _cmd_doctor(args: argparse.Namespace) -> int:
    from edge.ops.doctor import main

    return main(args.config, args.json)
