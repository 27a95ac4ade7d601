"""``vt-edge collect`` and ``vt-edge dataset``: a collection's presses recorded, summed up
and exported."""

from __future__ import annotations

import argparse

from edge.cli.options import config_option
from edge.core.errors import EdgeError


def add_parsers(sub: argparse._SubParsersAction) -> None:
    col = sub.add_parser("collect", help="record the presses of a collection plan (or of "
                                         "one object)")
    config_option(col, required=True)
    col.add_argument("--plan", default=None,
                     help="a collection plan (TOML, see README 'Collecting a dataset'); run "
                          "again, it goes on up to each class's count")
    col.add_argument("--label", default=None, help="one object instead of a plan")
    col.add_argument("--presses", type=int, default=10, help="with --label")
    col.add_argument("--description", default=None,
                     help="with --label: what the object is (default: the label)")
    col.add_argument("--photo", action="store_true", help="with --label: a photo per press")
    col.add_argument("--out", required=True, help="the dataset directory")
    col.add_argument("--x-th", type=float, default=None,
                     help="with --label: press threshold for this object (e.g. 0.003 for a "
                          "fragile one); default: the configuration's [press] x_th")
    col.add_argument("--no-prompt", action="store_true",
                     help="do not wait for Enter between presses")
    col.set_defaults(func=_cmd_collect)

    ds = sub.add_parser("dataset", help="collected datasets")
    dssub = ds.add_subparsers(dest="dataset_command", required=True)
    summ = dssub.add_parser("summary", help="per class: presses kept and failed, thresholds, "
                            "peaks, stop latency, what looks wrong; exit 1 on a class that "
                            "mixes thresholds or has fewer presses than planned")
    summ.add_argument("dir", help="the dataset directory (vt-edge collect --out)")
    summ.add_argument("--plan", default=None, help="the plan to compare against (default: "
                      "the counts dataset.json records)")
    summ.set_defaults(func=_cmd_dataset_summary)

    dexp = dssub.add_parser("export", help="a collection as one LeRobotDataset v3.0 "
                            "(pip install 'vtzero[export]')")
    dexp.add_argument("dir", help="the collection (DIR/dataset.json)")
    dexp.add_argument("--format", choices=["lerobot"], default="lerobot")
    dexp.add_argument("--out", default=None, help="the dataset directory (default DIR.lerobot)")
    dexp.set_defaults(func=_cmd_dataset_export)


def _cmd_collect(args: argparse.Namespace) -> int:
    import asyncio
    from pathlib import Path

    from edge.core.config import load_config
    from edge.core.prompt import read_line
    from edge.lab.collect import CollectReport, collect_plan
    from edge.lab.plan import load_plan, plan_of_one

    cfg = load_config(args.config)
    if (args.plan is None) == (args.label is None):
        raise EdgeError("collect: give --plan PLAN.toml, or --label NAME [--presses N]")
    if args.plan is not None:
        plan = load_plan(args.plan)
    else:
        plan = plan_of_one(args.label, args.presses, description=args.description,
                           x_th=args.x_th, photo=args.photo,
                           name=Path(args.out).resolve().name or "collected")
    report = CollectReport()
    asyncio.run(collect_plan(cfg, plan, args.out, None if args.no_prompt else read_line,
                             report=report))
    print(f"kept {len(report.kept)} presses in this run, {report.failed} failed; "
          f"dataset in {args.out}")
    if report.skipped or not report.complete:
        short = [f"{k} {report.have[k]}/{n}" for k, n in report.planned.items()
                 if report.have[k] < n]
        print(f"not complete: {', '.join(short)}; run the same command again to go on")
        return 1
    return 0


def _cmd_dataset_summary(args: argparse.Namespace) -> int:
    from edge.lab.dataset import format_summary, summarize
    from edge.lab.plan import load_plan

    summary = summarize(args.dir, load_plan(args.plan) if args.plan else None)
    print(format_summary(summary))
    return 1 if summary.problems else 0


def _cmd_dataset_export(args: argparse.Namespace) -> int:
    from edge.ops.export import export_collection

    print(export_collection(args.dir, args.out))
    return 0
