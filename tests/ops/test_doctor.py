"""``vt-edge doctor`` on the emulated robot: a good setup is all OK; each wrong setting gives
the line that names its cause and fix, and only that line; nothing moves.

One emulated robot and the fake VLM servers run for the whole module on an event loop of their
own in a thread; each case runs the doctor (real drivers: the bus over the robot's pty, the
pads over loopback WebSocket) on the test's thread.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from edge.cli import build_parser
from edge.core import tomledit
from edge.core.config import Config
from edge.core.model import Origin
from edge.ops import doctor as doctor_module
from edge.ops.doctor import Level, Report, run_doctor
from edge.runtime.references import references_dir
from edge.sim.fake_vlm import FakeVLM
from edge.sim.robot import SimRobot
from edge.sim.xela_server import Fault, encode_frame
from tests.support.daemon import ROOT, base_config
from tests.support.waits import free_port

# Long enough for a tare and a hundred idle frames, whose rate a busy host's stall of a few
# tens of milliseconds moves by less than doctor's 10 % (0.3 s once read 141 frames/s);
# the CLI case runs the shipped 2 s.
TEST_NOISE_WINDOW_S = 0.8
TEST_TARE_S = 0.1
# The host's timing: long enough for a few dozen sampler ticks and stops.
TEST_TIMING_S = 0.5
# Its level depends on how busy the host is, not on the setting a case breaks.
HOST_TIMING = "host timing"
MODEL = "fake-vlm"


@dataclass
class Lab:
    robot: SimRobot
    vlm: FakeVLM
    # Refuses response_format json_schema with a 400, as older Ollama and llama.cpp do.
    refusing: FakeVLM
    # Wants a key (vLLM started with --api-key).
    keyed: FakeVLM
    call: Callable


@pytest.fixture(scope="module")
def lab() -> Iterator[Lab]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="emulated-lab", daemon=True)
    thread.start()

    def call(coro, timeout_s: float = 30.0):
        return asyncio.run_coroutine_threadsafe(coro, loop).result(timeout_s)

    robot = SimRobot("stainless_cube", seed=5, cfg=base_config())
    vlm = FakeVLM(model=MODEL)
    refusing = FakeVLM(model=MODEL, structured="json_object_only")
    keyed = FakeVLM(model=MODEL, api_key="lab-secret-key-0123")
    servers = (robot, vlm, refusing, keyed)
    for server in servers:
        call(server.start())
    try:
        yield Lab(robot, vlm, refusing, keyed, call)
    finally:
        for server in reversed(servers):
            call(server.stop())
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()


def good_config(lab: Lab, state: Path) -> Config:
    cfg = lab.robot.runtime_config(base_config(lab.vlm.base_url))
    return replace(cfg, press=replace(cfg.press, tare_s=TEST_TARE_S),
                   runtime=replace(cfg.runtime, state_dir=str(state)))


def doctor(cfg: Config) -> Report:
    return asyncio.run(run_doctor(cfg, noise_window_s=TEST_NOISE_WINDOW_S,
                                  timing_s=TEST_TIMING_S))


def not_ok(report: Report) -> dict[str, Level]:
    return {c.part: c.level for c in report.checks
            if c.level is not Level.OK and c.part != HOST_TIMING}


def line(report: Report, part: str) -> str:
    (check,) = [c for c in report.checks if c.part == part]
    return f"{check.found} -> {check.fix}"


def sub(cfg: Config, section: str, **changes) -> Config:
    return replace(cfg, **{section: replace(getattr(cfg, section), **changes)})


def _pty() -> str:
    """A serial device without modem lines (a pseudo-terminal), open for the module."""
    main, tty = os.openpty()
    _KEPT_OPEN.extend((main, tty))
    return os.ttyname(tty)


_KEPT_OPEN: list[int] = []


def _token(mode: int, host: str) -> Callable[[Config, Lab], Config]:
    def make(cfg: Config, lab: Lab) -> Config:
        path = Path(cfg.runtime.state_dir).parent / "api-token"
        path.write_text("a-lab-token-of-32-characters-000\n")
        path.chmod(mode)
        return sub(cfg, "api", host=host, token_file=str(path))
    return make


def _not_a_dir(cfg: Config, lab: Lab) -> Config:
    blocker = Path(cfg.runtime.state_dir).parent / "a-file"
    blocker.write_text("")
    return sub(cfg, "runtime", state_dir=str(blocker / "state"))


# (id, the wrong setting, {part: level} of every line that is not OK, what the line says)
CASES = [
    ("port missing", lambda c, lab: sub(c, "bus", port="/dev/vtzero-no-such-port"),
     {"bus port": Level.FAIL}, ["/dev/vtzero-no-such-port does not exist", "/dev/serial/by-id"]),
    ("port not a serial device", lambda c, lab: sub(c, "bus", port=str(ROOT / "README.md")),
     {"bus port": Level.FAIL}, ["cannot open Dynamixel port", "bus.port"]),
    ("wrong motor ID", lambda c, lab: sub(c, "bus", joint_ids=(11, 12, 13, 17)),
     {"motor 17": Level.FAIL, "bus scan": Level.FAIL},
     ["motor 17 did not answer a ping", "bus.joint_ids"]),
    ("xela_server down", lambda c, lab: sub(c, "sensor", url=f"ws://127.0.0.1:{free_port()}/"),
     {"xela server": Level.FAIL}, ["cannot connect to ws://127.0.0.1:", "start xela_server"]),
    ("wrong taxel count", lambda c, lab: sub(c, "sensor", taxels_per_pad=24),
     {"xela layout": Level.FAIL},
     ["configured 2 x XR1944 (24 taxels each)", "XR1944 x 16 taxels",
      "set sensor.taxels_per_pad = 16"]),
    ("wrong sensor model", lambda c, lab: sub(c, "sensor", model="XR1946"),
     {"xela layout": Level.FAIL},
     ["configured 2 x XR1946 (16 taxels each)", "set sensor.model = 'XR1944'"]),
    ("camera command failing",
     lambda c, lab: sub(c, "camera", kind="command", command="vtzero-no-camera -o {out}"),
     {"camera": Level.FAIL},
     ["vtzero-no-camera", "cannot start", "'vision_tactile' needs a photo", "camera.command"]),
    ("camera failing, no photo needed",
     lambda c, lab: sub(sub(c, "camera", kind="command", command="vtzero-no-camera -o {out}"),
                        "vlm", mode="tactile_only"),
     {"camera": Level.WARN}, ["vtzero-no-camera", "cannot start", "camera.command"]),
    ("VLM URL unreachable",
     lambda c, lab: sub(c, "vlm", base_url=f"http://127.0.0.1:{free_port()}/v1"),
     {"vlm server": Level.FAIL}, ["http://127.0.0.1:", "start the server", "vlm.base_url"]),
    ("VLM key missing", lambda c, lab: sub(c, "vlm", base_url=lab.keyed.base_url),
     {"vlm key": Level.FAIL},
     ["refuses a request without a key", "HTTP 401", "$VTZERO_VLM_API_KEY"]),
    ("wrong VLM model name", lambda c, lab: sub(c, "vlm", model="llava:13b"),
     {"vlm server": Level.FAIL}, ["does not serve 'llava:13b'", MODEL, "set vlm.model"]),
    ("VLM refusing json_schema", lambda c, lab: sub(c, "vlm", base_url=lab.refusing.base_url),
     {"vlm probe": Level.WARN},
     ["structured output 'json_object'", "json_schema", "vlm.structured_output = 'json_object'"]),
    ("threshold inside the idle noise", lambda c, lab: sub(c, "press", x_th=0.0001),
     # (0.0001 is also far from the x_th the model's references were pressed at.)
     {"idle noise": Level.FAIL, "x_th": Level.WARN},
     ["press.x_th = 0.0001", "inside the noise", "raise press.x_th above 0.00"]),
    ("emulated database on a robot", lambda c, lab: replace(c, mode="robot"),
     {"references": Level.WARN}, ["pressed by the emulated robot", "vt-edge collect"]),
    ("API exposed without a token", lambda c, lab: sub(c, "api", host="0.0.0.0"),
     {"api": Level.FAIL}, ["exposes the API beyond this machine", "api.token_file"]),
    ("MQTT broker unreachable",
     lambda c, lab: sub(c, "mqtt", enabled=True, port=free_port(), connect_timeout_s=1.0),
     {"mqtt": Level.FAIL}, ["Connection refused", "start the broker"]),
    ("button port without modem lines",
     lambda c, lab: sub(c, "button", kind="serial", port=_pty(), line="cts"),
     {"button": Level.FAIL}, ["has no modem lines", "/dev/pts/", "kind = \"gpio\""]),
    ("GPIO button line missing",
     lambda c, lab: sub(c, "button", kind="gpio", chip="/dev/vtzero-no-gpiochip", line="17"),
     {"button": Level.FAIL}, ["GPIO", "button.chip and button.line"]),
    ("API token world-readable off loopback", _token(0o644, "0.0.0.0"),
     {"api": Level.FAIL}, ["api-token is readable by others (mode 644)", "chmod 600"]),
    ("API token group-readable on loopback", _token(0o640, "127.0.0.1"),
     {"api": Level.WARN}, ["readable by its group (mode 640)", "chmod 600"]),
    ("state dir not a directory", _not_a_dir,
     {"state dir": Level.FAIL}, ["a-file is not a directory", "runtime.state_dir"]),
]


def test_a_good_setup_is_all_ok_and_nothing_moves(lab, tmp_path, capsys):
    """The CLI as a lab runs it (the shipped 2 s noise window), on a config file."""
    path = tmp_path / "robot.toml"
    cfg = good_config(lab, tmp_path / "state")
    tomledit.update(ROOT / "configs/sim.toml", path, {
        "sensor": {"url": cfg.sensor.url}, "bus": {"port": cfg.bus.port},
        "camera": {"kind": "http", "url": cfg.camera.url},
        "runtime": {"models_dir": str(ROOT / "models"), "state_dir": str(tmp_path / "state")},
        "vlm": {"base_url": lab.vlm.base_url, "model": MODEL}})
    before = {i: lab.robot.dxl.get_register(i, "Goal Position") for i in range(11, 16)}
    started = time.monotonic()
    # The command as the CLI parses it (not main(): its logging set-up would outlive the test).
    args = build_parser().parse_args(["doctor", "--config", str(path), "--json"])
    assert args.func(args) == 0
    elapsed = time.monotonic() - started
    out = json.loads(capsys.readouterr().out)
    print(f"doctor on a good setup: {elapsed:.2f} s")
    assert out["ok"] and out["counts"]["FAIL"] == 0
    parts = [c["part"] for c in out["checks"]]
    assert all(c["level"] == "OK" for c in out["checks"] if c["part"] != HOST_TIMING), \
        out["checks"]
    assert {"bus port", "bus latency", "motor 11", "motor 15", "xela server", "xela layout",
            "xela rate", "idle noise", "camera", "vlm server", "vlm key", "vlm probe", "model",
            "references", "state dir", "api", "mqtt", "button", "store", HOST_TIMING} <= set(parts)
    checks = {c["part"]: c for c in out["checks"]}
    noise = checks["idle noise"]["data"]
    # 2 s at 125 frames/s; fewer where the loaded host delays the emulator's ticks.
    assert noise["frames"] > 100 and 0 < noise["p999"] < noise["x_th"] / 2, noise
    assert 62.5 <= checks["xela rate"]["data"]["rate_hz"] < 150
    assert checks["vlm probe"]["data"]["structured_output"] == "json_schema"
    photo = Path(checks["camera"]["data"]["path"])
    assert photo.read_bytes()[:2] == b"\xff\xd8" and checks["camera"]["data"]["width"] == 320
    assert checks["references"]["data"]["origin"]["kind"] == "emulated"
    # Read-only: no goal written, torque never on.
    assert {i: lab.robot.dxl.get_register(i, "Goal Position") for i in range(11, 16)} == before
    assert all(lab.robot.dxl.get_register(i, "Torque Enable") == 0 for i in range(11, 16))
    assert elapsed < 15


@pytest.mark.parametrize(("setting", "wrong", "expected", "says"), CASES,
                         ids=[c[0] for c in CASES])
def test_each_wrong_setting_names_its_cause_and_fix(lab, tmp_path, setting, wrong, expected,
                                                     says):
    cfg = wrong(good_config(lab, tmp_path / "state"), lab)
    report = doctor(cfg)
    assert not_ok(report) == expected, report.table()
    (part,) = [p for p, level in expected.items() if level is Level.FAIL][:1] or list(expected)
    text = line(report, part)
    for words in says:
        assert words in text, f"{setting}: {words!r} not in {text!r}"
    assert report.failed == (Level.FAIL in expected.values())
    assert all(c.fix for c in report.checks if c.level is not Level.OK)


def test_the_listening_starts_at_the_first_frame_and_a_silent_server_fails(lab, tmp_path):
    # A first frame later than the whole listening window (a busy host, a server still
    # starting) is not "no data": the window starts at it. A server that stays silent fails
    # after FIRST_FRAME_TIMEOUT_S, saying so.
    cfg = good_config(lab, tmp_path / "state")
    xela = lab.robot.xela
    late_s = 2 * (TEST_TARE_S + TEST_NOISE_WINDOW_S)
    assert late_s < doctor_module.FIRST_FRAME_TIMEOUT_S
    xela.fault = Fault.SILENT
    try:
        resume = threading.Timer(late_s, setattr, (xela, "fault", Fault.NONE))
        resume.start()
        t0 = time.monotonic()
        report = doctor(cfg)
        resume.join()
        assert not_ok(report) == {}, report.table()
        assert time.monotonic() - t0 >= late_s
        xela.fault = Fault.SILENT
        report = doctor(cfg)
    finally:
        xela.fault = Fault.NONE
    assert not_ok(report) == {"xela server": Level.FAIL}, report.table()
    assert (f"accepts the connection but sent no data frame in "
            f"{doctor_module.FIRST_FRAME_TIMEOUT_S:g} s") in line(report, "xela server")


def test_a_motor_in_alarm_fails_and_the_table_says_what_to_do(lab, tmp_path):
    lab.robot.dxl.set_hardware_error(12, 0x20)
    try:
        report = doctor(good_config(lab, tmp_path / "state"))
    finally:
        lab.robot.dxl.set_hardware_error(12, 0)
    assert not_ok(report) == {"motor 12": Level.FAIL}
    assert "overload" in line(report, "motor 12") and "power-cycle" in line(report, "motor 12")
    table = report.table().splitlines()
    assert any(row.startswith("FAIL  motor 12") and " -> remove the cause" in row
               for row in table)
    warned = report.count(Level.WARN)  # the host's timing alone may warn
    assert warned == sum(c.part == HOST_TIMING for c in report.checks if c.level is Level.WARN)
    assert table[-1].startswith(f"{len(report.checks) - 1 - warned} OK, {warned} WARN, 1 FAIL")


def test_the_port_lines_explain_permissions_names_and_the_latency_timer(tmp_path, monkeypatch):
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    tty = tmp_path / "ttyUSB0"
    tty.write_text("")
    link = by_id / "usb-FTDI_USB__-__Serial_Converter_FT1234-if00-port0"
    link.symlink_to(tty)
    monkeypatch.setattr(doctor_module, "SERIAL_BY_ID", by_id)
    missing = doctor_module._port_problem(str(tmp_path / "ttyUSB1"))
    assert missing.level is Level.FAIL and link.name in missing.found
    assert doctor_module._by_id_name(str(tty)) == str(link)
    assert doctor_module._by_id_name(str(link)) is None
    alias = tmp_path / "ttyDXL"  # a udev rule's stable name
    alias.symlink_to(tty)
    assert doctor_module._by_id_name(str(alias)) is None
    # (Root may open anything: the refusal a lab user meets is simulated at os.access.)
    monkeypatch.setattr(doctor_module.os, "access", lambda path, mode: False)
    denied = doctor_module._port_problem(str(tty))
    assert denied.level is Level.FAIL and "permission denied" in denied.found
    assert "usermod -aG" in denied.fix or "udev rule" in denied.fix

    timers = tmp_path / "usb-serial"
    (timers / "ttyUSB0").mkdir(parents=True)
    (timers / "ttyUSB0" / "latency_timer").write_text("16\n")
    slow = doctor_module._check_latency(str(link), timers)
    assert slow.level is Level.WARN and "16 ms" in slow.found
    assert "echo 1 | sudo tee" in slow.fix and 'ATTR{latency_timer}="1"' in slow.fix
    (timers / "ttyUSB0" / "latency_timer").write_text("1\n")
    assert doctor_module._check_latency(str(tty), timers).level is Level.OK
    assert doctor_module._check_latency("/dev/pts/0", timers).found.startswith("not a USB")


def test_a_lab_database_is_ok_on_its_robot_and_warned_with_other_pads(tmp_path):
    models = tmp_path / "models"
    shutil.copytree(ROOT / "models", models, ignore=shutil.ignore_patterns("eval"))
    manifest = json.loads((models / "manifest.json").read_text())
    manifest["origin"] = Origin("robot", "the lab's own presses (vt-edge collect)", "arm-3",
                                "XR1944", ("S1", "S2")).to_json()
    (models / "manifest.json").write_text(json.dumps(manifest))
    cfg = Config(mode="robot")
    cfg = sub(cfg, "runtime", models_dir=str(models))
    model, _x_th, _taught, refs = doctor_module._check_model(cfg)
    assert model.level is Level.OK and "every file verified" in model.found
    assert refs.level is Level.OK and "pressed by a real robot (arm-3)" in refs.found
    _, _, _, refs = doctor_module._check_model(sub(cfg, "sensor", model="uSPa46"))
    assert refs.level is Level.WARN and "XR1944" in refs.found and "uSPa46" in refs.fix
    (models / "database.npz").write_bytes(b"damaged")
    (broken,) = doctor_module._check_model(cfg)
    assert broken.level is Level.FAIL and "database.npz: sha256" in broken.found


@pytest.mark.parametrize(("dialect", "says"), [
    ("1.8", "xela_server 1.8.0-vtzero-emulator"), ("1.7.7", "xela_server 1.7.7 (data as ints)"),
    ("1.7", "xela_server 1.7 (data as hex)")])
def test_the_server_version_is_told_from_its_frames(dialect, says):
    raw = np.full(96, 30000, dtype=np.uint16)
    frame = json.loads(encode_frame(7, 1.0, raw, dialect=dialect))
    assert doctor_module._dialect(frame) == says
    real = json.loads((ROOT / "tests/fixtures/xela/v1.8_uSPa46_two_sensors.json").read_text())
    assert doctor_module._dialect(real) == "xela_server 1.8.0b_208601"


def test_a_disk_below_the_daemons_floor_fails(lab, tmp_path, monkeypatch):
    from edge.runtime import store

    # The daemon's own floor, not a second one.
    assert doctor_module.STORE_MIN_FREE_BYTES is store.MIN_FREE_BYTES
    state = tmp_path / "state"
    assert doctor_module._check_state_dir(state).level is Level.OK
    # This disk's real free space, against a floor just above it.
    free = shutil.disk_usage(tmp_path).free
    monkeypatch.setattr(doctor_module, "STORE_MIN_FREE_BYTES", free + (64 << 20))
    check = doctor_module._check_state_dir(state)
    print(check.found)
    assert check.level is Level.FAIL
    assert "the daemon refuses every press below" in check.found and "free space" in check.fix


def test_a_slow_part_is_told_every_few_seconds(lab, tmp_path):
    slow = FakeVLM(model=MODEL, latency_s=1.5)
    lab.call(slow.start())
    lines: list[str] = []
    try:
        cfg = sub(good_config(lab, tmp_path / "state"), "vlm", base_url=slow.base_url)
        report = asyncio.run(run_doctor(cfg, noise_window_s=TEST_NOISE_WINDOW_S,
                                        timing_s=TEST_TIMING_S, progress=lines.append,
                                        progress_every_s=0.25))
    finally:
        lab.call(slow.stop())
    print("\n".join(lines))
    assert not_ok(report) == {}, report.table()
    # The probe alone took 1.5 s: several lines, the last of them naming only the VLM;
    # then the host's timing, measured alone.
    assert all(line.startswith("doctor: waiting for ") for line in lines)
    vlm = [line for line in lines if "vlm" in line]
    assert len(vlm) >= 3 and vlm[-1].startswith("doctor: waiting for vlm (")
    assert lines[-1].startswith(f"doctor: waiting for {HOST_TIMING} (")


def test_the_host_timing_line_gives_the_figures_and_warns_past_1_ms(lab, tmp_path):
    cfg = good_config(lab, tmp_path / "state")
    report = doctor(cfg)
    (check,) = [c for c in report.checks if c.part == HOST_TIMING]
    print(check.found, check.fix)
    data = check.data
    # A few dozen ticks of the 125 Hz sampler, a stop every fifth frame.
    assert 20 <= data["ticks"] + data["missed_ticks"] <= 1.5 * 125 * TEST_TIMING_S
    assert data["stops"] >= 5
    assert 0 <= data["sampler_late_p50_ms"] <= data["sampler_late_p99_ms"]
    assert 0 < data["stop_p50_ms"] <= data["stop_p99_ms"] <= data["stop_max_ms"]
    assert "sampler period error p99" in check.found and "frame to Goal Position" in check.found
    late = data["sampler_late_p99_ms"] > 1.0 or data["missed_ticks"] > 0
    assert check.level is (Level.WARN if late else Level.OK)
    if late:
        assert "realtime" in check.fix and "CPU" in check.fix
    # The robot's own bus is untouched: the stops went to a motor of its own.
    assert lab.robot.dxl.get_register(15, "Torque Enable") == 0
    assert not data["realtime_applied"]
    # As the daemon runs with [runtime] realtime = true, where the host allows it.
    timed = doctor_module.measure(sub(cfg, "runtime", realtime=True), TEST_TIMING_S)
    print(timed)
    assert timed.realtime_applied == (timed.realtime_refused is None)


def test_the_host_timing_advice_follows_what_the_host_allows(monkeypatch):
    # The figures as a busy host gives them (measured by the test above), the advice for each
    # answer the host gives to real-time scheduling.
    timing = doctor_module.HostTiming(3.0, 370, 2, 2e-4, 3e-3, 5e-3, 75, 2e-4, 1e-2, 3e-2,
                                      False, None)
    advice = {}
    for applied, refused in ((False, None), (False, "Operation not permitted"), (True, None)):
        t = replace(timing, realtime_applied=applied, realtime_refused=refused)
        (check,) = _timing_check(t, monkeypatch)
        assert check.level is Level.WARN and "p99 3.00 ms" in check.found
        advice[applied, refused] = check.fix
    assert "set [runtime] realtime = true" in advice[False, None]
    assert "LimitRTPRIO" in advice[False, "Operation not permitted"]
    assert "realtime = true" not in advice[True, None] and "isolcpus" in advice[True, None]
    quiet = replace(timing, missed_ticks=0, late_p99_s=4e-4)
    (check,) = _timing_check(quiet, monkeypatch)
    assert check.level is Level.OK and "allowed, off" in check.found


def _timing_check(timing, monkeypatch):
    monkeypatch.setattr(doctor_module, "measure", lambda cfg, duration_s: timing)
    return asyncio.run(doctor_module._check_timing(Config(), 0.0))


def test_x_th_far_from_the_models_is_a_warning(tmp_path):
    models = tmp_path / "models"
    shutil.copytree(ROOT / "models", models, ignore=shutil.ignore_patterns("eval"))
    manifest = json.loads((models / "manifest.json").read_text())
    # Most classes at a calibrated value, a fragile one lower.
    labels = sorted(manifest["class_x_th"])
    manifest["class_x_th"] = {**{label: 0.00445 for label in labels[:-1]}, labels[-1]: 0.003}
    (models / "manifest.json").write_text(json.dumps(manifest))
    cfg = sub(Config(), "runtime", models_dir=str(models))

    def x_th_line(x_th: float):
        (check,) = [c for c in doctor_module._check_model(sub(cfg, "press", x_th=x_th))
                    if c.part == "x_th"]
        print(check.level, check.found, check.fix)
        return check

    # The calibrated value rounded passes; a typo and another robot's value do not.
    assert x_th_line(0.004).level is Level.OK
    typo = x_th_line(0.02)
    assert typo.level is Level.WARN and "x_th = 0.02 is 4.49 times" in typo.found
    assert "0.00445" in typo.found and "set press.x_th = 0.00445" in typo.fix
    assert typo.data == {"x_th": 0.02, "model_x_th": 0.00445}
    assert x_th_line(0.0025).level is Level.WARN
    # A model that records no thresholds has nothing to compare with.
    del manifest["class_x_th"]
    (models / "manifest.json").write_text(json.dumps(manifest))
    assert x_th_line(0.2).level is Level.OK


def test_the_store_line_gives_its_size_growth_and_days_left(tmp_path):
    from edge.runtime.domain import Episode, Status
    from edge.runtime.store import EpisodeStore, new_id

    cfg = sub(Config(), "runtime", state_dir=str(tmp_path / "state"))
    (empty,) = doctor_module._check_store(cfg)
    assert empty.level is Level.OK and "no episodes yet" in empty.found
    assert not (tmp_path / "state").exists()  # doctor creates nothing
    store = EpisodeStore(tmp_path / "state" / "episodes")
    for _ in range(3):
        store.create(Episode(new_id(), Status.DONE, label="macaron"),
                     {"image.jpg": b"\xff" * 50_000})
    (line,) = doctor_module._check_store(cfg)
    print(line.found)
    assert line.level is Level.OK and line.found.startswith("3 episodes, 0.1 MiB")
    assert "before retention removes the oldest finished episodes" in line.found
    assert line.data["bytes"] > 150_000 and line.data["days_left"] > 0
    # With retention off the days are the disk's.
    off = sub(cfg, "runtime", keep_free_mb=0.0)
    (line,) = doctor_module._check_store(off)
    assert "its disk is full (retention off)" in line.found


def test_taught_references_are_checked_against_the_model(tmp_path):
    """None taught is OK; a damaged index is the FAIL the daemon's start would be, naming
    the file (the stale case shares the daemon's Overlay: tests/runtime/test_references.py)."""
    cfg = sub(Config(), "runtime", state_dir=str(tmp_path / "state"),
              models_dir=str(ROOT / "models"))

    def taught():
        (check,) = [c for c in doctor_module._check_model(cfg) if c.part == "taught references"]
        return check

    none = taught()
    assert none.level is Level.OK and none.found == "none taught"
    assert none.data == {"current": 0, "stale": 0}
    index = references_dir(tmp_path / "state") / "references.json"
    index.parent.mkdir(parents=True)
    index.write_text("{not json")
    damaged = taught()
    assert damaged.level is Level.FAIL and str(index) in damaged.found
    assert "move it aside" in damaged.fix
