"""``vt-edge episodes``: the stored recognitions listed, shown, exported and asked again."""

from __future__ import annotations

import argparse

from edge.cli.options import config_option
from edge.runtime.domain import Status

# `vt-edge episodes list`: the width of the reason column.
LIST_TEXT_CHARS = 60


def add_parsers(sub: argparse._SubParsersAction) -> None:
    eps = sub.add_parser("episodes", help="stored recognitions")
    config_option(eps, "configs/robot.toml")
    epsub = eps.add_subparsers(dest="episodes_command", required=True)
    ls = epsub.add_parser("list")
    config_option(ls, "configs/robot.toml")
    ls.add_argument("--status", default=None, choices=[s.value for s in Status])
    ls.add_argument("--limit", type=int, default=50)
    show = epsub.add_parser("show")
    config_option(show, "configs/robot.toml")
    show.add_argument("id")
    export = epsub.add_parser("export")
    config_option(export, "configs/robot.toml")
    export.add_argument("id", nargs="+")
    export.add_argument("--out", default=".",
                        help="a file, or a directory for ID.tar.gz/ID.mcap; the bag or dataset "
                             "directory (inside an existing other directory: DIR/ID)")
    export.add_argument("--format", choices=["tar.gz", "mcap", "rosbag2", "lerobot"],
                        default="tar.gz",
                        help="tar.gz: the episode directory as stored; mcap: tactile frames, "
                             "gripper, press states, photo and result for Foxglove; rosbag2: "
                             "all the episodes as one ROS 2 bag; lerobot: all as one "
                             "LeRobotDataset v3.0 (both: pip install 'vtzero[export]')")
    retry = epsub.add_parser("retry", help="ask the VLM again about a vlm_error or "
                             "invalid_answer episode, through the running daemon")
    config_option(retry, "configs/robot.toml")
    which = retry.add_mutually_exclusive_group(required=True)
    which.add_argument("id", nargs="?", default=None)
    which.add_argument("--all-failed", action="store_true",
                       help="every vlm_error and invalid_answer episode, oldest first")
    retry.add_argument("--url", default=None,
                       help="the daemon's API (default: from [api] host and port)")
    eps.set_defaults(func=_cmd_episodes)


def _cmd_episodes(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from edge.core.config import load_config
    from edge.runtime.store import EpisodeStore

    cfg = load_config(args.config)
    store = EpisodeStore(Path(cfg.runtime.state_dir) / "episodes")
    if args.episodes_command == "retry":
        from edge.ops.episode_retry import run_retry

        return run_retry(cfg, store, args.id, args.all_failed, args.url)
    if args.episodes_command == "list":
        status = Status(args.status) if args.status else None
        for ep in store.list(status=status, limit=args.limit):
            # Why it failed (a press error, or the VLM's last one), else what touch said.
            why = ep.error or ep.last_error or ep.description or ""
            print(f"{ep.id}  {ep.status:15s} {ep.label or '-':28s} {_first_words(why)}")
    elif args.episodes_command == "show":
        print(json.dumps(store.get(args.id).to_json(), indent=2))
    elif args.format in ("rosbag2", "lerobot"):
        from edge.ops.export import export_episodes

        print(export_episodes(store, args.id, args.format, args.out))
    else:
        from edge.recordings.mcaplog import export_episode

        for eid in args.id:
            print(export_episode(store, eid, args.out) if args.format == "mcap"
                  else store.export(eid, args.out))
    return 0


def _first_words(text: str, width: int = LIST_TEXT_CHARS) -> str:
    """``text`` on one line, cut at a word with an ellipsis past ``width`` characters."""
    line = " ".join(text.split())
    if len(line) <= width:
        return line
    cut = line[:width - 3].rsplit(" ", 1)[0]
    return f"{cut}..."
