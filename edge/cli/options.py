"""``--config``, taken before or after the subcommand (`vt-edge --config F episodes list` and
`vt-edge episodes list --config F`): every parser that reads one declares it with no default
of its own (argparse copies a subcommand's defaults over what the main parser read), and the
main parser fills in the command's default afterwards (edge.cli)."""

from __future__ import annotations

import argparse

CONFIG_HELP = "the configuration file (TOML); before or after the subcommand"


def config_option(parser: argparse.ArgumentParser, default: str | None = None, *,
                  required: bool = False, help: str = CONFIG_HELP) -> None:
    """``--config`` on ``parser``; ``default`` (or ``required``) applies when it is given
    neither there nor before the subcommand."""
    parser.add_argument("--config", default=argparse.SUPPRESS, help=help)
    parser.set_defaults(config_default=default, config_required=required)
