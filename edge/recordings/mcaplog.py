"""MCAP files of presses: one stored episode exported, or the live stream recorded.

MCAP (https://mcap.dev) is the log container Foxglove, ROS 2 and ``mcap`` tools read. Every
message is JSON with a JSON schema (``jsonschema`` encoding). The photo uses Foxglove's
well-known ``foxglove.CompressedImage``; the rest are ``vtzero.*`` schemas whose
``timestamp`` is Foxglove's ``{sec, nsec}`` time, so Foxglove plots any field against it.

Topics::

    /tactile/raw    vtzero.TactileFrame       raw counts, both pads, x/y/z per taxel
    /tactile/units  vtzero.TactileFrame       (raw - tare) / 65536: the units x_th is in
    /gripper        vtzero.GripperState       width and squeeze current (every 20 ms)
    /press/state    vtzero.PressState         above, lowered, tare, closing, ... idle
    /camera/image   foxglove.CompressedImage  the photo sent to the VLM
    /result         vtzero.Result             label, top-k, description, error, timings
    /events         vtzero.Event              (live recording) every daemon event as sent

Clock: log times and ``timestamp`` fields are the robot's monotonic clock (seconds since
boot), the clock the daemon stamps tactile frames with, so an export and a live recording
of the same press line up to the frame. ``sensor_time`` is the XELA server's own clock. The
episode's wall-clock times are in the result and in the file's ``vtzero`` metadata. The
photo has no capture time of its own: it is stamped at the press's first state (it is taken
while the arm moves), the result at the press's last.

Files are written atomically: to ``.NAME.tmp`` beside the target, fsynced, renamed.
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer

from edge import __version__
from edge.core import preprocess, recording
from edge.core.atomic import fsync_dir
from edge.core.errors import NotFoundError, StoreError
from edge.core.layout import PadLayout
from edge.runtime.domain import Episode, PressState, PressSummary

log = logging.getLogger(__name__)

SUFFIX = ".mcap"
PROFILE = ""  # no ROS profile: plain JSON messages
TIME = {"type": "object", "title": "time", "properties": {
    "sec": {"type": "integer", "minimum": 0},
    "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}


def _pad_schema(item: str) -> dict[str, Any]:
    axis = {"type": "array", "items": {"type": item}, "minItems": 1}
    return {"type": "object", "properties": {"pad": {"type": "integer"}, "x": axis,
                                             "y": axis, "z": axis}}


def _tactile_schema(item: str, what: str) -> dict[str, Any]:
    return {
        "title": "vtzero.TactileFrame", "type": "object",
        "description": f"One frame of both XELA pads, {what}; taxel i of a pad is x[i], "
                       "y[i], z[i] (row-major from the top left, 4 x 4 on XR1944 pads)",
        "properties": {"timestamp": {**TIME, "description": "receive time (monotonic)"},
                       "recv_time": {"type": "number", "description": "monotonic s"},
                       "sensor_time": {"type": "number", "description": "sensor server s"},
                       "seq": {"type": "integer"},
                       "pads": {"type": "array", "items": _pad_schema(item)}}}


SCHEMAS: dict[str, dict[str, Any]] = {
    "vtzero.TactileFrame.raw": _tactile_schema("integer", "raw counts"),
    "vtzero.TactileFrame.units": _tactile_schema(
        "number", "tactile units (raw - tare) / 65536"),
    "vtzero.GripperState": {
        "title": "vtzero.GripperState", "type": "object",
        "properties": {"timestamp": TIME, "width_m": {"type": "number"},
                       "current_ma": {"type": "number"}}},
    "vtzero.PressState": {
        "title": "vtzero.PressState", "type": "object",
        "properties": {"timestamp": TIME, "state": {"type": "string"},
                       "episode": {"type": ["string", "null"]}}},
    "foxglove.CompressedImage": {
        "title": "foxglove.CompressedImage", "description": "A compressed image",
        "type": "object",
        "properties": {
            "timestamp": {**TIME, "description": "Timestamp of image"},
            "frame_id": {"type": "string", "description": "Frame of reference for the image"},
            "data": {"type": "string", "contentEncoding": "base64",
                     "description": "Compressed image data"},
            "format": {"type": "string", "description": "Image format: jpeg, png"}}},
    "vtzero.Result": {
        "title": "vtzero.Result", "type": "object",
        "properties": {
            "timestamp": TIME, "episode": {"type": "string"}, "status": {"type": "string"},
            "label": {"type": ["string", "null"]},
            "candidates": {"type": "array", "items": {"type": "string"}},
            "topk": {"type": "array", "items": {"type": "object", "properties": {
                "label": {"type": "string"}, "distance": {"type": "number"}}}},
            "description": {"type": ["string", "null"]},
            "error": {"type": ["string", "null"]},
            "timings": {"type": "object", "additionalProperties": {"type": "number"}},
            "press": {"type": "object"}, "vlm_mode": {"type": ["string", "null"]},
            "created": {"type": ["number", "null"], "description": "wall clock, Unix s"}}},
    "vtzero.Event": {
        "title": "vtzero.Event", "type": "object",
        "description": "A daemon event as /v1/events sends it (type, episode, ...)",
        "properties": {"timestamp": TIME, "type": {"type": "string"}}},
}
TOPICS: dict[str, str] = {
    "/tactile/raw": "vtzero.TactileFrame.raw",
    "/tactile/units": "vtzero.TactileFrame.units",
    "/gripper": "vtzero.GripperState",
    "/press/state": "vtzero.PressState",
    "/camera/image": "foxglove.CompressedImage",
    "/result": "vtzero.Result",
    "/events": "vtzero.Event",
}
EPISODE_TOPICS = tuple(t for t in TOPICS if t != "/events")
LIVE_TOPICS = ("/tactile/raw", "/press/state", "/events")
# What of the press the result message carries.
_RESULT_PRESS = PressSummary.keys("result", "message", "t_cross", "t_stop", "stop_latency_ms",
                                  "peak_level")


def ns(t: float) -> int:
    return max(0, round(t * 1e9))


def stamp(t: float) -> dict[str, int]:
    n = ns(t)
    return {"sec": n // 1_000_000_000, "nsec": n % 1_000_000_000}


class McapLog:
    """One MCAP file being written to ``.NAME.tmp``; :meth:`finish` renames it into place."""

    def __init__(self, path: str | Path, topics: tuple[str, ...] = EPISODE_TOPICS,
                 chunk_size: int = 1024 * 1024) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.tmp")
        self.counts: dict[str, int] = dict.fromkeys(topics, 0)
        self._fh = open(self.tmp, "wb")  # closed in finish() or abandon()
        try:
            self._writer = Writer(self._fh, chunk_size=chunk_size,
                                  compression=CompressionType.ZSTD)
            self._writer.start(profile=PROFILE, library=f"vtzero {__version__}")
            schema_ids: dict[str, int] = {}
            self._channels: dict[str, int] = {}
            for topic in topics:
                name = TOPICS[topic]
                if name not in schema_ids:
                    schema_ids[name] = self._writer.register_schema(
                        name.removesuffix(".raw").removesuffix(".units"),
                        SchemaEncoding.JSONSchema,
                        json.dumps(SCHEMAS[name]).encode())
                self._channels[topic] = self._writer.register_channel(
                    topic, MessageEncoding.JSON, schema_ids[name])
        except BaseException:
            self.abandon()
            raise

    def add(self, topic: str, t: float, message: dict[str, Any]) -> None:
        """``message`` on ``topic`` at monotonic time ``t`` (seconds); ``timestamp`` set."""
        data = json.dumps({"timestamp": stamp(t), **message}, allow_nan=False,
                          separators=(",", ":")).encode()
        self._writer.add_message(self._channels[topic], ns(t), data, ns(t),
                                 self.counts[topic])
        self.counts[topic] += 1

    def tactile(self, topic: str, recv_time: np.ndarray, sensor_time: np.ndarray,
                seq: np.ndarray, values: np.ndarray, pads: int = 2) -> None:
        """Frames (N, C) with channel = (pad * taxels + taxel) * 3 + axis, one message each."""
        if len(values) == 0:
            return
        per_pad = values.reshape(len(values), pads, -1, 3)
        as_list = per_pad.tolist() if values.dtype.kind in "iu" else \
            np.round(per_pad.astype(np.float64), 8).tolist()
        for i, frame in enumerate(as_list):
            self.add(topic, float(recv_time[i]), {
                "recv_time": float(recv_time[i]), "sensor_time": float(sensor_time[i]),
                "seq": int(seq[i]),
                "pads": [{"pad": p, "x": [v[0] for v in taxels], "y": [v[1] for v in taxels],
                          "z": [v[2] for v in taxels]} for p, taxels in enumerate(frame)]})

    def metadata(self, name: str, data: dict[str, Any]) -> None:
        self._writer.add_metadata(name, {k: "" if v is None else str(v)
                                         for k, v in data.items()})

    def attach(self, name: str, media_type: str, data: bytes, t: float = 0.0) -> None:
        self._writer.add_attachment(ns(t), ns(t), name, media_type, data)

    def finish(self) -> Path:
        """Footer and index written, fsynced, renamed to :attr:`path`."""
        try:
            self._writer.finish()
            self._fh.flush()
            os.fsync(self._fh.fileno())
            self._fh.close()
            os.replace(self.tmp, self.path)
            fsync_dir(self.path.parent)
        except BaseException:
            self.abandon()
            raise
        return self.path

    def abandon(self) -> None:
        with contextlib.suppress(OSError):
            self._fh.close()
        with contextlib.suppress(OSError):
            self.tmp.unlink()


# --------------------------------------------------------------------------------------
# One stored episode


def _optional_file(store: Any, episode_id: str, name: str) -> Path | None:
    try:
        return store.file(episode_id, name)
    except NotFoundError:
        return None


def episode_mcap_path(episode_id: str, dest: str | Path) -> Path:
    dest = Path(dest)
    return dest / f"{episode_id}{SUFFIX}" if dest.is_dir() else dest


@dataclass(frozen=True)
class EpisodeFiles:
    """A stored episode as the exports read it."""

    episode: Episode
    press: PressSummary | None
    rec: recording.Recording | None
    image: bytes | None
    image_format: str  # jpeg | png | ""
    states: list[tuple[PressState, float]]
    t_first: float  # the press's first state (monotonic s): the photo's stamp
    t_last: float  # its last: the result's


def episode_files(store: Any, episode_id: str) -> EpisodeFiles:
    episode = store.get(episode_id)
    rec = None
    npz = _optional_file(store, episode_id, "press.press.npz")
    if npz is not None:
        rec = recording.load(npz)
    image, image_format = None, ""
    for name, fmt in (("image.jpg", "jpeg"), ("image.png", "png")):
        found = _optional_file(store, episode_id, name)
        if found is not None:
            image, image_format = found.read_bytes(), fmt
            break
    press = episode.press
    states = list(press.states) if press is not None else []
    t_first = states[0][1] if states else (float(rec.recv_time[0]) if rec else 0.0)
    t_last = states[-1][1] if states else (float(rec.recv_time[-1]) if rec else 0.0)
    return EpisodeFiles(episode, press, rec, image, image_format, states, t_first, t_last)


def export_episode(store: Any, episode_id: str, dest: str | Path) -> Path:
    """Write one stored episode as an MCAP file (``dest`` a file, or a directory for
    ``ID.mcap``); returns the path written. Blocks (file I/O): off the event loop."""
    path = episode_mcap_path(episode_id, dest)
    item = episode_files(store, episode_id)
    episode, rec, image, image_format = item.episode, item.rec, item.image, item.image_format
    states, t_first, t_last = item.states, item.t_first, item.t_last
    try:
        out = McapLog(path)
    except OSError as exc:
        raise StoreError(f"episode {episode_id}: cannot write {path}: {exc}") from None
    try:
        if rec is not None:
            pads = PadLayout.of_recording(rec.extra, rec.channels).pads
            out.tactile("/tactile/raw", rec.recv_time, rec.sensor_time, rec.seq,
                        rec.frames, pads)
            out.tactile("/tactile/units", rec.recv_time, rec.sensor_time, rec.seq,
                        preprocess.recording_units(rec), pads)
            for t, width, current in zip(rec.gripper_time, rec.gripper_width_m,
                                         rec.gripper_current_ma, strict=True):
                out.add("/gripper", float(t), {"width_m": float(width),
                                               "current_ma": float(current)})
        for state, t in states:
            out.add("/press/state", t, {"state": state, "episode": episode_id})
        if image is not None:
            out.add("/camera/image", t_first, {
                "frame_id": "camera", "format": image_format,
                "data": base64.b64encode(image).decode("ascii")})
        out.add("/result", t_last, result_message(episode))
        out.metadata("vtzero", {
            "episode": episode_id, "software_version": __version__,
            "episode_software_version": episode.software_version,
            "clock": "monotonic (seconds since the robot booted)",
            "created_unix_s": episode.created, "x_th": episode.x_th,
            "t_stop": item.press.t_stop if item.press is not None else None,
            "t_cross": item.press.t_cross if item.press is not None else None,
            "sensor_model": rec.sensor_model if rec is not None else None})
        out.attach("episode.json", "application/json",
                   json.dumps(episode.to_json(), indent=2, sort_keys=True,
                              default=str).encode(), t_last)
        return out.finish()
    except OSError as exc:
        out.abandon()
        raise StoreError(f"episode {episode_id}: cannot write {path}: {exc}") from None
    except BaseException:
        out.abandon()
        raise


def result_message(episode: Episode) -> dict[str, Any]:
    return {
        "episode": episode.id, "status": episode.status.value,
        "label": episode.label, "candidates": list(episode.candidates or []),
        "topk": [n.to_json() for n in episode.topk or []],
        "description": episode.description,
        "error": episode.error or episode.last_error,
        "timings": {k: float(v) for k, v in episode.timings.items()
                    if isinstance(v, int | float)},
        "press": episode.press_json(_RESULT_PRESS),
        "vlm_mode": episode.vlm_mode, "created": episode.created,
    }
