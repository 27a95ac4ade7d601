"""``vt-edge calibrate``: settings found for this robot's own hardware."""

from __future__ import annotations

import argparse

from edge.cli.options import config_option


def add_parsers(sub: argparse._SubParsersAction) -> None:
    cal = sub.add_parser("calibrate", help="find settings for this robot's own hardware")
    calsub = cal.add_subparsers(dest="calibrate_command", required=True)
    th = calsub.add_parser(
        "threshold", help="find [press] x_th for these pads: idle noise, a slow probing "
        "press on a reference object, the norm at a gentle force (docs/hardware.md)")
    config_option(th, required=True)
    force = th.add_mutually_exclusive_group()
    force.add_argument("--force-ma", type=float, default=None,
                       help="the gentle force as gripper motor current above its free-closing "
                            "current, mA (default 20: today's x_th on the emulated XR1944 "
                            "with a kitchen sponge)")
    force.add_argument("--force-n", type=float, default=None,
                       help="the gentle force in newtons per finger (pads whose xela_server "
                            "sends `calibrated` forces)")
    th.add_argument("--max-ma", type=float, default=None,
                    help="the probe never commands more current than this, mA (default 200; "
                         "never more than [bus] gripper_goal_current)")
    th.add_argument("--idle-s", type=float, default=None,
                    help="seconds of idle noise measured (default 4)")
    th.add_argument("--speed-mps", type=float, default=None,
                    help="the probe's gap closing speed, m/s (default 0.004)")
    th.add_argument("--out", default="calibration",
                    help="directory for threshold.png and threshold.json")
    th.add_argument("--no-prompt", action="store_true",
                    help="do not wait for Enter once the reference object is placed")
    th.add_argument("--yes", action="store_true",
                    help="write x_th into the configuration without asking")
    th.set_defaults(func=_cmd_calibrate_threshold)


def _cmd_calibrate_threshold(args: argparse.Namespace) -> int:
    import asyncio

    from edge.core.config import load_config
    from edge.core.prompt import read_line
    from edge.ops.calibrate import calibrate_threshold

    # Options left out take the procedure's own defaults.
    given = {k: v for k, v in (("force_ma", args.force_ma), ("max_ma", args.max_ma),
                               ("idle_s", args.idle_s), ("speed_mps", args.speed_mps))
             if v is not None}
    if args.force_n is not None:
        given.update(force_ma=None, force_n=args.force_n)
    asyncio.run(calibrate_threshold(
        load_config(args.config), args.config, args.out, **given,
        prompt=None if args.no_prompt else read_line,
        confirm=None if args.yes else read_line))
    return 0
