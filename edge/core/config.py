"""Configuration: frozen dataclasses loaded once from TOML.

Every section is a frozen dataclass with safe defaults; :func:`load_config` reads a TOML file,
refuses unknown keys and wrong types, and names the offending field (``press.x_th``) and value
in the error, then applies the environment's overrides (:func:`apply_environment`): the one
place the environment changes a configured value. Sections that later parts of the runtime
need are added here, next to these.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

from edge.core.errors import ConfigError


@dataclass(frozen=True)
class SensorConfig:
    """The tactile stream (XELA ``xela_server`` WebSocket)."""

    url: str = "ws://127.0.0.1:5000"
    model: str = "XR1944"
    pads: int = 2
    taxels_per_pad: int = 16
    # Rows of each pad's taxel grid (row-major from the top left): 4 x 4 on the XR1944,
    # 24 taxels in 4 rows on a 4 x 6 pad.
    taxel_rows: int = 4
    # No fresh frame for this long means the stream is stale: never press on it.
    stale_timeout_s: float = 0.1
    reconnect_max_backoff_s: float = 5.0
    # TCP + WebSocket handshake with xela_server.
    connect_timeout_s: float = 2.0
    # No fresh frame for this long on an open connection: hang up and dial again (a host
    # that vanished leaves TCP open; a hung server may keep resending its last frame).
    dead_timeout_s: float = 2.0

    def validate(self, path: str) -> None:
        _require(self.pads >= 1, path, "pads", self.pads, "must be >= 1")
        _require(
            self.taxels_per_pad >= 1, path, "taxels_per_pad", self.taxels_per_pad, "must be >= 1"
        )
        _require(self.taxel_rows >= 1 and self.taxels_per_pad % self.taxel_rows == 0, path,
                 "taxel_rows", self.taxel_rows,
                 f"must divide taxels_per_pad ({self.taxels_per_pad}) into whole rows")
        _require(
            self.stale_timeout_s > 0, path, "stale_timeout_s", self.stale_timeout_s, "must be > 0"
        )
        _require(
            self.url.startswith(("ws://", "wss://")),
            path,
            "url",
            self.url,
            "must be a ws:// or wss:// URL",
        )
        _require(
            self.reconnect_max_backoff_s > 0,
            path,
            "reconnect_max_backoff_s",
            self.reconnect_max_backoff_s,
            "must be > 0",
        )
        _require(
            self.connect_timeout_s > 0,
            path,
            "connect_timeout_s",
            self.connect_timeout_s,
            "must be > 0",
        )
        _require(
            self.dead_timeout_s > self.stale_timeout_s,
            path,
            "dead_timeout_s",
            self.dead_timeout_s,
            f"must be > stale_timeout_s ({self.stale_timeout_s})",
        )

    @property
    def channels(self) -> int:
        return self.pads * self.taxels_per_pad * 3

    def layout_text(self) -> str:
        """The channels' make-up for messages: ``2 pads x 16 taxels x 3``."""
        return f"{self.pads} pad{'s' * (self.pads != 1)} x {self.taxels_per_pad} taxels x 3"


@dataclass(frozen=True)
class BusConfig:
    """The Dynamixel bus (U2D2, Protocol 2.0)."""

    port: str = "/dev/ttyUSB0"
    baudrate: int = 1_000_000
    joint_ids: tuple[int, ...] = (11, 12, 13, 14)
    gripper_id: int = 15
    # Goal Current cap of the gripper in raw units (~2.69 mA each): limits the squeeze.
    gripper_goal_current: int = 200
    # Bus Watchdog period while torque is on (20 ms units): a host silent this long stops the
    # motors. Long enough to ride out a Python pause, short enough to stop a dead host.
    watchdog_ms: int = 300

    def validate(self, path: str) -> None:
        ids = (*self.joint_ids, self.gripper_id)
        _require(
            len(set(ids)) == len(ids),
            path,
            "joint_ids",
            self.joint_ids,
            "motor IDs must be distinct (gripper_id included)",
        )
        for motor_id in ids:
            _require(0 <= motor_id <= 252, path, "joint_ids", motor_id, "IDs are 0..252")
        _require(
            0 < self.gripper_goal_current <= 1193,
            path,
            "gripper_goal_current",
            self.gripper_goal_current,
            "must be 1..1193 (XM430 Current Limit)",
        )
        _require(
            self.watchdog_ms % 20 == 0 and 20 <= self.watchdog_ms <= 127 * 20,
            path,
            "watchdog_ms",
            self.watchdog_ms,
            "must be a multiple of 20 in 20..2540",
        )


@dataclass(frozen=True)
class PressConfig:
    """The press (docs/method.md, 'Press')."""

    # Tactile norm threshold in tactile units ((raw - tare) / 65536); 0.003 for fragile objects.
    x_th: float = 0.004
    dt_stopping_s: float = 0.2
    # Gripper gap closing speed while searching for contact.
    close_speed_mps: float = 0.01
    # Unloaded samples averaged into the tare before every press.
    tare_s: float = 0.3
    # A norm this many times x_th means the stop came too late: abort and open.
    abort_factor: float = 25.0
    # Gripper width (ROBOTIS joint value, -0.010 closed .. 0.019 fully open) before closing.
    open_width_m: float = 0.019
    # The stop goal lies this many encoder counts past the present position: keeps a gentle
    # squeeze (0 would release it; each count is ~0.035 mm of finger gap).
    stop_squeeze_raw: int = 2
    # 0: after a press the arm lifts once the gripper is fully open. Above 0: it lifts once
    # the fingers are clear of the object (this much wider than where the press crossed
    # x_th, and the pads back under half of x_th) while the gripper opens on: the label and
    # the next press come sooner by the rest of the opening.
    lift_clearance_m: float = 0.0
    # Refuse to close when lowering the arm alone moved the pads by x_th or more (an object
    # already touching the fingers). false only for pads that shift that much with the arm's
    # motion while nothing touches them: each press's tare then stands alone.
    refuse_contact_before_closing: bool = True

    def validate(self, path: str) -> None:
        _require(0 < self.x_th < 1, path, "x_th", self.x_th, "must be in (0, 1)")
        _require(self.dt_stopping_s >= 0, path, "dt_stopping_s", self.dt_stopping_s, "must be >= 0")
        _require(
            0 < self.close_speed_mps <= 0.1,
            path,
            "close_speed_mps",
            self.close_speed_mps,
            "must be in (0, 0.1] m/s (a gentle push)",
        )
        _require(self.tare_s > 0, path, "tare_s", self.tare_s, "must be > 0")
        _require(self.abort_factor > 1, path, "abort_factor", self.abort_factor, "must be > 1")
        _require(-0.010 < self.open_width_m <= 0.019, path, "open_width_m", self.open_width_m,
                 "must be in (-0.010, 0.019] m (the gripper's range)")
        _require(0 <= self.stop_squeeze_raw <= 20, path, "stop_squeeze_raw",
                 self.stop_squeeze_raw, "must be 0..20 counts")
        _require(0 <= self.lift_clearance_m <= 0.02, path, "lift_clearance_m",
                 self.lift_clearance_m, "must be in [0, 0.02] m (0: lift once fully open)")


@dataclass(frozen=True)
class SimConfig:
    """The simulated robot."""

    seed: int = 0
    object: str = "stainless_cube"
    sensor_rate_hz: float = 125.0
    # The emulated pads' sensitivity to load, relative to the XR1944 model (edge/sim/skin.py):
    # another sensor's scale, for `vt-edge calibrate threshold` to find.
    pad_gain: float = 1.0

    def validate(self, path: str) -> None:
        _require(0.1 <= self.pad_gain <= 10, path, "pad_gain", self.pad_gain,
                 "must be in [0.1, 10]")
        _require(
            1 <= self.sensor_rate_hz <= 1000,
            path,
            "sensor_rate_hz",
            self.sensor_rate_hz,
            "must be in [1, 1000] Hz",
        )


@dataclass(frozen=True)
class CameraConfig:
    """Where the still image comes from when a request brings none."""

    kind: Literal["none", "command", "v4l2", "http"] = "none"
    # kind = "command": a program writing a JPEG to {out}, e.g. "fswebcam -q --no-banner {out}".
    command: str = ""
    device: str = "/dev/video0"
    # kind = "http": a snapshot URL (IP cameras; the simulated robot serves one).
    url: str = ""
    timeout_s: float = 10.0

    def validate(self, path: str) -> None:
        _require(self.kind != "command" or "{out}" in self.command, path, "command",
                 self.command, "must contain {out}, the file the program writes")
        _require(self.kind != "http" or self.url.startswith(("http://", "https://")), path,
                 "url", self.url, "must be an http(s) URL")
        _require(self.timeout_s > 0, path, "timeout_s", self.timeout_s, "must be > 0")


@dataclass(frozen=True)
class ButtonConfig:
    kind: Literal["none", "serial", "gpio"] = "none"
    port: str = ""  # serial: e.g. /dev/ttyUSB1
    line: str = "cts"  # serial: cts or dsr; gpio: the line offset
    chip: str = "/dev/gpiochip0"

    def validate(self, path: str) -> None:
        _require(self.kind != "serial" or bool(self.port), path, "port", self.port,
                 "a serial button needs its port")
        _require(self.kind != "serial" or self.line in ("cts", "dsr"), path, "line",
                 self.line, "must be cts or dsr for a serial button")
        _require(self.kind != "gpio" or self.line.isdigit(), path, "line", self.line,
                 "must be the GPIO line offset (a number) for a gpio button")


@dataclass(frozen=True)
class RuntimeConfig:
    """Paths and the press controller's timeouts."""

    models_dir: str = "models"
    # Episodes go here; under systemd $VTZERO_STATE_DIR (StateDirectory) wins.
    state_dir: str = "state"
    # Duration of each arm move between poses (time-based profile).
    move_time_s: float = 1.5
    move_timeout_s: float = 5.0
    # Closing without crossing x_th for this long ends the press with "no contact".
    close_timeout_s: float = 8.0
    vlm_retry_base_s: float = 5.0
    vlm_retry_max_s: float = 300.0
    # Record the live tactile stream and events to MCAP segments here ("": off).
    record_mcap_dir: str = ""
    record_mcap_segment_s: float = 600.0
    # The segments' encoding: "mcap" (JSON messages, Foxglove) or "rosbag2" (a bag directory
    # of CDR messages, ros2 bag; needs the export extra).
    record_format: str = "mcap"
    # Real-time scheduling of the event loop and the bus thread (edge/runtime/realtime.py):
    # SCHED_FIFO at realtime_priority on CPU realtime_cpu (-1: the last one the daemon may
    # use). Needs root, CAP_SYS_NICE or LimitRTPRIO=; a restart applies it.
    realtime: bool = False
    realtime_priority: int = 20
    realtime_cpu: int = -1
    # Retention (edge/runtime/store.py): the oldest finished episodes and live recording
    # segments are removed once the store (episodes and record_mcap_dir) is over
    # store_max_mb (0: no bound by size), or its filesystem has less than keep_free_mb free.
    store_max_mb: float = 0.0
    keep_free_mb: float = 200.0
    # A press whose familiarity (edge.core.model.Familiarity: how clearly it lies in its
    # nearest class, a percentile of the reference database's own leave-one-out figures) is
    # at or past this is flagged unfamiliar (100: only one less clear than every reference).
    unfamiliar_percentile: float = 95.0
    # How the presses of a recognition of several presses ({"presses": N}) are fused into one
    # top-k (edge.runtime.compute.fuse_presses): "votes" (each press and subsampling
    # offset's top-k vote) or "mean" (their mean embedding looked up once).
    fusion: str = "votes"

    def validate(self, path: str) -> None:
        for name in ("move_time_s", "move_timeout_s", "close_timeout_s", "vlm_retry_base_s",
                     "vlm_retry_max_s"):
            _require(getattr(self, name) > 0, path, name, getattr(self, name), "must be > 0")
        for name in ("store_max_mb", "keep_free_mb"):
            _require(getattr(self, name) >= 0, path, name, getattr(self, name),
                     "must be >= 0 (0: off)")
        _require(self.record_mcap_segment_s >= 1, path, "record_mcap_segment_s",
                 self.record_mcap_segment_s, "must be >= 1 s")
        _require(self.record_format in ("mcap", "rosbag2"), path, "record_format",
                 self.record_format, 'must be "mcap" or "rosbag2"')
        _require(1 <= self.realtime_priority <= 99, path, "realtime_priority",
                 self.realtime_priority, "must be a SCHED_FIFO priority, 1..99")
        _require(self.realtime_cpu >= -1, path, "realtime_cpu", self.realtime_cpu,
                 "must be a CPU number, or -1 for the last one the daemon may use")
        _require(0 < self.unfamiliar_percentile <= 100, path, "unfamiliar_percentile",
                 self.unfamiliar_percentile, "must be a percentile in (0, 100]")
        _require(self.fusion in ("votes", "mean"), path, "fusion", self.fusion,
                 'must be "votes" or "mean"')


def _default_poses() -> dict[str, tuple[int, ...]]:
    # Raw Goal Positions of joints 11-14; teach real ones with `vt-edge pose teach NAME`.
    return {"rest": (2048, 1024, 3072, 2048), "above": (2048, 1650, 2650, 2048),
            "lowered": (2048, 1850, 2600, 1900)}


@dataclass(frozen=True)
class ApiConfig:
    """The HTTP API: loopback by default; a bearer token is required anywhere else."""

    host: str = "127.0.0.1"
    port: int = 8080
    # The token itself, or better a file holding it (kept out of the config file).
    token: str = ""
    token_file: str = ""
    max_candidates: int = 32
    max_body_bytes: int = 10 * 1024 * 1024
    # Default candidates for the button and SIGUSR1 triggers.
    default_candidates: tuple[str, ...] = ()

    def validate(self, path: str) -> None:
        _require(0 <= self.port <= 65535, path, "port", self.port, "must be 0..65535")
        _require(1 <= self.max_candidates <= 256, path, "max_candidates",
                 self.max_candidates, "must be 1..256")
        _require(1024 <= self.max_body_bytes <= 100 * 1024 * 1024, path, "max_body_bytes",
                 self.max_body_bytes, "must be 1 KiB..100 MiB")
        _require(not (self.token and self.token_file), path, "token", "***",
                 "set token or token_file, not both")
        _require(len(set(self.default_candidates)) == len(self.default_candidates), path,
                 "default_candidates", self.default_candidates, "must not repeat a label")

    @property
    def loopback_only(self) -> bool:
        return self.host in ("127.0.0.1", "::1", "localhost") or self.host.startswith("127.")


@dataclass(frozen=True)
class VLMConfig:
    """The ``[vlm]`` section. An empty ``base_url`` means no VLM is configured (``NoVLM``)."""

    # OpenAI-compatible endpoint up to and including /v1, e.g. "http://localhost:11434/v1"
    # (Ollama), "http://localhost:8000/v1" (vLLM), "https://api.openai.com/v1".
    base_url: str = ""
    model: str = ""
    mode: Literal["vision_tactile", "vision_only", "tactile_only"] = "vision_tactile"
    # Directory of <mode>.txt templates; None = the shipped models/prompts.
    prompt_dir: Path | None = None
    # The API key: from this file if set, else from this environment variable; none is fine
    # for a local server.
    api_key_env: str = "VTZERO_VLM_API_KEY"
    api_key_file: Path | None = None
    seed: int = 0
    # Per attempt: to get a connection, and for the whole request and response.
    connect_timeout_s: float = 5.0
    total_timeout_s: float = 60.0
    # Transport retries after the first attempt (the corrective retry is separate).
    max_retries: int = 3
    backoff_base_s: float = 0.5
    backoff_cap_s: float = 8.0
    # A server's Retry-After is honoured up to this long.
    retry_after_cap_s: float = 30.0
    max_image_side_px: int = 1024
    max_image_bytes: int = 1_000_000
    max_response_bytes: int = 1_000_000
    # How the answer is constrained: a strict JSON schema of the candidates, JSON mode, or
    # none (free text read by the label parser). A server that refuses the mode makes the
    # client step down one mode at a time for its session (README, "VLM").
    structured_output: Literal["json_schema", "json_object", "none"] = "json_schema"
    # Ask for a short reason before the label (the answer's ``reason``); off: the paper's
    # label-only answer, the prompt and schema unchanged.
    ask_reason: bool = False

    @property
    def configured(self) -> bool:
        return bool(self.base_url)

    def validate(self, path: str) -> None:
        if self.base_url:
            try:
                parts = urlsplit(self.base_url)
                parts.port  # noqa: B018 - raises for a port that is not a port
            except ValueError as exc:
                raise ConfigError(f"{path}.base_url = {_show(self.base_url)}: not a valid URL "
                                  f"({exc})") from None
            _require(parts.scheme in ("http", "https") and bool(parts.hostname), path,
                     "base_url", self.base_url, "must be an http:// or https:// URL")
            _require(parts.username is None and parts.password is None, path, "base_url",
                     "<redacted>", "must not hold credentials; use api_key_env/api_key_file")
            _require(not parts.query and not parts.fragment, path, "base_url",
                     self.base_url, "must not have a query or fragment")
            _require(bool(self.model.strip()), path, "model", self.model,
                     "must name the model when base_url is set")
        _require(self.api_key_env == "" or re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*",
                                                         self.api_key_env) is not None,
                 path, "api_key_env", self.api_key_env, "must be an environment variable name")
        _require(0 <= self.seed < 2**31, path, "seed", self.seed, "must be in [0, 2**31)")
        _require(self.connect_timeout_s > 0, path, "connect_timeout_s",
                 self.connect_timeout_s, "must be > 0")
        _require(self.total_timeout_s >= self.connect_timeout_s, path, "total_timeout_s",
                 self.total_timeout_s, "must be >= connect_timeout_s")
        _require(0 <= self.max_retries <= 10, path, "max_retries", self.max_retries,
                 "must be in 0..10")
        _require(self.backoff_base_s > 0, path, "backoff_base_s", self.backoff_base_s,
                 "must be > 0")
        _require(self.backoff_cap_s >= self.backoff_base_s, path, "backoff_cap_s",
                 self.backoff_cap_s, "must be >= backoff_base_s")
        _require(self.retry_after_cap_s >= 0, path, "retry_after_cap_s",
                 self.retry_after_cap_s, "must be >= 0")
        _require(64 <= self.max_image_side_px <= 8192, path, "max_image_side_px",
                 self.max_image_side_px, "must be in 64..8192")
        _require(self.max_image_bytes >= 10_000, path, "max_image_bytes",
                 self.max_image_bytes, "must be >= 10000")
        _require(self.max_response_bytes >= 1024, path, "max_response_bytes",
                 self.max_response_bytes, "must be >= 1024")
        _require(self.structured_output in ("json_schema", "json_object", "none"), path,
                 "structured_output", self.structured_output,
                 "must be 'json_schema', 'json_object' or 'none'")
        _require(isinstance(self.ask_reason, bool), path, "ask_reason", self.ask_reason,
                 "must be true or false")


@dataclass(frozen=True)
class MqttConfig:
    """The ``[mqtt]`` section: the MQTT bridge (off unless ``enabled``)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 1883  # 8883 is the usual port with tls
    # "" = "vtzero-<hostname>"; unique per broker (a second client with it is disconnected).
    client_id: str = ""
    # Topic prefix of this robot; "" = "vtzero/<hostname>".
    prefix: str = ""
    username: str = ""
    # The password in a file of its own (kept out of the config file; never logged).
    password_file: str = ""
    tls: bool = False
    # CA bundle for tls; "" = the system's.
    ca_file: str = ""
    keepalive_s: int = 30
    connect_timeout_s: float = 5.0
    # Waiting for the broker's acknowledgement of a QoS 1 message.
    publish_timeout_s: float = 5.0
    reconnect_base_s: float = 0.5
    reconnect_max_backoff_s: float = 30.0
    # Results kept for the broker while it is away (the oldest dropped beyond).
    queue_size: int = 1000

    def validate(self, path: str) -> None:
        _require(bool(self.host.strip()), path, "host", self.host, "must name the broker")
        _require(1 <= self.port <= 65535, path, "port", self.port, "must be 1..65535")
        _require(len(self.client_id) <= 128 and (not self.client_id
                                                 or self.client_id.isprintable()),
                 path, "client_id", self.client_id, "must be printable, at most 128 characters")
        _require(not any(c in self.prefix for c in "+#\0") and not self.prefix.startswith("/")
                 and not self.prefix.endswith("/") and "//" not in self.prefix
                 and len(self.prefix) <= 200, path, "prefix", self.prefix,
                 "must be a topic without wildcards (+, #) or a leading/trailing '/'")
        _require(not self.password_file or bool(self.username), path, "password_file",
                 self.password_file, "needs a username")
        _require(not self.ca_file or self.tls, path, "ca_file", self.ca_file,
                 "is used with tls = true only")
        _require(5 <= self.keepalive_s <= 65535, path, "keepalive_s", self.keepalive_s,
                 "must be 5..65535 s")
        for name in ("connect_timeout_s", "publish_timeout_s", "reconnect_base_s"):
            _require(getattr(self, name) > 0, path, name, getattr(self, name), "must be > 0")
        _require(self.reconnect_max_backoff_s >= self.reconnect_base_s, path,
                 "reconnect_max_backoff_s", self.reconnect_max_backoff_s,
                 "must be >= reconnect_base_s")
        _require(1 <= self.queue_size <= 100_000, path, "queue_size", self.queue_size,
                 "must be 1..100000")


@dataclass(frozen=True)
class Config:
    """The whole configuration; ``mode`` says whether devices are real or emulated."""

    mode: Literal["sim", "robot"] = "sim"
    sensor: SensorConfig = field(default_factory=SensorConfig)
    bus: BusConfig = field(default_factory=BusConfig)
    press: PressConfig = field(default_factory=PressConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    api: ApiConfig = field(default_factory=ApiConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    button: ButtonConfig = field(default_factory=ButtonConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    vlm: VLMConfig = field(default_factory=VLMConfig)
    mqtt: MqttConfig = field(default_factory=MqttConfig)
    poses: dict[str, tuple[int, ...]] = field(default_factory=_default_poses)

    def validate(self, path: str) -> None:
        for name in ("rest", "above", "lowered"):
            if name not in self.poses:
                raise ConfigError(f"poses.{name} is missing: add it, or teach it with "
                                  f"`vt-edge pose teach {name}`")
        for name, pose in self.poses.items():
            _require(len(pose) == len(self.bus.joint_ids), "poses", name, pose,
                     f"needs one raw position per joint {self.bus.joint_ids}")
            _require(all(0 <= v <= 4095 for v in pose), "poses", name, pose,
                     "raw positions are 0..4095")


def _require(ok: bool, path: str, name: str, value: Any, why: str) -> None:
    if not ok:
        raise ConfigError(f"{path}.{name} = {_show(value)}: {why}")


def _show(value: Any) -> str:
    """``repr`` for an error message: short, and never failing (Python refuses to print
    integers of more than 4300 digits)."""
    try:
        text = repr(value)
    except ValueError:
        return f"<an integer of {value.bit_length()} bits>"
    return text if len(text) <= 200 else text[:200] + "..."


def load_config(path: str | Path) -> Config:
    """Read ``path`` (TOML) into a validated :class:`Config`."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file {path} cannot be read: {exc}") from None
    except ValueError as exc:  # TOMLDecodeError, or an integer Python will not parse
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None
    return apply_environment(config_from_dict(raw, source=str(path)))


def apply_environment(cfg: Config, environ: Mapping[str, str] | None = None) -> Config:
    """``cfg`` with the environment's overrides, which win over the file so that a
    supervisor need not edit it: ``$VTZERO_STATE_DIR`` (``runtime.state_dir``: systemd's
    StateDirectory=), ``$VTZERO_VLM_URL`` and ``$VTZERO_VLM_MODEL`` (``vlm.base_url``,
    ``vlm.model``), and ``$VTZERO_API_TOKEN`` (``api.token``, where neither it nor
    ``api.token_file`` is set)."""
    env = os.environ if environ is None else environ
    runtime, vlm, api = cfg.runtime, cfg.vlm, cfg.api
    if state_dir := env.get("VTZERO_STATE_DIR"):
        runtime = replace(runtime, state_dir=state_dir)
    if url := env.get("VTZERO_VLM_URL", "").strip():
        vlm = replace(vlm, base_url=url.rstrip("/"))
    if model := env.get("VTZERO_VLM_MODEL", "").strip():
        vlm = replace(vlm, model=model)
    if vlm is not cfg.vlm:
        vlm.validate("vlm (with $VTZERO_VLM_URL/$VTZERO_VLM_MODEL)")
    if (token := env.get("VTZERO_API_TOKEN")) and not (api.token or api.token_file):
        api = replace(api, token=token)
    return replace(cfg, runtime=runtime, vlm=vlm, api=api)


def config_from_dict(raw: dict[str, Any], source: str = "<config>") -> Config:
    try:
        return from_dict(Config, raw, "")
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def from_dict(cls: type, raw: Any, path: str) -> Any:
    """Build dataclass ``cls`` from a TOML table, checking keys and types recursively."""
    where = path or "top level"
    if not isinstance(raw, dict):
        raise ConfigError(f"{where} must be a table, got {type(raw).__name__} {_show(raw)}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - set(fields))
    if unknown:
        raise ConfigError(
            f"unknown key {_join(path, unknown[0])!r}; known keys of {where}: "
            + ", ".join(sorted(fields))
        )
    values = {name: _convert(hints[name], raw[name], _join(path, name)) for name in raw}
    obj = cls(**values)
    validate = getattr(obj, "validate", None)
    if validate is not None:
        validate(path or "config")
    return obj


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


def _convert(tp: Any, value: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, path)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, path)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError("; ".join(errors))
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{path} = {_show(value)}: must be one of "
                              f"{', '.join(map(repr, args))}")
        return value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{path} = {_show(value)}: must be an array")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{path}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(f"{path} = {_show(value)}: must have {len(args)} elements")
        pairs = enumerate(zip(args, value, strict=True))
        return tuple(_convert(a, v, f"{path}[{i}]") for i, (a, v) in pairs)
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{path} = {_show(value)}: must be a table")
        return {str(k): _convert(args[1], v, f"{path}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path} = {_show(value)}: must be true or false")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path} = {_show(value)}: must be an integer")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{path} = {_show(value)}: must be a number")
        try:
            number = float(value)
        except OverflowError:  # an integer beyond any float
            number = math.inf
        if not math.isfinite(number):
            raise ConfigError(f"{path} = {_show(value)}: must be finite")
        return number
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path} = {_show(value)}: must be a string")
        return value
    if tp is Path:
        if not isinstance(value, str) or not value:
            raise ConfigError(f"{path} = {_show(value)}: must be a non-empty path string")
        return Path(value)
    raise ConfigError(f"{path}: unsupported type {tp!r} in the config schema")
