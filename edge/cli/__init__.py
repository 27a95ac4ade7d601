"""``vt-edge``: the on-robot command line."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence

from edge import __version__
from edge.cli import (
    bench,
    calibrate,
    daemon,
    dataset,
    demo,
    doctor,
    episodes,
    install,
    models,
    pose,
    sim,
    teach,
)
from edge.cli.options import CONFIG_HELP
from edge.core.errors import EdgeError
from edge.core.logs import setup_logging

log = logging.getLogger(__name__)

# Each adds its commands' parsers, beside their handlers; in the order of `vt-edge --help`.
COMMAND_GROUPS = (demo, doctor, daemon, dataset, pose, models, calibrate, bench, episodes,
                  teach, install, sim)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vt-edge", description=__doc__)
    parser.add_argument("--version", action="version", version=f"vtzero {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--config", default=argparse.SUPPRESS, help=CONFIG_HELP)
    sub = parser.add_subparsers(dest="command", required=True)
    for group in COMMAND_GROUPS:
        group.add_parsers(sub)
    return parser


def _resolve_config(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``args.config``: as given (before or after the subcommand), else the command's
    default (edge.cli.options); an error for a command that needs one and got none, or
    takes none."""
    if not hasattr(args, "config_required"):
        if hasattr(args, "config"):
            parser.error(f"{_command_name(args)} takes no --config")
        return
    if not hasattr(args, "config"):
        if args.config_required:
            parser.error(f"{_command_name(args)}: the following arguments are required: "
                         "--config")
        args.config = args.config_default


def _command_name(args: argparse.Namespace) -> str:
    words = [args.command, getattr(args, f"{args.command}_command", None) or ""]
    return "vt-edge " + " ".join(w for w in words if w)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _resolve_config(parser, args)
    setup_logging(logging.DEBUG if args.verbose else None)
    try:
        return int(args.func(args) or 0)
    except EdgeError as exc:
        # (A KeyError's str() quotes its message.)
        log.error("%s", exc.args[0] if isinstance(exc, KeyError) and exc.args else exc)
        return 2
    except OSError as exc:
        # A file or device the command writes or opens (install-udev, install-service,
        # models install...): one line, not a traceback.
        hint = " (it needs root: run it with sudo)" if isinstance(exc, PermissionError) else ""
        log.error("%s%s", exc, hint)
        return 2
    except KeyboardInterrupt:
        return 130
