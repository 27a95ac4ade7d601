"""``vt-edge models``: the model directory the daemon loads."""

from __future__ import annotations

import argparse

from edge import SERVICE_NAME
from edge.core.errors import EdgeError

# Where `vt-edge models install` puts a model without --to or --config.
MODELS_DIR = "/opt/vtzero/models"


def add_parsers(sub: argparse._SubParsersAction) -> None:
    models = sub.add_parser("models", help="the model directory the daemon loads")
    modsub = models.add_subparsers(dest="models_command", required=True)
    minst = modsub.add_parser("install", help="verify a model directory and put it in place "
                              "(the one it replaces kept as DIR.previous)")
    minst.add_argument("src", help="a model directory (manifest.json, encoder, database)")
    where = minst.add_mutually_exclusive_group()
    where.add_argument("--to", default=None, help=f"default: {MODELS_DIR}")
    # --config here is the other place to install to, one of a group with --to: declared
    # by hand, as config_option does, with no default.
    where.add_argument("--config", default=argparse.SUPPRESS,
                       help="install to this configuration's [runtime] models_dir")
    minst.set_defaults(func=_cmd_models_install, config_default=None, config_required=False)


def _cmd_models_install(args: argparse.Namespace) -> int:
    from edge.ops.models import describe, install_models

    if args.config is not None:
        from edge.core.config import load_config

        if args.to is not None:
            raise EdgeError("models install: give --to DIR or --config FILE, not both")
        dest = load_config(args.config).runtime.models_dir
    else:
        dest = args.to or MODELS_DIR
    manifest, previous = install_models(args.src, dest)
    kept = f" (the one it replaced is {previous})" if previous else ""
    print(f"installed {args.src} as {dest}{kept}: {describe(manifest)}")
    print(f"reload the daemon: systemctl reload {SERVICE_NAME} (or kill -HUP its pid)")
    return 0
