"""``vt-edge install-service`` and ``vt-edge install-udev``: the systemd unit and the udev
rules, printed or installed."""

from __future__ import annotations

import argparse

from edge.cli.options import config_option


def add_parsers(sub: argparse._SubParsersAction) -> None:
    svc = sub.add_parser("install-service", help="print (or install) the systemd unit")
    config_option(svc, "/etc/vtzero/robot.toml")
    svc.add_argument("--user", default="vtzero", help="the system user the daemon runs as")
    svc.add_argument("--create-user", action="store_true",
                     help="create the user (useradd --system) and the device groups the "
                          "configuration needs where missing (as root)")
    what = svc.add_mutually_exclusive_group()
    what.add_argument("--print", action="store_true",
                      help="print the unit (the default), with a warning for each thing it "
                           "could not see or use")
    what.add_argument("--install", action="store_true",
                      help="write /etc/systemd/system/vtzero-edge.service (refused while the "
                           "unit could not start: a path it could not see, a missing user or "
                           "group)")
    svc.set_defaults(func=_cmd_install_service)

    udev = sub.add_parser("install-udev", help="print (or install) the udev rules: U2D2 "
                          "latency timer 1 ms, /dev/ttyDXL")
    udev.add_argument("--install", action="store_true",
                      help="write /etc/udev/rules.d/60-vtzero.rules")
    udev.set_defaults(func=_cmd_install_udev)


def _cmd_install_service(args: argparse.Namespace) -> int:
    from edge.deploy.install import install_service

    return install_service(args.config, args.user, create_user=args.create_user,
                           write=args.install)


def _cmd_install_udev(args: argparse.Namespace) -> int:
    from edge.deploy import udev

    if not args.install:
        print(udev.rules_text(), end="")
        return 0
    path = udev.install()
    print(f"installed {path}; now: {udev.RELOAD_COMMAND}, then unplug and replug the U2D2")
    return 0
