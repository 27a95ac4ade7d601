"""``vt-edge``: the on-robot command line."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from edge import __version__
from edge.core.errors import EdgeError
from edge.core.logs import setup_logging
from edge.daemon.episode import Status

log = logging.getLogger(__name__)


def _cmd_sim_record(args: argparse.Namespace) -> int:
    from edge.core.config import load_config
    from edge.core.progress import Progress
    from edge.sim.catalogue import DATASETS
    from edge.tools.record import record_dataset

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
    from edge.tools.press_table import print_press_table

    print_press_table(args.objects, seed=args.seed, x_th=args.x_th)
    return 0


def _cmd_sim_vlm(args: argparse.Namespace) -> int:
    import asyncio

    from edge.sim.standin_vlm import serve

    asyncio.run(serve(args.host, args.port, lambda line: print(line, flush=True)))
    return 0


def _cmd_sim_consistency(args: argparse.Namespace) -> int:
    from edge.tools.consistency import run_consistency

    command = "vt-edge sim consistency " + " ".join(sys.argv[3:]) if len(sys.argv) > 3 else (
        "vt-edge sim consistency")
    report = run_consistency(args.objects, args.presses, args.dataset_presses, args.seed,
                             args.models, args.config, args.out, command=command.strip())
    print(report.markdown(command.strip()))
    return 0 if report.passed else 1


def _cmd_demo(args: argparse.Namespace) -> int:
    from edge.tools.demo import run_demo

    return run_demo(args.config)


def _cmd_run(args: argparse.Namespace) -> int:
    from edge.daemon.serve import run

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
                         replay=replay, replay_loop=not args.replay_once)
        async with robot:
            print(f"xela_server emulator: {robot.xela.url}", flush=True)
            if replay is not None:
                print(f"  replaying {replay.describe()}, "
                      f"{'once' if args.replay_once else 'looping'}", flush=True)
            print(f"Dynamixel bus (pty):  {robot.dxl.port}", flush=True)
            print(f"control + camera:     {robot.control_url}", flush=True)
            if args.write_config:
                tomledit.update(args.config, args.write_config, {
                    "sensor": {"url": robot.xela.url}, "bus": {"port": robot.dxl.port},
                    "camera": {"kind": "http", "url": f"{robot.control_url}/camera.jpg"}})
                print(f"runtime config:       {args.write_config}", flush=True)
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, stop.set)
            await stop.wait()

    asyncio.run(serve())
    return 0


def _cmd_collect(args: argparse.Namespace) -> int:
    import asyncio
    from dataclasses import replace

    from edge.core.config import load_config
    from edge.tools.collect import collect

    cfg = load_config(args.config)
    if args.x_th is not None:
        cfg = replace(cfg, press=replace(cfg.press, x_th=args.x_th))
        cfg.press.validate("press (--x-th)")
    files = asyncio.run(collect(cfg, args.label, args.presses, args.out,
                                prompt=None if args.no_prompt else input))
    print(f"wrote {len(files)} presses of {args.label} to {args.out}")
    return 0


def _cmd_pose_teach(args: argparse.Namespace) -> int:
    import asyncio

    from edge.core.config import load_config
    from edge.tools.collect import teach_pose

    asyncio.run(teach_pose(load_config(args.config), args.config, args.name))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from edge.tools.bench import run_bench

    return run_bench(args)


def _cmd_episodes(args: argparse.Namespace) -> int:
    import json

    from edge.core.config import load_config
    from edge.daemon.episode import Status
    from edge.daemon.serve import state_dir
    from edge.daemon.store import EpisodeStore

    store = EpisodeStore(state_dir(load_config(args.config)) / "episodes")
    if args.episodes_command == "list":
        status = Status(args.status) if args.status else None
        for ep in store.list(status=status, limit=args.limit):
            print(f"{ep.id}  {ep.status:15s} {ep.label or '-':28s} "
                  f"{(ep.error or ep.description or '')[:60]}")
    elif args.episodes_command == "show":
        print(json.dumps(store.get(args.id).to_json(), indent=2))
    elif args.format == "mcap":
        from edge.daemon.mcaplog import export_episode

        print(export_episode(store, args.id, args.out))
    else:
        print(store.export(args.id, args.out))
    return 0


def _cmd_install_service(args: argparse.Namespace) -> int:
    import shutil
    from pathlib import Path

    from edge.daemon import systemd

    beside = Path(sys.executable).with_name("vt-edge")
    exe = str(beside) if beside.exists() else shutil.which("vt-edge") or f"{sys.executable} -m edge"
    config = Path(args.config).resolve()
    priority = None
    if config.exists():
        # The unit lets the daemon do what its configuration asks (real-time scheduling).
        from edge.core.config import load_config

        runtime = load_config(config).runtime
        priority = runtime.realtime_priority if runtime.realtime else None
    unit = systemd.unit_text(exe, str(config), args.user, realtime_priority=priority)
    if not args.install:
        print(unit, end="")
        return 0
    path = systemd.install(unit)
    print(f"installed {path}; now: systemctl daemon-reload && systemctl enable --now "
          f"{systemd.UNIT_NAME}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vt-edge", description=__doc__)
    parser.add_argument("--version", action="version", version=f"vtzero {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="the main job: recognitions on the emulated robot")
    demo.add_argument("--config", default="configs/sim.toml")
    demo.set_defaults(func=_cmd_demo)

    run = sub.add_parser("run", help="run the daemon")
    run.add_argument("--config", required=True)
    run.set_defaults(func=_cmd_run)

    col = sub.add_parser("collect", help="record reference presses of an object")
    col.add_argument("--config", required=True)
    col.add_argument("--label", required=True)
    col.add_argument("--presses", type=int, default=10)
    col.add_argument("--out", required=True)
    col.add_argument("--x-th", type=float, default=None,
                     help="press threshold for this object (e.g. 0.003 for a fragile one); "
                          "default: the configuration's [press] x_th")
    col.add_argument("--no-prompt", action="store_true",
                     help="do not wait for Enter between presses")
    col.set_defaults(func=_cmd_collect)

    pose = sub.add_parser("pose", help="arm poses")
    posesub = pose.add_subparsers(dest="pose_command", required=True)
    teach = posesub.add_parser("teach", help="store the arm's present pose by name")
    teach.add_argument("name", help="e.g. above, lowered, rest")
    teach.add_argument("--config", required=True)
    teach.set_defaults(func=_cmd_pose_teach)

    bench = sub.add_parser("bench", help="measure the runtime on the emulated robot")
    bench.add_argument("--out", default="bench", help="directory for results.json/.md")
    bench.add_argument("--baseline", default=None,
                       help="an earlier results.json: results.md compares every figure")
    bench.add_argument("--quick", action="store_true",
                       help="short runs (a smoke test; figures are not representative)")
    bench.set_defaults(func=_cmd_bench)

    eps = sub.add_parser("episodes", help="stored recognitions")
    eps.add_argument("--config", default="configs/robot.toml")
    epsub = eps.add_subparsers(dest="episodes_command", required=True)
    ls = epsub.add_parser("list")
    ls.add_argument("--status", default=None, choices=[s.value for s in Status])
    ls.add_argument("--limit", type=int, default=50)
    show = epsub.add_parser("show")
    show.add_argument("id")
    export = epsub.add_parser("export")
    export.add_argument("id")
    export.add_argument("--out", default=".", help="a file, or a directory for ID.tar.gz/ID.mcap")
    export.add_argument("--format", choices=["tar.gz", "mcap"], default="tar.gz",
                        help="tar.gz: the episode directory as stored; mcap: tactile frames, "
                             "gripper, press states, photo and result for Foxglove")
    eps.set_defaults(func=_cmd_episodes)

    svc = sub.add_parser("install-service", help="print (or install) the systemd unit")
    svc.add_argument("--config", default="/etc/vtzero/robot.toml")
    svc.add_argument("--user", default="vtzero")
    svc.add_argument("--install", action="store_true",
                     help="write /etc/systemd/system/vtzero-edge.service")
    svc.set_defaults(func=_cmd_install_service)

    sim = sub.add_parser("sim", help="the simulated robot")
    simsub = sim.add_subparsers(dest="sim_command", required=True)

    rec = simsub.add_parser("record", help="record a simulated dataset of presses")
    rec.add_argument("--dataset", required=True, choices=["reference", "foodreplica", "cube"])
    rec.add_argument("--presses", type=int, default=10, help="presses per class")
    rec.add_argument("--out", required=True, help="output directory")
    rec.add_argument("--seed", type=int, default=0)
    rec.add_argument("--workers", type=int, default=None, help="processes (default: cores)")
    rec.add_argument("--config", default="configs/sim.toml",
                     help="the emulated robot's configuration (press settings)")
    rec.add_argument("--x-th", type=float, default=None,
                     help="stop threshold for every class (default: [press] x_th, the "
                          "catalogue's per-class threshold for fragile classes)")
    rec.add_argument("-q", "--quiet", action="store_true")
    rec.set_defaults(func=_cmd_sim_record)

    serve = simsub.add_parser("serve", help="run the emulated robot until stopped")
    serve.add_argument("--config", default="configs/sim.toml")
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
    serve.set_defaults(func=_cmd_sim_serve)

    cons = simsub.add_parser(
        "consistency", help="the daemon's presses on the emulated robot against the dataset "
        "recorder's, encoded by the shipped model (exit 1 if the targets are missed)")
    cons.add_argument("--objects", nargs="+", default=None, help="default: the 8 of the report")
    cons.add_argument("--presses", type=int, default=5, help="daemon presses per object")
    cons.add_argument("--dataset-presses", type=int, default=10)
    cons.add_argument("--seed", type=int, default=0)
    cons.add_argument("--models", default="models")
    cons.add_argument("--config", default="configs/sim.toml")
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
    args = build_parser().parse_args(argv)
    setup_logging(logging.DEBUG if args.verbose else None)
    try:
        return int(args.func(args) or 0)
    except EdgeError as exc:
        log.error("%s", exc)
        return 2
    except KeyboardInterrupt:
        return 130
