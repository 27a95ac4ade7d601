"""``vt-edge``: the on-robot command line."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from edge import SERVICE_NAME, __version__
from edge.core.errors import EdgeError
from edge.core.logs import setup_logging
from edge.runtime.episode import Status

log = logging.getLogger(__name__)

# `--config` is taken before or after the subcommand (`vt-edge --config F episodes list` and
# `vt-edge episodes list --config F`): every parser that reads one declares it with no
# default of its own (argparse copies a subcommand's defaults over what the main parser
# read), and _resolve_config fills in the command's default afterwards.
CONFIG_HELP = "the configuration file (TOML); before or after the subcommand"
# `vt-edge sim place`: the emulated robot answers on loopback at once.
SIM_CONTROL_TIMEOUT_S = 5.0
# `vt-edge episodes list`: the width of the reason column.
LIST_TEXT_CHARS = 60
# The emulated robot's camera, under its control API.
SIM_CAMERA_PATH = "/camera.jpg"
# Where `vt-edge models install` puts a model without --to or --config.
MODELS_DIR = "/opt/vtzero/models"


def _cmd_sim_record(args: argparse.Namespace) -> int:
    from edge.core.config import load_config
    from edge.core.progress import Progress
    from edge.lab.record import record_dataset
    from edge.sim.catalogue import DATASETS

    cfg = load_config(args.config)
    total = len(DATASETS[args.dataset]) * args.presses
    with Progress(f"record {args.dataset}", total, "presses", enabled=not args.quiet) as bar:
        index = record_dataset(args.dataset, args.presses, args.out, seed=args.seed, cfg=cfg,
                               x_th=args.x_th, workers=args.workers,
                               progress=lambda done, _total: bar.set(done))
    n = len(index["classes"]) * args.presses
    print(f"wrote {n} presses of {len(index['classes'])} classes ({args.dataset}) to {args.out}")
    if index["retried"]:
        print(f"note: {len(index['retried'])} presses needed a second try: "
              + ", ".join(index["retried"][:10]))
    return 0


def _cmd_sim_press(args: argparse.Namespace) -> int:
    from edge.lab.press_table import print_press_table

    print_press_table(args.objects, seed=args.seed, x_th=args.x_th)
    return 0


def _cmd_sim_vlm(args: argparse.Namespace) -> int:
    import asyncio

    from edge.sim.standin_vlm import serve

    asyncio.run(serve(args.host, args.port, lambda line: print(line, flush=True)))
    return 0


def _cmd_sim_consistency(args: argparse.Namespace) -> int:
    from edge.lab.consistency import run_consistency

    command = "vt-edge sim consistency " + " ".join(sys.argv[3:]) if len(sys.argv) > 3 else (
        "vt-edge sim consistency")
    report = run_consistency(args.objects, args.presses, args.dataset_presses, args.seed,
                             args.models, args.config, args.out, command=command.strip(),
                             runs=args.runs)
    print(report.markdown(command.strip()))
    return 0 if report.passed else 1


def _cmd_demo(args: argparse.Namespace) -> int:
    from edge.lab.demo import run_demo

    return run_demo(args.config)


def _cmd_doctor(args: argparse.Namespace) -> int:
    from edge.ops.doctor import main

    return main(args.config, args.json)


def _cmd_run(args: argparse.Namespace) -> int:
    from edge.runtime import forkserver

    forkserver.start()  # its imports beside the daemon's below (edge/runtime/forkserver.py)
    from edge.app import run

    return run(args.config)


def _cmd_sim_serve(args: argparse.Namespace) -> int:
    import asyncio
    import signal

    from edge.core import tomledit
    from edge.core.config import load_config
    from edge.sim.robot import SimRobot

    cfg = load_config(args.config)
    replay = None
    if args.replay is not None:
        from edge.sim.xela_replay import load_replay

        # Before anything starts: a bad file is refused with the file and the problem.
        replay = load_replay(args.replay)

    async def serve() -> None:
        robot = SimRobot(args.object, cfg.sim.seed, xela_port=args.xela_port,
                         rate_hz=cfg.sim.sensor_rate_hz, dialect=args.dialect, cfg=cfg,
                         replay=replay, replay_loop=not args.replay_once,
                         calibrated=args.calibrated)
        async with robot:
            print(f"xela_server emulator: {robot.xela.url}", flush=True)
            if replay is not None:
                print(f"  replaying {replay.describe()}, "
                      f"{'once' if args.replay_once else 'looping'}", flush=True)
            print(f"Dynamixel bus (pty):  {robot.dxl.port}", flush=True)
            print(f"control + camera:     {robot.control_url}", flush=True)
            if args.write_config:
                tomledit.update(args.config, args.write_config, {
                    **_absolute_paths(args.config),
                    "sensor": {"url": robot.xela.url}, "bus": {"port": robot.dxl.port},
                    "camera": {"kind": "http", "url": robot.control_url + SIM_CAMERA_PATH}})
                print(f"runtime config:       {args.write_config}", flush=True)
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, stop.set)
            await stop.wait()

    asyncio.run(serve())
    return 0


# The settings that name a file or directory, by table.
PATH_SETTINGS = {
    "runtime": ("models_dir", "state_dir", "record_mcap_dir"),
    "api": ("token_file",),
    "vlm": ("prompt_dir", "api_key_file"),
    "mqtt": ("password_file", "ca_file"),
}


def _absolute_paths(config: str) -> dict[str, dict[str, str]]:
    """The path settings of ``config`` (the file's, defaults included, not the
    environment's) that are relative, made absolute from the current directory, where this
    process reads them: a config written elsewhere still finds the same files."""
    import tomllib
    from pathlib import Path

    from edge.core.config import config_from_dict

    with open(config, "rb") as f:
        cfg = config_from_dict(tomllib.load(f), source=config)
    changes: dict[str, dict[str, str]] = {}
    for table, keys in PATH_SETTINGS.items():
        for key in keys:
            value = getattr(getattr(cfg, table), key)
            if value and not Path(value).is_absolute():
                changes.setdefault(table, {})[key] = str(Path(value).resolve())
    return changes


def _cmd_sim_place(args: argparse.Namespace) -> int:
    import json
    import urllib.error
    import urllib.request

    url = _control_url(args)
    request = urllib.request.Request(f"{url}/object", data=json.dumps({"name": args.name})
                                     .encode(), headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=SIM_CONTROL_TIMEOUT_S) as reply:
            placed = json.load(reply)["object"]
    except urllib.error.HTTPError as exc:
        try:
            why = json.loads(exc.read())["error"]
        except (ValueError, KeyError, TypeError):  # not the emulator's JSON error
            why = f"HTTP {exc.code} {exc.reason}"
        raise EdgeError(f"the emulated robot at {url} refused {args.name!r}: {why}") from None
    except (urllib.error.URLError, OSError) as exc:
        raise EdgeError(f"no emulated robot answers at {url} ({exc}): start `vt-edge sim "
                        "serve` and pass its control address (--url) or the config it "
                        "wrote (--config)") from None
    print(f"{placed} is on the emulated table ({url})")
    return 0


def _control_url(args: argparse.Namespace) -> str:
    """The emulated robot's control API: --url, or the one a config written by
    `sim serve --write-config` points its camera at (CONTROL/camera.jpg)."""
    if args.url:
        return args.url.rstrip("/")
    if args.config is None:
        raise EdgeError("sim place: give --url (the control address `vt-edge sim serve` "
                        "prints) or --config (the file its --write-config wrote)")
    from edge.core.config import load_config

    camera = load_config(args.config).camera
    if camera.kind != "http" or not camera.url.endswith(SIM_CAMERA_PATH):
        raise EdgeError(f"{args.config} was not written by `vt-edge sim serve --write-config` "
                        f"(its camera.url is not the emulated robot's ...{SIM_CAMERA_PATH}): "
                        "pass --url")
    return camera.url.removesuffix(SIM_CAMERA_PATH)


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


def _cmd_pose_teach(args: argparse.Namespace) -> int:
    import asyncio

    from edge.core.config import load_config
    from edge.ops.pose import teach_pose

    asyncio.run(teach_pose(load_config(args.config), args.config, args.name))
    return 0


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


def _cmd_pose_goto(args: argparse.Namespace) -> int:
    import asyncio

    from edge.core.config import load_config
    from edge.ops.pose import goto_pose

    asyncio.run(goto_pose(load_config(args.config), args.name))
    return 0


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


def _cmd_install_udev(args: argparse.Namespace) -> int:
    from edge.deploy import udev

    if not args.install:
        print(udev.rules_text(), end="")
        return 0
    path = udev.install()
    print(f"installed {path}; now: {udev.RELOAD_COMMAND}, then unplug and replug the U2D2")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from edge.bench import run_bench

    return run_bench(args)


def _cmd_episodes(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from edge.core.config import load_config
    from edge.runtime.episode import Status
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


def _cmd_dataset_export(args: argparse.Namespace) -> int:
    from edge.ops.export import export_collection

    print(export_collection(args.dir, args.out))
    return 0


def _cmd_install_service(args: argparse.Namespace) -> int:
    from edge.deploy.install import install_service

    return install_service(args.config, args.user, create_user=args.create_user,
                           write=args.install)


def _config_option(parser: argparse.ArgumentParser, default: str | None = None, *,
                   required: bool = False, help: str = CONFIG_HELP) -> None:
    """``--config`` on ``parser``; ``default`` (or ``required``) applies when it is given
    neither there nor before the subcommand."""
    parser.add_argument("--config", default=argparse.SUPPRESS, help=help)
    parser.set_defaults(config_default=default, config_required=required)


def _resolve_config(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``args.config``: as given (before or after the subcommand), else the command's
    default; an error for a command that needs one and got none, or takes none."""
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vt-edge", description=__doc__)
    parser.add_argument("--version", action="version", version=f"vtzero {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--config", default=argparse.SUPPRESS, help=CONFIG_HELP)
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="the main job: recognitions on the emulated robot")
    _config_option(demo, "configs/sim.toml")
    demo.set_defaults(func=_cmd_demo)

    doc = sub.add_parser("doctor", help="check every part of the setup before the first "
                         "press, without moving the arm (exit 1 on any FAIL)")
    _config_option(doc, required=True)
    doc.add_argument("--json", action="store_true", help="the checks as JSON")
    doc.set_defaults(func=_cmd_doctor)

    run = sub.add_parser("run", help="run the daemon")
    _config_option(run, required=True)
    run.set_defaults(func=_cmd_run)

    col = sub.add_parser("collect", help="record the presses of a collection plan (or of "
                                         "one object)")
    _config_option(col, required=True)
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

    pose = sub.add_parser("pose", help="arm poses")
    posesub = pose.add_subparsers(dest="pose_command", required=True)
    teach = posesub.add_parser("teach", help="store the arm's present pose by name")
    teach.add_argument("name", help="e.g. above, lowered, rest")
    _config_option(teach, required=True)
    teach.set_defaults(func=_cmd_pose_teach)
    goto = posesub.add_parser("goto", help="move slowly to a taught pose to check it")
    goto.add_argument("name")
    _config_option(goto, required=True)
    goto.set_defaults(func=_cmd_pose_goto)

    models = sub.add_parser("models", help="the model directory the daemon loads")
    modsub = models.add_subparsers(dest="models_command", required=True)
    minst = modsub.add_parser("install", help="verify a model directory and put it in place "
                              "(the one it replaces kept as DIR.previous)")
    minst.add_argument("src", help="a model directory (manifest.json, encoder, database)")
    where = minst.add_mutually_exclusive_group()
    where.add_argument("--to", default=None, help=f"default: {MODELS_DIR}")
    where.add_argument("--config", default=argparse.SUPPRESS,
                       help="install to this configuration's [runtime] models_dir")
    minst.set_defaults(func=_cmd_models_install, config_default=None, config_required=False)

    cal = sub.add_parser("calibrate", help="find settings for this robot's own hardware")
    calsub = cal.add_subparsers(dest="calibrate_command", required=True)
    th = calsub.add_parser(
        "threshold", help="find [press] x_th for these pads: idle noise, a slow probing "
        "press on a reference object, the norm at a gentle force (docs/hardware.md)")
    _config_option(th, required=True)
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

    bench = sub.add_parser("bench", help="measure the runtime on the emulated robot")
    bench.add_argument("--out", default="bench", help="directory for results.json/.md")
    bench.add_argument("--baseline", default=None,
                       help="an earlier results.json: results.md compares every figure")
    bench.add_argument("--quick", action="store_true",
                       help="short runs (a smoke test; figures are not representative)")
    bench.set_defaults(func=_cmd_bench)

    eps = sub.add_parser("episodes", help="stored recognitions")
    _config_option(eps, "configs/robot.toml")
    epsub = eps.add_subparsers(dest="episodes_command", required=True)
    ls = epsub.add_parser("list")
    _config_option(ls, "configs/robot.toml")
    ls.add_argument("--status", default=None, choices=[s.value for s in Status])
    ls.add_argument("--limit", type=int, default=50)
    show = epsub.add_parser("show")
    _config_option(show, "configs/robot.toml")
    show.add_argument("id")
    export = epsub.add_parser("export")
    _config_option(export, "configs/robot.toml")
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
    _config_option(retry, "configs/robot.toml")
    which = retry.add_mutually_exclusive_group(required=True)
    which.add_argument("id", nargs="?", default=None)
    which.add_argument("--all-failed", action="store_true",
                       help="every vlm_error and invalid_answer episode, oldest first")
    retry.add_argument("--url", default=None,
                       help="the daemon's API (default: from [api] host and port)")
    eps.set_defaults(func=_cmd_episodes)

    dexp = dssub.add_parser("export", help="a collection as one LeRobotDataset v3.0 "
                            "(pip install 'vtzero[export]')")
    dexp.add_argument("dir", help="the collection (DIR/dataset.json)")
    dexp.add_argument("--format", choices=["lerobot"], default="lerobot")
    dexp.add_argument("--out", default=None, help="the dataset directory (default DIR.lerobot)")
    dexp.set_defaults(func=_cmd_dataset_export)

    svc = sub.add_parser("install-service", help="print (or install) the systemd unit")
    _config_option(svc, "/etc/vtzero/robot.toml")
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

    sim = sub.add_parser("sim", help="the simulated robot")
    simsub = sim.add_subparsers(dest="sim_command", required=True)

    rec = simsub.add_parser("record", help="record a simulated dataset of presses")
    rec.add_argument("--dataset", required=True, choices=["reference", "foodreplica", "cube"])
    rec.add_argument("--presses", type=int, default=10, help="presses per class")
    rec.add_argument("--out", required=True, help="output directory")
    rec.add_argument("--seed", type=int, default=0)
    rec.add_argument("--workers", type=int, default=None, help="processes (default: cores)")
    _config_option(rec, "configs/sim.toml",
                   help="the emulated robot's configuration (press settings)")
    rec.add_argument("--x-th", type=float, default=None,
                     help="stop threshold for every class (default: [press] x_th, the "
                          "catalogue's per-class threshold for fragile classes)")
    rec.add_argument("-q", "--quiet", action="store_true")
    rec.set_defaults(func=_cmd_sim_record)

    serve = simsub.add_parser("serve", help="run the emulated robot until stopped")
    _config_option(serve, "configs/sim.toml")
    serve.add_argument("--object", default="stainless_cube")
    serve.add_argument("--xela-port", type=int, default=0, help="0: any free port")
    serve.add_argument("--dialect", choices=["1.7", "1.7.7", "1.8"], default="1.8")
    serve.add_argument("--write-config", default=None,
                       help="write the config with this robot's addresses here")
    serve.add_argument("--replay", default=None, metavar="FILE",
                       help="the pads send this real recording (a XELA CSV directory such as "
                            "tests/fixtures/xela/real-xr1944/data_sample_2022-02-22-15-15-00, "
                            "or a .press.npz) at its recorded timing, from the start again "
                            "after the end; the arm and gripper are still emulated")
    serve.add_argument("--replay-once", action="store_true",
                       help="after the recording's last frame send nothing more (the "
                            "connection stays open: the stream goes stale)")
    serve.add_argument("--calibrated", action="store_true",
                       help="send each taxel's force as `calibrated` newtons, as xela_server "
                            "does for the models XELA calibrates (the XR1944 is not)")
    serve.set_defaults(func=_cmd_sim_serve)

    place = simsub.add_parser(
        "place", help="put an object on the emulated table (the control API of a running "
        "`vt-edge sim serve`); the next press presses it")
    place.add_argument("name", help="an object of the catalogue, e.g. wood_cube")
    place.add_argument("--url", default=None,
                       help="the control address `sim serve` prints (control + camera)")
    _config_option(place, help="instead of --url: the config `sim serve --write-config` "
                   "wrote")
    place.set_defaults(func=_cmd_sim_place)

    cons = simsub.add_parser(
        "consistency", help="the daemon's presses on the emulated robot against the dataset "
        "recorder's, encoded by the shipped model (exit 1 if the targets are missed)")
    cons.add_argument("--objects", nargs="+", default=None, help="default: the 8 of the report")
    cons.add_argument("--presses", type=int, default=10,
                      help="daemon presses per object and run")
    cons.add_argument("--dataset-presses", type=int, default=20,
                      help="dataset recorder presses per object and run")
    cons.add_argument("--runs", type=int, default=3, help="repeats with new presses; the "
                      "targets must hold in each (run k: dataset seed SEED+k)")
    cons.add_argument("--seed", type=int, default=0)
    cons.add_argument("--models", default="models")
    _config_option(cons, "configs/sim.toml")
    cons.add_argument("--out", default=None, help="write consistency.md/.json here")
    cons.set_defaults(func=_cmd_sim_consistency)

    press = simsub.add_parser("press", help="press objects once and print a summary")
    press.add_argument("objects", nargs="+", help="object class names")
    press.add_argument("--seed", type=int, default=0)
    press.add_argument("--x-th", type=float, default=None,
                       help="stop threshold (default: the configuration's or the class's)")
    press.set_defaults(func=_cmd_sim_press)

    vlm = simsub.add_parser("vlm", help="serve the simulated VLM (an OpenAI-compatible "
                            "stand-in that knows only object names and pictures)")
    vlm.add_argument("--host", default="127.0.0.1")
    vlm.add_argument("--port", type=int, default=8011, help="0: any free port")
    vlm.set_defaults(func=_cmd_sim_vlm)
    return parser


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
