"""``vt-edge doctor``: check every part of a robot's setup before its first press.

Each check gives one line: OK, WARN or FAIL, what was found and, unless OK, what to do. Nothing
moves: the Dynamixel bus is opened read-only (pings and register reads through the real
driver's owner thread; no goal, no torque), the pads are only listened to, the camera takes
one photo and the VLM gets one tiny question. ``--json`` gives the same lines as data.
"""

from __future__ import annotations

import asyncio
import enum
import getpass
import grp
import json
import logging
import os
import shutil
import stat
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import aiohttp
import numpy as np

from edge import SERVICE_NAME
from edge.app import vlm_config
from edge.core import preprocess
from edge.core.atomic import atomic_write_bytes
from edge.core.config import Config, SensorConfig, VLMConfig, load_config
from edge.core.errors import (
    ConfigError,
    DeviceError,
    EdgeError,
    ModelError,
    MotorError,
    PreprocessError,
    SensorLayoutError,
    VLMHTTPError,
)
from edge.core.model import (
    DEFAULT_WINDOW,
    Model,
    class_x_th,
    load_model,
    manifest_layout,
    model_ref,
    model_x_th,
    x_th_mismatch,
)
from edge.hw.contracts import StreamStats
from edge.hw.control_table import (
    MIN_FIRMWARE,
    MODE_CURRENT_BASED_POSITION,
    MODE_POSITION,
    describe_hardware_error,
)
from edge.hw.dynamixel import (
    LATENCY_TIMER_DIR,
    LATENCY_TIMER_UDEV_RULE,
    XM430_MODELS,
    DynamixelBus,
    latency_timer_path,
    read_latency_timer,
)
from edge.hw.xela import MAX_FRAME_CHARS, parse_frame, parse_layout_free
from edge.interfaces.http.api import MIN_TOKEN_CHARS, load_token
from edge.interfaces.mqtt import check_config, read_password, tls_context
from edge.ops.calibrate import NOISE_FLOOR_FACTOR
from edge.ops.hosttiming import MEASURE_S, HostTiming, measure
from edge.runtime.devices import make_button, make_camera
from edge.runtime.references import Overlay, ReferenceStore, references_dir
from edge.runtime.startcheck import BUILD_FOR_THESE_PADS, model_mismatch
from edge.runtime.store import MIN_FREE_BYTES as STORE_MIN_FREE_BYTES
from edge.runtime.store import EpisodeStore
from edge.vlm.client import OpenAIVLM
from edge.vlm.images import check_image
from edge.vlm.transport import is_loopback, load_api_key

log = logging.getLogger(__name__)

# How long the pads are listened to, after a tare as long as the press's, for the idle noise.
NOISE_WINDOW_S = 2.0
# How long a connected server may take to send its first data frame (the listening starts at
# it): a server still starting, or a busy host.
FIRST_FRAME_TIMEOUT_S = 2.0
NOISE_PERCENTILE = 99.9
# Below this rate the press refuses its tare (edge.runtime.press: 50 frames per second).
MIN_RATE_HZ = 50.0
# Free space under which the state directory (episodes, photos, MCAP) is short; below
# STORE_MIN_FREE_BYTES the daemon refuses every press.
LOW_FREE_BYTES = 1 << 30
SERIAL_BY_ID = Path("/dev/serial/by-id")
# HTTP statuses of a VLM server that wants another key (or one at all).
KEY_REFUSED = (401, 403)
DOCTOR_DIR = "doctor"
# While a part is slow to answer (a VLM taking 40 s), a line this often says which.
PROGRESS_EVERY_S = 5.0
# The sampler's period error (p99) past which the host is too busy for the 125 Hz path:
# a tick that late samples a frame 1/8 of a period off, and a stop waits as long.
LATE_P99_WARN_S = 1e-3
# With retention off, fewer days than this before the store fills its disk is a WARN.
STORE_DAYS_WARN = 7.0
# Mode bits that let the group or others read a secret.
READABLE_BY_OTHERS = 0o044


class Level(enum.StrEnum):
    OK = "OK"
    WARN = "WARN"
    FAIL = "FAIL"


@dataclass(frozen=True)
class Check:
    """One line of the report: which part, how it stands, what was found, what to do."""

    part: str
    level: Level
    found: str
    fix: str = ""
    data: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"part": self.part, "level": str(self.level), "found": self.found,
                "fix": self.fix, "data": self.data}


def ok(part: str, found: str, **data: Any) -> Check:
    return Check(part, Level.OK, found, "", data)


def warn(part: str, found: str, fix: str, **data: Any) -> Check:
    return Check(part, Level.WARN, found, fix, data)


def fail(part: str, found: str, fix: str, **data: Any) -> Check:
    return Check(part, Level.FAIL, found, fix, data)


@dataclass(frozen=True)
class Report:
    config: str
    checks: tuple[Check, ...]
    elapsed_s: float

    @property
    def failed(self) -> bool:
        return any(c.level is Level.FAIL for c in self.checks)

    def count(self, level: Level) -> int:
        return sum(c.level is level for c in self.checks)

    def table(self) -> str:
        width = max(len(c.part) for c in self.checks)
        lines = [f"vt-edge doctor: {self.config}"]
        for c in self.checks:
            line = f"{c.level:<4}  {c.part:<{width}}  {c.found}"
            lines.append(f"{line}  -> {c.fix}" if c.fix else line)
        lines.append(f"{self.count(Level.OK)} OK, {self.count(Level.WARN)} WARN, "
                     f"{self.count(Level.FAIL)} FAIL in {self.elapsed_s:.1f} s; nothing moved"
                     + ("" if not self.failed else ": fix every FAIL before the first press"))
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        return {"config": self.config, "ok": not self.failed,
                "counts": {str(lv): self.count(lv) for lv in Level},
                "elapsed_s": round(self.elapsed_s, 3),
                "checks": [c.to_json() for c in self.checks]}


Progress = Callable[[str], None]


def to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


async def run_doctor(cfg: Config, config_path: str = "<config>", *,
                     noise_window_s: float = NOISE_WINDOW_S, timing_s: float = MEASURE_S,
                     progress: Progress | None = None,
                     progress_every_s: float = PROGRESS_EVERY_S) -> Report:
    """Every check of ``cfg``; the slow ones (the pads' noise, the VLM) run side by side,
    then the host's timing for ``timing_s`` alone (the doctor's own work would disturb
    it). ``progress`` gets a line every ``progress_every_s`` while a part has not
    answered."""
    started = time.monotonic()
    state = Path(cfg.runtime.state_dir)
    vlm, vlm_checks = _vlm_client(cfg)
    needs_photo = vlm is not None and vlm.template.uses_image
    try:
        groups = await _all_parts({
            "bus": _check_bus(cfg),
            "xela server": _check_xela(cfg, noise_window_s),
            "camera": _check_camera(cfg, state, needs_photo),
            "vlm": _check_vlm(vlm, vlm_checks),
            "model": asyncio.to_thread(_check_model, cfg),
            "mqtt": _check_mqtt(cfg),
            "button": _check_button(cfg),
            "store": asyncio.to_thread(_check_store, cfg),
        }, started, progress, progress_every_s)
    finally:
        if vlm is not None:
            await vlm.close()
    groups += await _all_parts({"host timing": _check_timing(cfg, timing_s)}, started,
                               progress, progress_every_s)
    checks = [c for group in groups for c in group]
    if any(c.part == "xela layout" and c.level is Level.FAIL for c in checks):
        # [sensor] is not what the server sends: that is the cause, and a model that does
        # not fit the wrong setting no second one.
        checks = [c for c in checks if c.part != MODEL_PADS]
    checks += [_check_state_dir(state), _check_api(cfg)]
    return Report(config_path, tuple(checks), time.monotonic() - started)


async def _all_parts(parts: dict[str, Coroutine[Any, Any, list[Check]]], started: float,
                     progress: Progress | None, every_s: float) -> list[list[Check]]:
    """Each part's lines, the parts run side by side; while some have not answered,
    ``progress`` hears which every ``every_s``."""
    tasks = {asyncio.ensure_future(_guard(part, coro)): part for part, coro in parts.items()}
    try:
        pending = set(tasks)
        while pending:
            _, pending = await asyncio.wait(pending, timeout=every_s)
            if pending and progress is not None:
                waiting = ", ".join(tasks[t] for t in tasks if t in pending)
                progress(f"doctor: waiting for {waiting} "
                         f"({time.monotonic() - started:.0f} s so far)")
    finally:
        for task in tasks:
            task.cancel()
    return [task.result() for task in tasks]


async def _guard(part: str, checks: Awaitable[list[Check]]) -> list[Check]:
    """A check that breaks is one FAIL line, not the end of the report."""
    try:
        return await checks
    except Exception as exc:
        log.debug("check %s", part, exc_info=True)
        return [fail(part, f"the check itself failed: {type(exc).__name__}: {exc}",
                     "run `vt-edge -v doctor` for the traceback and report it")]


# ------------------------------------------------------------------------------- the bus


def _port_problem(port: str) -> Check | None:
    """Why ``port`` cannot be opened, before trying: missing, or not ours to use."""
    path = Path(port)
    if not path.exists():
        present = sorted(p.name for p in SERIAL_BY_ID.glob("*")) if SERIAL_BY_ID.is_dir() else []
        seen = (f"{SERIAL_BY_ID}/ holds {', '.join(present)}" if present
                else f"{SERIAL_BY_ID}/ lists no USB serial adapter")
        return fail("bus port", f"{port} does not exist ({seen})",
                    "plug in the U2D2 and set bus.port to its /dev/serial/by-id/ path, or to "
                    "/dev/ttyDXL after `vt-edge install-udev --install` (names stable across "
                    "reboots and plug order)")
    if not os.access(path, os.R_OK | os.W_OK):
        st = path.stat()
        try:
            group = grp.getgrgid(st.st_gid).gr_name
        except KeyError:
            group = str(st.st_gid)
        member = st.st_gid in os.getgroups()
        user = getpass.getuser()
        found = (f"{port}: permission denied (group {group}, mode {stat.filemode(st.st_mode)}); "
                 f"user {user} is {'' if member else 'not '}in group {group}")
        fix = (f"sudo usermod -aG {group} {user}, then log in again (the service: "
               f"SupplementaryGroups={group})" if not member else
               f"give group {group} read and write on the device (udev rule "
               f'MODE="0660", GROUP="{group}")')
        return fail("bus port", found, fix)
    return None


def _by_id_name(port: str) -> str | None:
    """The /dev/serial/by-id/ link to ``port`` when ``port`` is the kernel's name
    (``ttyUSBn``, given in plug order), not a stable link (by-id, a udev rule's alias)."""
    if not SERIAL_BY_ID.is_dir() or Path(port).is_symlink():
        return None
    target = os.path.realpath(port)
    for link in sorted(SERIAL_BY_ID.iterdir()):
        if os.path.realpath(link) == target:
            return str(link)
    return None


def _check_latency(port: str, timer_dir: Path = LATENCY_TIMER_DIR) -> Check:
    path = latency_timer_path(port, timer_dir)
    try:
        value = read_latency_timer(path)
    except (OSError, ValueError) as exc:
        return warn("bus latency", f"cannot read {path}: {exc}",
                    f"check it by hand: cat {path} (1 ms is right)")
    if value is None:
        return ok("bus latency", "not a USB serial adapter: no latency timer")
    if value != 1:
        return warn("bus latency", f"USB latency timer {value} ms: up to {value} ms added to "
                    "every reply, the stop included",
                    f"echo 1 | sudo tee {path}; for good: the udev rule "
                    f"{LATENCY_TIMER_UDEV_RULE} (vt-edge install-udev --install)",
                    latency_timer_ms=value)
    return ok("bus latency", "USB latency timer 1 ms", latency_timer_ms=value)


async def _check_bus(cfg: Config) -> list[Check]:
    bc = cfg.bus
    ids = (*bc.joint_ids, bc.gripper_id)
    problem = _port_problem(bc.port)
    if problem is not None:
        return [problem]
    bus = DynamixelBus(bc)
    try:
        await bus.connect(configure=False)
    except DeviceError as exc:
        return [fail("bus port", str(exc), "where another program holds the port, stop it "
                     f"(the daemon: systemctl stop {SERVICE_NAME}); else check bus.port and "
                     "bus.baudrate (1000000 for the OpenMANIPULATOR-X)")]
    try:
        by_id = _by_id_name(bc.port)
        checks = [warn("bus port", f"{bc.port} opens at {bc.baudrate} bps, but its name follows "
                       "plug order", f"set bus.port = {by_id!r}") if by_id else
                  ok("bus port", f"{bc.port} opens at {bc.baudrate} bps"),
                  _check_latency(bc.port)]
        motors = [await _check_motor(bus, cfg, motor_id) for motor_id in ids]
        checks += motors
        if any(c.data.get("answered") is False for c in motors):
            # Which IDs are there after all: a wrong ID or baud rate shows at once.
            found = await bus.scan()
            answering = ", ".join(map(str, found)) or "none"
            checks.append(
                fail("bus scan", f"motors answering a broadcast ping at {bc.baudrate} bps: "
                     f"{answering}; configured {', '.join(map(str, ids))}",
                     "set bus.joint_ids and bus.gripper_id to the IDs on the bus" if found else
                     "power the arm (12 V), check the cable, or set bus.baudrate to the motors' "
                     "(Dynamixel Wizard 2 scans every rate)", answering=list(found)))
        return checks
    finally:
        await bus.close()


async def _check_motor(bus: DynamixelBus, cfg: Config, motor_id: int) -> Check:
    part = f"motor {motor_id}"
    gripper = motor_id == cfg.bus.gripper_id
    try:
        model = await bus.ping(motor_id)
        regs = {name: await bus.read(motor_id, name) for name in (
            "Firmware Version", "Operating Mode", "Hardware Error Status", "Torque Enable",
            "Bus Watchdog", "Current Limit")}
    except MotorError as exc:
        if "did not answer" in str(exc):
            return fail(part, f"{'gripper' if gripper else 'joint'} {exc}",
                        "check the motor's power and cable, its ID (bus.joint_ids, "
                        "bus.gripper_id) and baud rate (bus.baudrate)", answered=False)
        # A motor in alarm answers every read with its Hardware Error Status.
        return fail(part, str(exc), "remove the cause (load, heat, voltage), then power-cycle "
                    "the arm or reboot the motor in Dynamixel Wizard 2")
    firmware = regs["Firmware Version"]
    mode = regs["Operating Mode"]
    want_mode = MODE_CURRENT_BASED_POSITION if gripper else MODE_POSITION
    name = XM430_MODELS.get(model, f"model {model}")
    data = {"model_number": model, "firmware": firmware, "operating_mode": mode,
            "hardware_error": regs["Hardware Error Status"], "torque": regs["Torque Enable"],
            "bus_watchdog": regs["Bus Watchdog"], "current_limit": regs["Current Limit"]}
    found = (f"{name} firmware {firmware}, operating mode {mode}"
             + ("" if mode == want_mode else f" (the daemon sets {want_mode} at start)")
             + f", torque {'on' if regs['Torque Enable'] else 'off'}, Bus Watchdog "
             f"{regs['Bus Watchdog']}, hardware error "
             f"{describe_hardware_error(regs['Hardware Error Status'])}")
    if regs["Hardware Error Status"]:
        return fail(part, found, "remove the cause, then power-cycle the arm or reboot the "
                    "motor in Dynamixel Wizard 2", **data)
    if firmware < MIN_FIRMWARE:
        return fail(part, found, f"update the firmware to {MIN_FIRMWARE} or later (Dynamixel "
                    "Wizard 2: the Bus Watchdog the daemon arms is missing before it)", **data)
    if gripper and cfg.bus.gripper_goal_current > regs["Current Limit"]:
        return fail(part, found + f"; Current Limit {regs['Current Limit']}",
                    f"lower bus.gripper_goal_current ({cfg.bus.gripper_goal_current}) to at "
                    f"most {regs['Current Limit']}", **data)
    if model not in XM430_MODELS:
        return warn(part, found, "the driver is written for the XM430 "
                    f"({', '.join(XM430_MODELS.values())}): check this model's control table",
                    **data)
    if regs["Torque Enable"]:
        return warn(part, found, "another program holds the arm (a running vt-edge run?): "
                    "stop it before the first press; two programs on one bus collide", **data)
    if regs["Bus Watchdog"] == -1:
        return warn(part, found + " (tripped)", "nothing to do: the daemon clears the trip "
                    "at start (an earlier run's host went silent on the bus)", **data)
    return ok(part, found, **data)


# ------------------------------------------------------------------------------ the pads


@dataclass
class _Sample:
    """What the pads sent while listened to."""

    dialect: str = ""
    frames: list[tuple[float, Any]] = field(default_factory=list)  # (receive time, parsed)
    malformed: list[str] = field(default_factory=list)
    first: Any = None  # the first data frame's text


def _dialect(obj: dict[str, Any]) -> str:
    """Which xela_server speaks: 1.8 names its version; 1.7.7 sends ints, 1.7 hex."""
    version = obj.get("version")
    if isinstance(version, str):
        return f"xela_server {version}"
    sensor = next((v for k, v in obj.items() if isinstance(k, str) and k.isdecimal()), None)
    data = sensor.get("data") if isinstance(sensor, dict) else None
    if isinstance(data, list):
        return "xela_server 1.7.7 (data as ints)"
    if isinstance(data, str):
        return "xela_server 1.7 (data as hex)"
    return ""


async def _listen(sc: SensorConfig, duration_s: float) -> _Sample:
    sample = _Sample()
    timeout = aiohttp.ClientTimeout(total=None, connect=sc.connect_timeout_s)
    loop = asyncio.get_running_loop()
    async with aiohttp.ClientSession(timeout=timeout) as session:
        async with asyncio.timeout(sc.connect_timeout_s):
            ws = await session.ws_connect(sc.url, max_msg_size=MAX_FRAME_CHARS)
        async with ws:
            # The window starts at the first data frame: on a busy host, or a server still
            # starting, that frame can come later than the window is long.
            deadline = loop.time() + FIRST_FRAME_TIMEOUT_S
            while (left := deadline - loop.time()) > 0:
                try:
                    msg = await ws.receive(timeout=left)
                except TimeoutError:
                    break
                if msg.type not in (aiohttp.WSMsgType.TEXT, aiohttp.WSMsgType.BINARY):
                    break
                recv = time.monotonic()
                try:
                    frame = parse_layout_free(msg.data)
                except EdgeError as exc:
                    sample.malformed.append(str(exc))
                    continue
                if frame is None:
                    continue
                if sample.first is None:
                    deadline = loop.time() + duration_s
                    sample.first = msg.data
                    # (Read as leniently as the parser reads it.)
                    sample.dialect = _dialect(json.loads(msg.data, strict=False))
                sample.frames.append((recv, frame))
    return sample


def _expected_rate(cfg: Config) -> tuple[float, str]:
    """The rate the model's input grid assumes (the manifest's window), and where from."""
    try:
        return model_ref(cfg.runtime.models_dir).window.rate_hz, "the model's grid"
    except ModelError:
        return DEFAULT_WINDOW.rate_hz, "the default grid"


async def _check_xela(cfg: Config, noise_window_s: float) -> list[Check]:
    sc = cfg.sensor
    try:
        sample = await _listen(sc, cfg.press.tare_s + noise_window_s)
    except (aiohttp.ClientError, OSError, TimeoutError) as exc:
        why = str(exc) or f"no answer within {sc.connect_timeout_s} s"
        return [fail("xela server", f"cannot connect to {sc.url}: {why}",
                     "start xela_server on the robot computer (and its pads' USB-CAN adapter), "
                     "and check sensor.url")]
    if not sample.frames:
        seen = f"; {len(sample.malformed)} malformed: {sample.malformed[0]}" \
            if sample.malformed else ""
        return [fail("xela server", f"{sc.url} accepts the connection but sent no data frame "
                     f"in {FIRST_FRAME_TIMEOUT_S:g} s{seen}",
                     "check that xela_server sees its pads (its own log, xela_viz)")]
    server = (ok("xela server", f"{sample.dialect} at {sc.url}", dialect=sample.dialect)
              if sample.dialect else
              warn("xela server", f"{sc.url} sends frames of an unknown xela_server version",
                   "check the frames against docs/hardware.md 'XELA server'"))
    return [server, _check_layout(cfg, sample), _check_rate(cfg, sample),
            _check_noise(cfg, sample)]


def _check_layout(cfg: Config, sample: _Sample) -> Check:
    sc = cfg.sensor
    frame = sample.frames[0][1]
    data = {"sensors": list(frame.sensors), "models": list(frame.models),
            "taxels": list(frame.taxels)}
    try:
        # The daemon's own check of the first frame (pads, taxels and the model the server
        # names: `vt-edge run` refuses to start on the same).
        parse_frame(sample.first, sc.pads, sc.taxels_per_pad, expected_model=sc.model)
        return ok("xela layout", frame.describe(), **data)
    except SensorLayoutError:
        pass
    # A server that does not name its model ("?") is taken at its layout.
    other_models = [m for m in frame.models if m != "?" and m.casefold() != sc.model.casefold()]
    found = (f"configured {sc.pads} x {sc.model} ({sc.taxels_per_pad} taxels each), the "
             f"server sends {frame.describe()}")
    if len(frame.sensors) != sc.pads:
        fix = (f"connect every pad and list it in xela_server's configuration, or set "
               f"sensor.pads = {len(frame.sensors)}")
    elif any(n != sc.taxels_per_pad for n in frame.taxels):
        fix = (f"set sensor.taxels_per_pad = {frame.taxels[0]} (and sensor.taxel_rows to the "
               f"rows of its grid) and sensor.model = "
               f"{frame.models[0]!r} if that is the hardware, or fix xela_server's "
               "configuration")
    else:
        fix = (f"set sensor.model = {other_models[0]!r} if that is the hardware (x_th and the "
               "references belong to one sensor model), or fix xela_server's configuration")
    return fail("xela layout", found, fix, **data)


def _check_rate(cfg: Config, sample: _Sample) -> Check:
    stats = StreamStats()
    fresh = [t for t, frame in sample.frames if stats.observe(frame.seq, frame.time)]
    span = fresh[-1] - fresh[0] if len(fresh) > 1 else 0.0
    received = (len(fresh) - 1) / span if span > 0 else 0.0
    # The rate xela_server is set to (the median interval on its clock), which a busy host
    # does not move; what arrives, for the press's own floor.
    rate = preprocess.fresh_rate(*zip(*((t, f.time, f.seq) for t, f in sample.frames),
                                      strict=True)) or 0.0
    expected, source = _expected_rate(cfg)
    data = {"rate_hz": round(rate, 1), "received_hz": round(received, 1),
            "expected_hz": expected, "repeats": stats.repeats, "lost": stats.lost,
            "malformed": len(sample.malformed)}
    found = (f"{rate:.1f} frames/s sent, {received:.1f} fresh frames/s received (expected "
             f"{expected:g}: {source}), {stats.repeats} repeated, {stats.lost} lost, "
             f"{len(sample.malformed)} malformed")
    if min(rate, received) < MIN_RATE_HZ:
        return fail("xela rate", found, f"the press needs at least {MIN_RATE_HZ:g} frames/s: "
                    "check xela_server's rate setting and the CAN adapter's load", **data)
    off = preprocess.rate_problem(rate, expected)
    if off is not None:
        return warn("xela rate", found, f"{off} ({source}), the rate its references were "
                    f"pressed at: {preprocess.RATE_SETTING}; or build a model from presses at "
                    "this rate", **data)
    if stats.repeats or sample.malformed:
        return warn("xela rate", found, "check xela_server's configuration and the computer's "
                    "load: the model's input is interpolated between frames", **data)
    return ok("xela rate", found, **data)


def _check_noise(cfg: Config, sample: _Sample) -> Check:
    x_th = cfg.press.x_th
    times = np.array([t for t, _ in sample.frames])
    sizes = {f.raw.shape for _, f in sample.frames}
    if len(sizes) != 1:
        return fail("idle noise", "the frames change layout while listened to",
                    "check xela_server's pads (a loose connector?)")
    raw = np.stack([f.raw for _, f in sample.frames])
    try:
        norms = preprocess.tared_norms(times, raw, cfg.press.tare_s)
    except PreprocessError as exc:
        return fail("idle noise", str(exc), "see xela rate: the stream is too slow")
    p = float(np.percentile(norms, NOISE_PERCENTILE))
    # Below the floor `vt-edge calibrate threshold` keeps, drift and the pads' slow wander
    # cross the threshold.
    safe = NOISE_FLOOR_FACTOR * p
    data = {"p999": p, "max": float(norms.max()), "frames": int(norms.size), "x_th": x_th,
            "margin": x_th / p if p > 0 else None, "safe_x_th": safe}
    found = (f"idle norm p{NOISE_PERCENTILE:g} {p:.5f}, max {norms.max():.5f} over "
             f"{norms.size} frames; press.x_th = {x_th:g} is "
             + (f"{x_th / p:.1f} x the p{NOISE_PERCENTILE:g}" if p > 0 else "above a silent pad"))
    if x_th <= p:
        return fail("idle noise", found + ": inside the noise, the press would stop on air",
                    f"raise press.x_th above {safe:.4f} ({NOISE_FLOOR_FACTOR:g} x the idle "
                    f"p{NOISE_PERCENTILE:g}); `vt-edge calibrate threshold` finds one", **data)
    if x_th < safe:
        return warn("idle noise", found, f"raise press.x_th to at least {safe:.4f} "
                    f"({NOISE_FLOOR_FACTOR:g} x the idle p{NOISE_PERCENTILE:g}): drift or a nudge "
                    "would cross it", **data)
    return ok("idle noise", found, **data)


# ---------------------------------------------------------------------------- the camera


async def _check_camera(cfg: Config, state: Path, needs_photo: bool) -> list[Check]:
    cc = cfg.camera
    why = f"vlm.mode = {cfg.vlm.mode!r} needs a photo"
    try:
        camera = make_camera(cfg)
        if camera is None:
            if needs_photo:
                return [fail("camera", f"camera.kind = 'none' but {why}",
                             "configure [camera] (kind = command, v4l2 or http), or set "
                             "vlm.mode = 'tactile_only'")]
            return [ok("camera", "none configured (no VLM question needs a photo)")]
        data = await camera.capture()
        fmt, width, height = await asyncio.to_thread(check_image, data)
    except EdgeError as exc:
        fix = {"command": f"run it by hand ({cc.command!r} with a file for {{out}}), install "
                          "it or fix camera.command",
               "v4l2": f"check {cc.device} (ls -l; the video group) and the camera extra",
               "http": f"open {cc.url} in a browser; check camera.url"}[cc.kind]
        level = fail if needs_photo else warn
        return [level("camera", f"camera.kind = {cc.kind!r}: {exc}"
                      + (f" ({why})" if needs_photo else ""), fix)]
    kept = state / DOCTOR_DIR / f"camera.{'png' if fmt == 'PNG' else 'jpg'}"
    try:
        await asyncio.to_thread(_keep, kept, data)
        where = f"kept at {kept}"
    except OSError as exc:
        where = f"not kept ({kept}: {exc.strerror or exc})"
    return [ok("camera", f"{fmt} {width} x {height}, {len(data) / 1024:.0f} KiB, {where}",
               width=width, height=height, bytes=len(data), path=str(kept))]


def _keep(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, data)


# ------------------------------------------------------------------------------- the VLM


def _vlm_client(cfg: Config) -> tuple[OpenAIVLM | None, list[Check]]:
    """The configured VLM client (None without one), or the line saying why there is
    none."""
    try:
        vc = vlm_config(cfg)
        if not vc.configured:
            if cfg.mode == "robot":
                return None, [warn("vlm", "none configured: every recognition ends "
                                   "not_configured, with the prompt it would have sent",
                                   "set vlm.base_url and vlm.model (or $VTZERO_VLM_URL "
                                   "and $VTZERO_VLM_MODEL)")]
            return None, [ok("vlm", "none configured: recognitions store the prompt")]
        return OpenAIVLM(vc), []
    except EdgeError as exc:
        return None, [fail("vlm", str(exc), "fix [vlm]")]


def _key_refused(vc: VLMConfig, keyed: bool, exc: Exception) -> Check:
    return fail("vlm key", f"{vc.base_url} refuses "
                + ("the key" if keyed else "a request without a key") + f": {exc}",
                f"set ${vc.api_key_env} or vlm.api_key_file to a key the server accepts")


async def _check_vlm(vlm: OpenAIVLM | None, checks: list[Check]) -> list[Check]:
    if vlm is None:
        return checks
    vc = vlm.config
    host = urlsplit(vc.base_url).hostname or ""
    keyed = load_api_key(vc) is not None
    key = (ok("vlm key", "present" if keyed else f"none needed: {host} is this machine")
           if keyed or is_loopback(host) else
           warn("vlm key", f"no API key for {host}, which is not this machine",
                f"a lab server without keys needs none; otherwise set ${vc.api_key_env} or "
                "vlm.api_key_file"))
    try:
        models = await vlm.list_models()
    except VLMHTTPError as exc:
        if exc.status in KEY_REFUSED:
            return [_key_refused(vc, keyed, exc)]
        return [fail("vlm server", str(exc), "check vlm.base_url: the server's /v1 root"), key]
    except EdgeError as exc:
        return [fail("vlm server", f"{vc.base_url}: {exc}",
                     "start the server, or fix vlm.base_url (it ends in /v1)"), key]
    if models is None:
        listed = ok("vlm server", f"{vc.base_url} answers (it serves no GET /models)")
    elif vc.model in models:
        listed = ok("vlm server", f"{vc.base_url} serves {vc.model!r}", models=models)
    else:
        return [fail("vlm server", f"{vc.base_url} does not serve {vc.model!r}; it serves "
                     f"{', '.join(models[:10]) or 'nothing'}",
                     "set vlm.model to one of them (Ollama: `ollama pull NAME` first)",
                     models=models), key]
    try:
        probe = await vlm.probe()
    except VLMHTTPError as exc:
        if exc.status in KEY_REFUSED:
            return [listed, _key_refused(vc, keyed, exc)]
        return [listed, key, fail("vlm probe", str(exc), "see the server's log")]
    except EdgeError as exc:
        return [listed, key, fail("vlm probe", str(exc), "see the server's log; check "
                                  "vlm.model and the key")]
    data = {"structured_output": probe.structured_output, "latency_s": probe.latency_s,
            "label": probe.label, "fallbacks": list(probe.fallbacks)}
    found = (f"a tiny question answered in {probe.latency_s:.2f} s with structured output "
             f"{probe.structured_output!r}")
    # Each mode the server refused or ignored, and why (VLMProbe.reasons).
    found += "".join(f"; {mode} {why}" for mode, why in
                     zip(probe.fallbacks, probe.reasons, strict=False))
    if probe.label is None:  # the daemon's own answer reader: the same verdict
        return [listed, key, warn("vlm probe", f"{found}; its answer {probe.raw[:80]!r} is "
                                  "none of the candidates: recognitions would end "
                                  "invalid_answer",
                                  f"try another model than {vc.model!r}, or a server that "
                                  "honours response_format", **data)]
    if probe.fallbacks:
        return [listed, key, warn("vlm probe", found,
                                  f"set vlm.structured_output = {probe.structured_output!r}: "
                                  "the client steps down by itself, but asks in vain first "
                                  "every session", **data)]
    return [listed, key, ok("vlm probe", found, **data)]


# ------------------------------------------------------------------------------ the rest


MODEL_PADS = "model pads"


def _check_model(cfg: Config) -> list[Check]:
    directory = cfg.runtime.models_dir
    try:
        model: Model = load_model(directory)
    except ModelError as exc:
        return [fail("model", str(exc), "put a released model directory at "
                     f"runtime.models_dir ({directory})")]
    db = model.database
    checks = [ok("model", f"{Path(directory).resolve()}: every file verified, "
                 f"{len(db.classes)} classes, {len(db)} references", digest=model.digest)]
    why = model_mismatch(cfg.sensor, manifest_layout(model.manifest))
    if why is not None:
        checks.append(fail(MODEL_PADS, f"the model {why}", BUILD_FOR_THESE_PADS))
    checks.append(_check_x_th(cfg, model))
    checks.append(_check_taught(cfg, model))
    origin = model.origin
    data = {"origin": origin.to_json()}
    if origin.emulated:
        found = f"the reference database was pressed by the emulated robot ({origin.recorder})"
        if cfg.mode == "robot":
            checks.append(warn("references", found, "collect this lab's references with the "
                               "robot (`vt-edge collect`, README 'Your own references') and "
                               "build a database from them; until then recognitions compare "
                               "real presses with simulated ones", **data))
        else:
            checks.append(ok("references", found, **data))
        return checks
    where = f" ({origin.robot})" if origin.robot else ""
    found = f"pressed by a real robot{where}: {origin.recorder}"
    if origin.sensor_model and origin.sensor_model != cfg.sensor.model:
        checks.append(warn("references", found + f", with {origin.sensor_model} pads",
                           f"sensor.model is {cfg.sensor.model!r}: collect references with "
                           "these pads", **data))
    else:
        checks.append(ok("references", found, **data))
    return checks


def _check_taught(cfg: Config, model: Model) -> Check:
    """The references taught beside the model: readable, and embedded by this model (those
    another model embedded are kept but never used: the daemon recognises without them)."""
    store = ReferenceStore(references_dir(cfg.runtime.state_dir))
    if not store.root.is_dir():  # (a state directory that cannot be one is its own check's)
        return ok("taught references", "none taught", current=0, stale=0)
    try:
        digest, refs = store.read()
    except ModelError as exc:
        return fail("taught references", str(exc), "the daemon refuses to start with them: "
                    "restore the file, or move it aside to start without taught references")
    overlay = Overlay.of(store.index, digest, refs, model.digest)
    labels = sorted({r.label for r in overlay.current})
    found = (f"{len(overlay.current)} taught presses of {len(labels)} objects "
             f"({', '.join(labels)})" if labels else "none taught")
    data = {"current": len(overlay.current), "stale": len(overlay.stale)}
    if overlay.stale:
        stale = ", ".join(sorted({r.label for r in overlay.stale}))
        return warn("taught references", f"{found}; {len(overlay.stale)} embedded by another "
                    f"model are not used ({stale})", "teach those objects again (`vt-edge "
                    "teach`), or fold them into the next build (`vt-edge references export "
                    "DIR`, then `vt-train build`)", **data)
    return ok("taught references", found, **data)


def _check_x_th(cfg: Config, model: Model) -> Check:
    """press.x_th against the threshold the model's references were pressed at."""
    x_th = cfg.press.x_th
    reference = model_x_th(class_x_th(model.manifest))
    if reference is None:
        return ok("x_th", f"press.x_th = {x_th:g}; the model records no threshold of its "
                  "references to compare with", x_th=x_th)
    data = {"x_th": x_th, "model_x_th": reference}
    why = x_th_mismatch(x_th, reference)
    if why is not None:
        return warn("x_th", why, f"set press.x_th = {reference:g}, or build a model from "
                    "presses at this robot's calibrated x_th (`vt-edge collect`, `vt-train "
                    "build`)", **data)
    return ok("x_th", f"press.x_th = {x_th:g}, the model's references were pressed at "
              f"{reference:g}", **data)


def _check_state_dir(state: Path) -> Check:
    existing = state
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return fail("state dir", f"{state}: {existing} is not a directory",
                    "set runtime.state_dir to a directory path")
    try:
        with tempfile.NamedTemporaryFile(dir=existing, prefix=".vtzero-doctor-"):
            pass
    except OSError as exc:
        return fail("state dir", f"{state}: cannot write in {existing} "
                    f"({exc.strerror or exc})", "run the doctor as the daemon's user "
                    "(sudo -u vtzero vt-edge doctor ...), chown the directory to that user, "
                    "or set runtime.state_dir")
    free = shutil.disk_usage(existing).free
    made = "" if existing == state else f" (created at start, in {existing})"
    found = f"{state} writable{made}, {_size(free)} free"
    if free < STORE_MIN_FREE_BYTES:
        return fail("state dir", found + f": the daemon refuses every press below "
                    f"{_size(STORE_MIN_FREE_BYTES)}", "free space on its filesystem (old "
                    "episodes, MCAP segments), or set runtime.state_dir to a larger one",
                    free_bytes=free, floor_bytes=STORE_MIN_FREE_BYTES)
    if free < LOW_FREE_BYTES:
        return warn("state dir", found, "free space: each recognition keeps its press and "
                    "photo, MCAP recording far more", free_bytes=free)
    return ok("state dir", found, free_bytes=free)


def _check_store(cfg: Config) -> list[Check]:
    """The episode store's size and growth, and the days that leaves (the daemon's own
    store, as `vt-edge run` opens it, its retention included)."""
    rc = cfg.runtime
    root = Path(rc.state_dir) / "episodes"
    if not root.is_dir():
        return [ok("store", f"no episodes yet ({root} is made at the first start)")]
    store = EpisodeStore(root, max_bytes=round(rc.store_max_mb * 1e6),
                         keep_free_bytes=round(rc.keep_free_mb * 1e6),
                         segments=rc.record_mcap_dir or None)
    u = store.usage()
    data = {"bytes": u.bytes, "episodes": u.episodes, "bytes_per_day": u.bytes_per_day,
            "days_left": u.days_left}
    found = f"{u.episodes} episodes, {_size(u.bytes)}"
    retention = bool(store.max_bytes or store.keep_free_bytes)
    if u.bytes_per_day is None or u.days_left is None:
        return [ok("store", found + ", none in the last days", **data)]
    found += (f", {_size(round(u.bytes_per_day))} a day lately: {u.days_left:.0f} days before "
              + ("retention removes the oldest finished episodes" if retention else
                 "its disk is full (retention off)"))
    if not retention and u.days_left < STORE_DAYS_WARN:
        return [warn("store", found, "set [runtime] store_max_mb or keep_free_mb (the oldest "
                     "finished episodes and MCAP segments go first), or free space", **data)]
    return [ok("store", found, **data)]


def _size(n: int) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


def _check_api(cfg: Config) -> Check:
    ac = cfg.api
    try:
        token = load_token(ac)
    except ConfigError as exc:
        return fail("api", str(exc), "bind api.host = '127.0.0.1', or put a token of "
                    f"{MIN_TOKEN_CHARS}+ characters in api.token_file")
    if ac.loopback_only:
        found = f"bound to {ac.host}:{ac.port}, this machine only" + (
            " (a token is set too)" if token else "")
    else:
        found = (f"bound to {ac.host}:{ac.port} with a bearer token of {len(token)} "
                 f"characters (at least {MIN_TOKEN_CHARS})")
    mode = Path(ac.token_file).stat().st_mode & 0o777 if ac.token_file else 0
    if mode & READABLE_BY_OTHERS:
        # Anyone who can log in to this computer could drive the arm with it.
        level = warn if ac.loopback_only else fail
        return level("api", f"{found}; api.token_file {ac.token_file} is readable by "
                     f"{'others' if mode & 0o004 else 'its group'} (mode {mode:o})",
                     f"chmod 600 {ac.token_file} (owned by the daemon's user)", mode=mode)
    return ok("api", found)


async def _check_button(cfg: Config) -> list[Check]:
    """The daemon's own opening of the button (a serial port's modem lines, a GPIO line),
    closed again at once; what it refuses at start fails here."""
    bc = cfg.button
    if bc.kind == "none":
        return [ok("button", "none configured (recognitions come from the API)")]
    where = f"{bc.port} {bc.line.upper()}" if bc.kind == "serial" else f"{bc.chip} line {bc.line}"
    try:
        button = await asyncio.to_thread(make_button, cfg)
    except DeviceError as exc:
        fix = ("check button.port (ls -l; the dialout group); a serial button needs a port "
               "with modem lines (a USB-serial adapter), else use [button] kind = \"gpio\""
               if bc.kind == "serial" else
               "check button.chip and button.line (gpioinfo), the gpio group, and the gpio "
               "extra (pip install 'vtzero[gpio]')")
        return [fail("button", str(exc), fix)]
    await button.close()
    return [ok("button", f"{bc.kind} {where} opens and reads")]


async def _check_timing(cfg: Config, duration_s: float) -> list[Check]:
    t: HostTiming = await asyncio.to_thread(measure, cfg, duration_s)
    data = {"sampler_late_p50_ms": 1e3 * t.late_p50_s, "sampler_late_p99_ms": 1e3 * t.late_p99_s,
            "sampler_late_max_ms": 1e3 * t.late_max_s, "ticks": t.ticks,
            "missed_ticks": t.missed_ticks, "stop_p50_ms": 1e3 * t.stop_p50_s,
            "stop_p99_ms": 1e3 * t.stop_p99_s, "stop_max_ms": 1e3 * t.stop_max_s,
            "stops": t.stops, "realtime_applied": t.realtime_applied,
            "realtime_refused": t.realtime_refused}
    rt = ("on" if t.realtime_applied else
          "allowed, off" if t.realtime_refused is None else f"refused ({t.realtime_refused})")
    found = (f"125 Hz sampler period error p99 {1e3 * t.late_p99_s:.2f} ms (p50 "
             f"{1e3 * t.late_p50_s:.2f}, max {1e3 * t.late_max_s:.1f}; {t.missed_ticks} of "
             f"{t.ticks} ticks missed); frame to Goal Position write p50 "
             f"{1e3 * t.stop_p50_s:.2f} / p99 {1e3 * t.stop_p99_s:.2f} ms ({t.stops} stops "
             f"on a loopback port); real-time scheduling {rt}")
    if t.late_p99_s <= LATE_P99_WARN_S and not t.missed_ticks:
        return [ok("host timing", found, **data)]
    free_cpu = ("keep a CPU free for the daemon (boot with isolcpus=N, set [runtime] "
                "realtime_cpu = N) or move other work off this computer")
    if t.realtime_applied:
        fix = free_cpu
    elif t.realtime_refused is None:
        fix = f"set [runtime] realtime = true (docs/hardware.md 'Real-time scheduling'); {free_cpu}"
    else:
        fix = ("allow real-time scheduling (the service: `vt-edge install-service` writes "
               "LimitRTPRIO= once the config sets realtime = true; a shell: root or "
               f"CAP_SYS_NICE), set [runtime] realtime = true; {free_cpu}")
    return [warn("host timing", found + f": past {1e3 * LATE_P99_WARN_S:g} ms, presses stop "
                 "late and overshoot", fix, **data)]


async def _check_mqtt(cfg: Config) -> list[Check]:
    mc = cfg.mqtt
    if not mc.enabled:
        return [ok("mqtt", "disabled")]
    try:
        import aiomqtt
    except ImportError:
        return [fail("mqtt", "[mqtt] is enabled but the MQTT client is not installed",
                     "pip install 'vtzero[mqtt]' (or set mqtt.enabled = false)")]
    try:
        check_config(mc)
        # A client ID of its own: the broker would drop a running daemon's session for it.
        client = aiomqtt.Client(mc.host, mc.port, identifier=f"vtzero-doctor-{os.getpid()}",
                                username=mc.username or None, password=read_password(mc),
                                timeout=mc.connect_timeout_s, tls_context=tls_context(mc))
        async with client:
            pass
    except ConfigError as exc:
        return [fail("mqtt", str(exc), "fix [mqtt]")]
    except aiomqtt.MqttError as exc:
        return [fail("mqtt", f"broker {mc.host}:{mc.port}: {exc}",
                     "start the broker, or fix mqtt.host, port, username, password_file and "
                     "tls (or set mqtt.enabled = false)")]
    return [ok("mqtt", f"broker {mc.host}:{mc.port} accepts the connection"
               + (" (TLS)" if mc.tls else "") + (f" as {mc.username}" if mc.username else ""))]


def main(config_path: str, as_json: bool) -> int:
    """``vt-edge doctor``: 0 when nothing FAILs, 1 otherwise."""
    cfg = load_config(config_path)
    report = asyncio.run(run_doctor(cfg, config_path, progress=to_stderr))
    print(json.dumps(report.to_json(), indent=2) if as_json else report.table())
    return 1 if report.failed else 0

