"""``vt-edge sim``: the simulated robot served, pressed, recorded and compared with the
daemon."""

from __future__ import annotations

import argparse
import sys

from edge.cli.options import config_option
from edge.core.errors import EdgeError

# `vt-edge sim place`: the emulated robot answers on loopback at once.
SIM_CONTROL_TIMEOUT_S = 5.0
# The emulated robot's camera, under its control API.
SIM_CAMERA_PATH = "/camera.jpg"
# The settings that name a file or directory, by table.
PATH_SETTINGS = {
    "runtime": ("models_dir", "state_dir", "record_mcap_dir"),
    "api": ("token_file",),
    "vlm": ("prompt_dir", "api_key_file"),
    "mqtt": ("password_file", "ca_file"),
}


def add_parsers(sub: argparse._SubParsersAction) -> None:
    sim = sub.add_parser("sim", help="the simulated robot")
    simsub = sim.add_subparsers(dest="sim_command", required=True)

    rec = simsub.add_parser("record", help="record a simulated dataset of presses")
    rec.add_argument("--dataset", required=True, choices=["reference", "foodreplica", "cube"])
    rec.add_argument("--presses", type=int, default=10, help="presses per class")
    rec.add_argument("--out", required=True, help="output directory")
    rec.add_argument("--seed", type=int, default=0)
    rec.add_argument("--workers", type=int, default=None, help="processes (default: cores)")
    config_option(rec, "configs/sim.toml",
                  help="the emulated robot's configuration (press settings)")
    rec.add_argument("--x-th", type=float, default=None,
                     help="stop threshold for every class (default: [press] x_th, the "
                          "catalogue's per-class threshold for fragile classes)")
    rec.add_argument("-q", "--quiet", action="store_true")
    rec.set_defaults(func=_cmd_sim_record)

    serve = simsub.add_parser("serve", help="run the emulated robot until stopped")
    config_option(serve, "configs/sim.toml")
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
    config_option(place, help="instead of --url: the config `sim serve --write-config` "
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
    config_option(cons, "configs/sim.toml")
    cons.add_argument("--out", default=None, help="write consistency.md/.json here")
    cons.set_defaults(func=_cmd_sim_consistency)

    teach = simsub.add_parser(
        "teaching", help="what teaching buys: the teaching curve of the unseen classes, the "
        "familiarity's ROC AUC and teaching through the running daemon (exit 1 if the "
        "daemon's presses and the recorder's do not agree)")
    teach.add_argument("--classes", nargs="+", default=None,
                       help="unseen classes (default: the 26 FoodReplica and Cube classes)")
    teach.add_argument("--ks", nargs="+", type=int, default=[1, 2, 5],
                       help="presses taught per class")
    teach.add_argument("--fresh", type=int, default=5,
                       help="fresh presses per class looked up after teaching")
    teach.add_argument("--reference-presses", type=int, default=10,
                       help="presses per reference class for the trivial baseline")
    teach.add_argument("--held-out", type=int, default=5,
                       help="held-out presses per reference class (familiarity)")
    teach.add_argument("--e2e-classes", nargs="*", default=None,
                       help="classes taught through the running daemon (default: macaron "
                            "and boiled_kiri_mochi; none: skip it)")
    teach.add_argument("--seed", type=int, default=0)
    teach.add_argument("--workers", type=int, default=2, help="recorder processes")
    teach.add_argument("--only", default=None,
                       help="measure only this: familiarity (its ROC AUC; no teaching, no "
                            "daemon)")
    teach.add_argument("--models", default="models")
    config_option(teach, "configs/sim.toml")
    teach.add_argument("--out", default=None, help="write teaching.md/.json here")
    teach.set_defaults(func=_cmd_sim_teaching)

    fusion = simsub.add_parser(
        "fusion", help="press again and fuse, measured: top-3 consistency of recognitions of "
        "1 and 3 presses of the unseen classes (both fusions, the simulated VLM's accuracy) "
        "and the seconds per recognition on the running daemon")
    fusion.add_argument("--presses", type=int, default=15, help="recorder presses per class")
    fusion.add_argument("--daemon", type=int, default=5,
                        help="recognitions of 1 and of 3 presses timed on the daemon (0: none)")
    fusion.add_argument("--classes", nargs="+", default=None,
                        help="unseen classes (default: the 26 FoodReplica and Cube classes)")
    fusion.add_argument("--models", default="models")
    fusion.add_argument("--out", default=None, help="write fusion.md/.json here")
    fusion.set_defaults(func=_cmd_sim_fusion)

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


def _cmd_sim_consistency(args: argparse.Namespace) -> int:
    from edge.lab.consistency import run_consistency

    command = "vt-edge sim consistency " + " ".join(sys.argv[3:]) if len(sys.argv) > 3 else (
        "vt-edge sim consistency")
    report = run_consistency(args.objects, args.presses, args.dataset_presses, args.seed,
                             args.models, args.config, args.out, command=command.strip(),
                             runs=args.runs)
    print(report.markdown(command.strip()))
    return 0 if report.passed else 1


def _cmd_sim_teaching(args: argparse.Namespace) -> int:
    from edge.lab.teaching_eval import markdown, run_teaching

    command = " ".join(["vt-edge sim teaching", *sys.argv[3:]])
    report = run_teaching(args.classes, args.ks, args.fresh, args.reference_presses,
                          args.held_out, args.e2e_classes, args.seed, args.models, args.config,
                          args.out, command=command, workers=args.workers, only=args.only)
    print(markdown(report))
    e2e = report["end_to_end"]
    return 0 if e2e is None or e2e["agree"] else 1


def _cmd_sim_fusion(args: argparse.Namespace) -> int:
    from edge.lab.fusion_eval import run_fusion

    if args.presses < 3:
        raise EdgeError("--presses must be at least 3 (a recognition of 3 presses needs them)")
    command = " ".join(["vt-edge sim fusion", *sys.argv[3:]])
    print(run_fusion(args.models, args.presses, args.daemon, args.out, args.classes,
                     command=command), end="")
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
