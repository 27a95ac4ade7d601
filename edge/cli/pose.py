"""``vt-edge pose``: the arm's named poses, taught and checked."""

from __future__ import annotations

import argparse

from edge.cli.options import config_option


def add_parsers(sub: argparse._SubParsersAction) -> None:
    pose = sub.add_parser("pose", help="arm poses")
    posesub = pose.add_subparsers(dest="pose_command", required=True)
    teach = posesub.add_parser("teach", help="store the arm's present pose by name")
    teach.add_argument("name", help="e.g. above, lowered, rest")
    config_option(teach, required=True)
    teach.set_defaults(func=_cmd_pose_teach)
    goto = posesub.add_parser("goto", help="move slowly to a taught pose to check it")
    goto.add_argument("name")
    config_option(goto, required=True)
    goto.set_defaults(func=_cmd_pose_goto)


def _cmd_pose_teach(args: argparse.Namespace) -> int:
    import asyncio

    from edge.core.config import load_config
    from edge.ops.pose import teach_pose

    asyncio.run(teach_pose(load_config(args.config), args.config, args.name))
    return 0


def _cmd_pose_goto(args: argparse.Namespace) -> int:
    import asyncio

    from edge.core.config import load_config
    from edge.ops.pose import goto_pose

    asyncio.run(goto_pose(load_config(args.config), args.name))
    return 0
