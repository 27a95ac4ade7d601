"""rosbag2 bags of presses: stored episodes exported, or the live stream recorded.

A bag is what ``ros2 bag`` reads: a directory with ``metadata.yaml`` and one MCAP file of
CDR-encoded ROS 2 messages whose ``ros2msg`` definitions are embedded, so ``ros2 bag info``,
PlotJuggler and Foxglove read it without any of its packages installed. It is written by
``rosbags`` (a maintained pure-Python rosbag2 library: its CDR serialiser and MCAP storage
are the ones its reader is tested against), in the ``export`` extra.

Topics::

    /xServTopic                xela_server_ros2/msg/SensStream     raw counts, both pads
    /tactile/units             std_msgs/msg/Float32MultiArray      (raw - tare) / 65536
    /gripper                   sensor_msgs/msg/JointState          width (m), current (mA)
    /press/state               vtzero_msgs/msg/PressState          above, ..., idle
    /camera/image/compressed   sensor_msgs/msg/CompressedImage     the photo sent to the VLM
    /result                    vtzero_msgs/msg/Result              label, top-k, error, JSON
    /events                    std_msgs/msg/String                 (live) each event, JSON

Raw frames use XELA's own ROS 2 messages (``xela_server_ros2``, MIT, as its ROS 2 node publishes
them on ``/xServTopic``): one ``SensorFull`` per pad, ``sensor_pos`` = pad + 1, ``message`` =
the server's sequence number, ``time`` = the server's time, ``taxels`` the pad's ``Taxel``
(uint16 x, y, z; 16 on an XR1944) row by row, ``forces`` empty. The tare-subtracted units have
no XELA message (its ``Forces`` are newtons from XELA's calibration, which ours are not): a
``Float32MultiArray`` with layout dims ``pad`` (2), ``taxel`` (16 on an XR1944), ``axis`` (3).
Press states and results are ``vtzero_msgs`` messages; their ``.msg`` files ship in
``edge/ros2/vtzero_msgs`` (a colcon package) for ``ros2 bag play``.

Time: bag times and header stamps are wall time (ns since the epoch): the robot's monotonic
times (the tactile clock of :mod:`edge.recordings.mcaplog`) plus the offset between the clocks,
taken at the instant the episode was stored (``created`` and ``created_monotonic``; an
episode stored before that was kept is mapped with its last press state at ``created``,
which puts it late by the time between the two: the press's analysis). The offset and how
it was found are in ``metadata.yaml``'s ``custom_data``. Messages without a header (the XELA and
array messages) carry their time as the bag's log time.

Bags are written to a staging directory beside the target and renamed into place complete
(:func:`edge.core.atomic.atomic_dir`): an interrupted export never replaces a good bag.
"""

from __future__ import annotations

import json
import logging
import time
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from edge import __version__
from edge.core import preprocess
from edge.core.atomic import atomic_dir
from edge.core.errors import EdgeError, StoreError
from edge.core.layout import PadLayout
from edge.recordings.mcaplog import ns, result_message
from edge.runtime.domain import Episode

log = logging.getLogger(__name__)

EXTRA_HINT = "pip install 'vtzero[export]'"
# rosbag2's metadata version (rosbags writes 8 or 9): the older, read by more ros2 releases.
ROSBAG_VERSION = 8
LIVE_EVENTS_TYPE = "std_msgs/msg/String"

# XELA's ROS 2 interface (github.com/mcsix/xela_server_ros2, msg/*.msg).
XELA_MSGS = {
    "xela_server_ros2/msg/Taxel": "uint16 x\nuint16 y\nuint16 z\n",
    "xela_server_ros2/msg/Forces": "float32 x\nfloat32 y\nfloat32 z\n",
    "xela_server_ros2/msg/SensorFull": (
        "uint32 message\nfloat64 time\nstring model\nuint8 sensor_pos\n"
        "xela_server_ros2/Taxel[] taxels\nxela_server_ros2/Forces[] forces\n"),
    "xela_server_ros2/msg/SensStream": "xela_server_ros2/SensorFull[] sensors\n",
}
TOPICS: dict[str, str] = {
    "/xServTopic": "xela_server_ros2/msg/SensStream",
    "/tactile/units": "std_msgs/msg/Float32MultiArray",
    "/gripper": "sensor_msgs/msg/JointState",
    "/press/state": "vtzero_msgs/msg/PressState",
    "/camera/image/compressed": "sensor_msgs/msg/CompressedImage",
    "/result": "vtzero_msgs/msg/Result",
    "/events": LIVE_EVENTS_TYPE,
}
# The MCAP export's topic names (edge.recordings.mcaplog) where the bag's differ.
FROM_MCAP = {"/tactile/raw": "/xServTopic", "/camera/image": "/camera/image/compressed"}
EPISODE_TOPICS = tuple(t for t in TOPICS if t != "/events")
LIVE_TOPICS = ("/xServTopic", "/press/state", "/events")


def require_rosbags() -> None:
    """A one-line error naming the extra to install where ``rosbags`` is missing."""
    try:
        import rosbags.rosbag2  # noqa: F401
    except ImportError:
        raise EdgeError(f"rosbag2 export needs the rosbags package: {EXTRA_HINT}") from None


def vtzero_msgs() -> dict[str, str]:
    """{type name: .msg text} of the messages shipped in ``edge/ros2/vtzero_msgs``."""
    folder = resources.files("edge") / "ros2" / "vtzero_msgs" / "msg"
    return {f"vtzero_msgs/msg/{p.name.removesuffix('.msg')}": p.read_text()
            for p in folder.iterdir() if p.name.endswith(".msg")}


def typestore() -> Any:
    """ROS 2 Humble's standard messages plus XELA's and vtzero's."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in {**XELA_MSGS, **vtzero_msgs()}.items():
        store.register(get_types_from_msg(text, name))
    return store


class RosbagLog:
    """One bag being written in a staging directory; :meth:`finish` renames it into place.

    Takes the same calls as :class:`edge.recordings.mcaplog.McapLog` (its topic names and JSON
    messages), so the live recorder writes either. ``offset_s`` maps monotonic times to
    wall time.
    """

    def __init__(self, path: str | Path, topics: tuple[str, ...] = EPISODE_TOPICS, *,
                 offset_s: float, sensor_model: str = "",
                 custom: dict[str, Any] | None = None) -> None:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        self.path = Path(path)
        self.offset_s = offset_s
        self.sensor_model = sensor_model
        self.counts: dict[str, int] = dict.fromkeys(topics, 0)
        self._store = typestore()
        self._types = self._store.types
        self._staging = atomic_dir(self.path)
        bag = self._staging.__enter__()
        self.tmp = bag.parent
        try:
            self._writer = Writer(bag, version=ROSBAG_VERSION, storage_plugin=StoragePlugin.MCAP)
            # zstd chunks inside the MCAP file (what ros2 bag record's MCAP storage does with
            # its zstd preset): a tenth the size, read by every MCAP reader.
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            self._writer.open()
            self._conns = {t: self._writer.add_connection(t, TOPICS[t], typestore=self._store)
                           for t in topics}
            for key, value in {"software_version": __version__,
                               "clock_offset_s": repr(offset_s), **(custom or {})}.items():
                self._writer.set_custom_data(f"vtzero.{key}", "" if value is None
                                             else str(value))
        except BaseException:
            self.abandon()
            raise

    # --- messages -------------------------------------------------------------------------
    def _write(self, topic: str, t: float, msg: Any) -> None:
        self._writer.write(self._conns[topic], ns(t + self.offset_s),
                           self._store.serialize_cdr(msg, TOPICS[topic]))
        self.counts[topic] += 1

    def header(self, t: float, frame_id: str = "") -> Any:
        n = ns(t + self.offset_s)
        return self._types["std_msgs/msg/Header"](
            stamp=self._types["builtin_interfaces/msg/Time"](
                sec=n // 1_000_000_000, nanosec=n % 1_000_000_000),
            frame_id=frame_id)

    def tactile(self, topic: str, recv_time: np.ndarray, sensor_time: np.ndarray,
                seq: np.ndarray, values: np.ndarray, pads: int = 2) -> None:
        """Frames (N, C), channel = (pad * taxels + taxel) * 3 + axis: raw counts on the XELA
        topic, tactile units as arrays."""
        topic = FROM_MCAP.get(topic, topic)
        per_pad = values.reshape(len(values), pads, -1, 3)
        if topic == "/xServTopic":
            taxel, full, stream = (self._types[f"xela_server_ros2/msg/{n}"]
                                   for n in ("Taxel", "SensorFull", "SensStream"))
            for i, frame in enumerate(per_pad.tolist()):
                self._write(topic, float(recv_time[i]), stream(sensors=[
                    full(message=int(seq[i]) & 0xFFFFFFFF, time=float(sensor_time[i]),
                         model=self.sensor_model, sensor_pos=p + 1,
                         taxels=[taxel(x=x, y=y, z=z) for x, y, z in taxels], forces=[])
                    for p, taxels in enumerate(frame)]))
            return
        dim, layout, array = (self._types[f"std_msgs/msg/{n}"] for n in (
            "MultiArrayDimension", "MultiArrayLayout", "Float32MultiArray"))
        n_pads, n_taxels = per_pad.shape[1], per_pad.shape[2]
        dims = [dim(label="pad", size=n_pads, stride=n_pads * n_taxels * 3),
                dim(label="taxel", size=n_taxels, stride=n_taxels * 3),
                dim(label="axis", size=3, stride=3)]
        data = values.astype(np.float32)
        for i in range(len(values)):
            self._write(topic, float(recv_time[i]),
                        array(layout=layout(dim=dims, data_offset=0), data=data[i]))

    def gripper(self, t: np.ndarray, width_m: np.ndarray, current_ma: np.ndarray) -> None:
        state = self._types["sensor_msgs/msg/JointState"]
        for ti, w, c in zip(t.tolist(), width_m.tolist(), current_ma.tolist(), strict=True):
            self._write("/gripper", ti, state(
                header=self.header(ti, "gripper"), name=["gripper"],
                position=np.array([w]), velocity=np.array([], dtype=np.float64),
                effort=np.array([c])))

    def image(self, t: float, data: bytes, fmt: str) -> None:
        self._write("/camera/image/compressed", t,
                    self._types["sensor_msgs/msg/CompressedImage"](
                        header=self.header(t, "camera"), format=fmt,
                        data=np.frombuffer(data, dtype=np.uint8)))

    def result(self, t: float, episode: Episode) -> None:
        res = result_message(episode)
        topk = res["topk"]
        self._write("/result", t, self._types["vtzero_msgs/msg/Result"](
            header=self.header(t), episode=res["episode"], status=res["status"],
            label=res["label"] or "", candidates=res["candidates"],
            topk_labels=[k["label"] for k in topk],
            topk_distances=np.array([k["distance"] for k in topk], dtype=np.float32),
            description=res["description"] or "", error=res["error"] or "",
            press_result=str(res["press"].get("result") or ""),
            json=json.dumps(res, sort_keys=True, default=str)))

    def add(self, topic: str, t: float, message: dict[str, Any]) -> None:
        """A JSON-shaped message as :class:`~edge.recordings.mcaplog.McapLog` takes it (press
        states and events)."""
        if topic == "/press/state":
            self._write(topic, t, self._types["vtzero_msgs/msg/PressState"](
                header=self.header(t), state=str(message.get("state")),
                episode=message.get("episode") or ""))
        elif topic == "/events":
            self._write(topic, t, self._types[LIVE_EVENTS_TYPE](
                data=json.dumps(message, sort_keys=True, default=str)))
        else:
            raise ValueError(f"no rosbag2 form for {topic}")

    def metadata(self, name: str, data: dict[str, Any]) -> None:
        for key, value in data.items():
            self._writer.set_custom_data(f"{name}.{key}", "" if value is None else str(value))

    # --- completion -----------------------------------------------------------------------
    def finish(self) -> Path:
        try:
            self._writer.close()
            self._staging.__exit__(None, None, None)
        except BaseException as exc:
            self._staging.__exit__(type(exc), exc, exc.__traceback__)
            raise
        return self.path

    def abandon(self) -> None:
        err = EdgeError("abandoned")
        self._staging.__exit__(EdgeError, err, None)


# --------------------------------------------------------------------------------------
# Stored episodes


def clock_offset(episode: Episode, t_last: float) -> tuple[float, str]:
    """(wall - monotonic seconds, how it was found) for a stored episode."""
    created = episode.created
    if created is None:
        return 0.0, "none (the episode has no creation time): stamps are monotonic"
    # (Kept by the store beside the fields of this version's episodes.)
    mono = episode.extra.get("created_monotonic")
    if mono is not None:
        return float(created) - float(mono), "created - created_monotonic"
    return float(created) - t_last, "created - the last press state (approximate)"


def export_episodes(store: Any, episode_ids: list[str], dest: str | Path) -> Path:
    """Write stored episodes as one rosbag2 bag (directory ``dest``); returns its path.
    Blocks (file I/O): off the event loop."""
    from edge.recordings.mcaplog import episode_files

    require_rosbags()
    items = [episode_files(store, eid) for eid in episode_ids]
    first = items[0]
    offset, how = clock_offset(first.episode, first.t_last)
    model = next((i.rec.sensor_model for i in items if i.rec is not None), "")
    try:
        out = RosbagLog(dest, offset_s=offset, sensor_model=model, custom={
            "episodes": ",".join(episode_ids), "clock": "the robot's monotonic clock + "
            "clock_offset_s", "clock_offset_from": how})
    except OSError as exc:
        raise StoreError(f"cannot write the bag {dest}: {exc}") from None
    try:
        for item in items:
            # Each episode on its own offset: the robot may have rebooted between them.
            out.offset_s, _ = clock_offset(item.episode, item.t_last)
            rec = item.rec
            if rec is not None:
                pads = PadLayout.of_recording(rec.extra, rec.channels).pads
                out.tactile("/tactile/raw", rec.recv_time, rec.sensor_time, rec.seq,
                            rec.frames, pads)
                out.tactile("/tactile/units", rec.recv_time, rec.sensor_time, rec.seq,
                            preprocess.recording_units(rec), pads)
                out.gripper(rec.gripper_time, rec.gripper_width_m, rec.gripper_current_ma)
            for state, t in item.states:
                out.add("/press/state", t, {"state": state, "episode": item.episode.id})
            if item.image is not None:
                out.image(item.t_first, item.image, item.image_format)
            out.result(item.t_last, item.episode)
        return out.finish()
    except OSError as exc:
        out.abandon()
        raise StoreError(f"cannot write the bag {dest}: {exc}") from None
    except BaseException:
        out.abandon()
        raise


def live_offset() -> float:
    """Wall minus monotonic now (the live recorder stamps with it)."""
    return time.time() - time.monotonic()

