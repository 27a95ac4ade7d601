"""``vt-edge teach`` and ``vt-edge references``: teach the running robot an object (or what an
episode's object really was), and review, remove and export what was taught.

Teaching presses the arm, and the daemon owns the bus: these commands ask the running daemon
over its HTTP API (as ``vt-edge episodes retry`` does), and say so in one line when it is
down. ``references export`` reads the taught references directly (read-only), so it works
with the daemon stopped too.
"""

from __future__ import annotations

import argparse
import urllib.parse
from typing import Any

from edge.cli.options import config_option
from edge.core.config import Config

# How long one taught press may take the daemon (arm moves, the press, the compute process),
# beyond the pause between presses.
PRESS_TIMEOUT_S = 60.0
# Any other request (a list, a removal, an episode taught).
REQUEST_TIMEOUT_S = 30.0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    teach = sub.add_parser(
        "teach", help="teach the running robot an object: it presses it and adds the presses "
        "to the references (or, with --episode, what an episode's object really was)")
    config_option(teach, "configs/robot.toml")
    teach.add_argument("label", help="the object's class label (letters, digits, _ - .)")
    teach.add_argument("--description", default=None,
                       help="what the object is, named for a VLM (never how it feels); "
                            "needed for a new label")
    teach.add_argument("--presses", type=int, default=1,
                       help="how many times to press it (default 1)")
    teach.add_argument("--append", action="store_true",
                       help="add presses to a label the references already have")
    teach.add_argument("--pause", type=float, default=None, metavar="S",
                       help="seconds between presses to move the object slightly "
                            "(default: the daemon's)")
    teach.add_argument("--episode", default=None, metavar="ID",
                       help="teach this episode's press as LABEL instead of pressing")
    teach.add_argument("--url", default=None,
                       help="the daemon's API (default: from [api] host and port)")
    teach.set_defaults(func=_cmd_teach)

    refs = sub.add_parser("references", help="the references taught to the robot: list, "
                          "remove, export for the next build")
    config_option(refs, "configs/robot.toml")
    refsub = refs.add_subparsers(dest="references_command", required=True)
    ls = refsub.add_parser("list", help="every taught reference (through the running daemon)")
    config_option(ls, "configs/robot.toml")
    ls.add_argument("--url", default=None)
    rm = refsub.add_parser("remove", help="remove a reference by id, or every one of a label "
                           "(through the running daemon)")
    config_option(rm, "configs/robot.toml")
    which = rm.add_mutually_exclusive_group(required=True)
    which.add_argument("id", nargs="?", default=None)
    which.add_argument("--label", default=None)
    rm.add_argument("--url", default=None)
    export = refsub.add_parser("export", help="write the taught presses as a collection "
                               "(the collect format) for `vt-train build`")
    config_option(export, "configs/robot.toml")
    export.add_argument("dir", help="a new directory")
    refs.set_defaults(func=_cmd_references)


def _cmd_teach(args: argparse.Namespace) -> int:
    from edge.core.config import load_config
    from edge.runtime.teaching import PAUSE_S

    cfg = load_config(args.config)
    if args.episode is not None:
        ref = _ask(cfg, "POST", f"/v1/episodes/{_quoted(args.episode)}/teach",
                         _without_none({"label": args.label,
                                        "description": args.description}), args.url)
        print(f"episode {args.episode} taught as {ref['label']}: reference {ref['id']}")
        return 0
    body = _without_none({"label": args.label, "description": args.description,
                          "presses": args.presses, "append": args.append,
                          "pause_s": args.pause, "wait": True})
    timeout = max(1, args.presses) * (PRESS_TIMEOUT_S + (args.pause or PAUSE_S))
    print(f"teaching {args.label}: {args.presses} press(es); move the object slightly "
          "between presses")
    run = _ask(cfg, "POST", "/v1/teach", body, args.url, timeout)
    for episode, ref in zip(run["episodes"], run["references"], strict=False):
        print(f"  episode {episode} -> reference {ref}")
    if run["status"] != "done":
        print(f"teaching {args.label} failed after {len(run['references'])} taught "
              f"press(es): {run['error']}")
        return 1
    print(f"taught {args.label}: {len(run['references'])} press(es)")
    return 0


def _cmd_references(args: argparse.Namespace) -> int:
    from edge.core.config import load_config

    cfg = load_config(args.config)
    if args.references_command == "export":
        from edge.runtime.references import ReferenceStore, references_dir

        print(ReferenceStore(references_dir(cfg.runtime.state_dir)).export(args.dir))
        return 0
    if args.references_command == "remove":
        path = (f"/v1/references/{_quoted(args.id)}" if args.id is not None
                else f"/v1/references?label={urllib.parse.quote(args.label)}")
        removed = _ask(cfg, "DELETE", path, None, args.url)["removed"]
        for ref in removed:
            print(f"removed {ref['id']}  {ref['label']}")
        return 0
    listing = _ask(cfg, "GET", "/v1/references", None, args.url)
    for ref in listing["references"]:
        stale = "  (stale: another model embedded it, not used)" if ref["stale"] else ""
        print(f"{ref['id']}  {ref['label']:24s} {ref['taught_at']}  {ref['source']:5s} "
              f"episode {ref['episode'] or '-'}  {ref['description']}{stale}")
    if not listing["references"]:
        print(f"no taught references in {listing['directory']}")
    return 0


def _ask(cfg: Config, method: str, path: str, body: dict[str, Any] | None,
         url: str | None = None, timeout_s: float = REQUEST_TIMEOUT_S) -> Any:
    """The running daemon's answer (teaching and the references go through it)."""
    from edge.ops.daemon_http import ask_daemon

    return ask_daemon(cfg, method, path, body, timeout_s=timeout_s, url=url,
                      what="teaching (and the taught references)")


def _quoted(segment: str) -> str:
    return urllib.parse.quote(segment, safe="")


def _without_none(body: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in body.items() if v is not None}
