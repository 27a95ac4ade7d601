"""The daemon's state as its consumers read it: the press's states and results, the summary of
one press and the daemon's health.

Each crosses a boundary as JSON (the API, MQTT, the store, MCAP and ROS 2 exports, the
operator page); the enums' values are the strings on the wire, and ``to_json`` gives the
documented form. A consumer reads the fields; one that passes on a subset of the JSON names
its keys with :meth:`PressSummary.keys`, which refuses an unknown one at import. Either way a
renamed field fails where it is read, not in a client far away.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from edge.core.errors import StoreError


class PressState(StrEnum):
    """Where a press is (docs/method.md, 'Press'); ``idle`` between presses."""

    IDLE = "idle"
    ABOVE = "above"  # the gripper opened, the arm moving above the object
    LOWERED = "lowered"  # the arm moving down around the object
    TARE = "tare"  # the unloaded tare window
    CLOSING = "closing"  # the gripper closing, the threshold armed
    HOLDING = "holding"  # stopped at the threshold, held for dt_stopping_s
    OPENING = "opening"
    RETURNING = "returning"  # the arm moving back above the object


class PressResult(StrEnum):
    """How a press ended."""

    OK = "ok"  # the threshold was crossed and the stop went out
    NO_CONTACT = "no_contact"  # closed for close_timeout_s without crossing x_th
    # The gripper stalled on the object at its current cap, the norm still under x_th.
    BELOW_THRESHOLD = "below_threshold"
    ABORTED = "aborted"  # on request, or a norm far past x_th
    STALE = "stale"  # the tactile stream went stale
    ERROR = "error"  # a device or internal error; ``message`` says which


@dataclass(frozen=True)
class PressSummary:
    """One press as the episode keeps it (``episode.json``'s ``"press"``, the API's
    episodes). JSON form::

        {"result": "ok" | "no_contact" | "below_threshold" | "aborted" | "stale" | "error",
         "message": str,                  # why, when not ok ("" when ok)
         "contact": bool,                 # result == "ok"
         "t_cross": float | null,         # receive time of the first frame over x_th (s)
         "t_stop": float | null,          # when the stop write went out (s)
         "stop_latency_ms": float | null, # t_stop - t_cross, in ms
         "peak_level": float,             # the highest norm over the tare
         "level_at_cross": float,         # the norm of the frame that crossed x_th
         "peak_squeeze_ma": float | null, # the highest gripper current traced
         "states": [[state, t], ...],     # every state entered, in order (s)
         "lowering_level": float | null,  # the norm lowering the arm moved the pads by
         "window_rate_hz": float | null,  # the rate xela_server sent at over the crop window
         "press_rate_hz": float | null}   # ... and over the press's recording

    Times are on the daemon's monotonic clock. Keys this version does not know (written by
    a newer one) are carried through in ``extra``, as the episode's are; ``lowering_level``
    and the rates, which older episodes lack, read as null there. ``peak_level`` is the
    press's peak norm (:func:`edge.core.preprocess.peak_norm`).
    """

    result: PressResult
    message: str
    contact: bool
    t_cross: float | None
    t_stop: float | None
    stop_latency_ms: float | None
    peak_level: float
    level_at_cross: float
    peak_squeeze_ma: float | None
    states: tuple[tuple[PressState, float], ...]
    lowering_level: float | None = None
    window_rate_hz: float | None = None
    press_rate_hz: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def entered(self, state: PressState) -> float | None:
        """When the press first entered ``state``; None if it never did."""
        return next((t for s, t in self.states if s == state), None)

    def to_json(self) -> dict[str, Any]:
        out = dict(self.extra)
        for k in _PRESS_KEYS:
            out[k] = getattr(self, k)
        out["result"] = str(self.result)
        out["states"] = [[str(s), t] for s, t in self.states]
        return out

    @classmethod
    def from_json(cls, data: Any, where: str = "press") -> PressSummary:
        """The summary in ``data``; :class:`StoreError` naming ``where`` and the key if it
        is not one."""
        if not isinstance(data, dict):
            raise StoreError(f"{where}: not a JSON object")
        missing = [k for k in _REQUIRED_PRESS_KEYS if k not in data]
        if missing:
            raise StoreError(f"{where}: missing {', '.join(missing)}")
        try:
            result = PressResult(data["result"])
        except ValueError:
            raise StoreError(f"{where}: unknown result {data['result']!r}; known: "
                             + ", ".join(PressResult)) from None
        try:
            states = tuple((PressState(s), float(t)) for s, t in data["states"])
        except (TypeError, ValueError):
            raise StoreError(f"{where}: 'states' must be a list of [state, time] with a "
                             "state of " + ", ".join(PressState)) from None
        return cls(**{k: data[k] for k in _PRESS_KEYS if k in data}
                   | {"result": result, "states": states},
                   extra={k: v for k, v in data.items() if k not in _PRESS_KEYS})

    @classmethod
    def keys(cls, *names: str) -> tuple[str, ...]:
        """``names``, each a key of the JSON form (ValueError naming any that is not): the
        subset a consumer carries."""
        unknown = [n for n in names if n not in _PRESS_KEYS]
        if unknown:
            raise ValueError(f"not keys of a press summary: {', '.join(unknown)}")
        return names


_PRESS_KEYS = tuple(f.name for f in dataclasses.fields(PressSummary) if f.name != "extra")
# What an episode written by any version holds (the others have a default).
_REQUIRED_PRESS_KEYS = tuple(f.name for f in dataclasses.fields(PressSummary)
                             if f.default is dataclasses.MISSING
                             and f.default_factory is dataclasses.MISSING)


@dataclass(frozen=True)
class Health:
    """The daemon's health (``GET /healthz``, MQTT ``P/health``). JSON form::

        {"ok": bool,                      # ready, fresh, and none of the errors below
         "ready": bool,                   # started: devices, model and first frame
         "sensor_fresh": bool,            # a frame younger than 1 s, the stream not stale
         "bus_error": str | null,         # a motor fault (names the motor)
         "store_error": str | null,       # why no episode can be kept (disk full)
         "sensor_error": str | null,      # no stream since the start, or a layout refused
         "vlm_error": str | null,         # the VLM server unreachable (names its URL)
         "torque_on": bool | null,        # null without a Dynamixel bus
         "state": "idle" | "above" | ..., # the press's state (PressState)
         "episode": str | null,           # the episode running
         "last_frame_age_s": float | null,# null before the first frame
         "model_digest": str,             # changes when a reload took a new model
         "version": str}                  # the software's
    """

    ok: bool
    ready: bool
    sensor_fresh: bool
    bus_error: str | None
    store_error: str | None
    sensor_error: str | None
    vlm_error: str | None
    torque_on: bool | None
    state: PressState
    episode: str | None
    last_frame_age_s: float | None
    model_digest: str
    version: str

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self) | {"state": str(self.state)}
