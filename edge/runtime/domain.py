"""The daemon's domain types, as its consumers read them: the press's states and results,
the summary of one press, the daemon's health, an episode (one recognition as the store
keeps it and the API, the CLI and the retry task read it), and the events published while
it runs.

Each crosses a boundary as JSON (the API, MQTT, the store, MCAP and ROS 2 exports, the
operator page); the enums' values are the strings on the wire, and ``to_json`` gives the
documented form. A consumer reads the fields; one that passes on a subset of the JSON names
its keys with :meth:`PressSummary.keys`, which refuses an unknown one at import. Either way a
renamed field fails where it is read, not in a client far away. The episode's JSON form
(``episode.json`` in the store, the API's answers) keeps the keys it has always had; keys
this version does not know (written by a newer one) are carried through unchanged in
``extra`` rather than refused or lost.

The bus that carries the events is :mod:`edge.runtime.events` (asyncio's, kept out of here so
that what reads these types, the command line included, loads no event loop machinery).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, ClassVar, Literal

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
         "version": str,                  # the software's
         "stale_references": int,         # taught references another model embedded
         "stale_reference_labels": [str]} # ... their labels (kept, never used: teach
                                          # again, or fold them into the next build)

    ``ok`` does not read the stale references: the daemon recognises without them.
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
    stale_references: int = 0
    stale_reference_labels: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self) | {"state": str(self.state),
                                           "stale_reference_labels":
                                               list(self.stale_reference_labels)}


# --- the episode ----------------------------------------------------------------------


class Status(StrEnum):
    RUNNING = "running"  # the press or its analysis is under way (never stored)
    PENDING = "pending"  # analysed; the VLM's answer is still due (retried with backoff)
    DONE = "done"  # the VLM answered with one of the candidates
    INVALID_ANSWER = "invalid_answer"  # it answered, but with no candidate, twice
    NOT_CONFIGURED = "not_configured"  # no VLM endpoint configured: the prompt is kept
    VLM_ERROR = "vlm_error"  # the VLM refused the question (asking again will not help)
    CAMERA_ERROR = "camera_error"  # the press worked, the photo the VLM needs did not; ``error``
    FAILED = "failed"  # the press or its analysis failed; ``error`` says why
    # Pressed and analysed with no question to the VLM (a press taught as a reference).
    PRESSED = "pressed"

    @property
    def final(self) -> bool:
        """Nothing more will happen to an episode in this status."""
        return self not in (Status.RUNNING, Status.PENDING)


@dataclass(frozen=True)
class Neighbour:
    """One of the nearest reference classes by touch."""

    label: str
    distance: float

    def to_json(self) -> dict[str, Any]:
        return {"label": self.label, "distance": self.distance}


@dataclass
class Episode:
    id: str
    status: Status
    candidates: list[str] | None = None
    source: str | None = None
    error: str | None = None
    note: str | None = None
    # The press and its analysis.
    press: PressSummary | None = None
    x_th: float | None = None
    software_version: str | None = None
    vlm_mode: str | None = None
    timings: dict[str, float] = field(default_factory=dict)
    code: int | None = None
    z: list[float] | None = None
    topk: list[Neighbour] | None = None
    description: str | None = None
    # The nearest reference's distance as a percentile of the database's own leave-one-out
    # nearest-neighbour distances (0: closer than every reference's nearest other press,
    # 100: farther than all; None for a database of one press), and whether it is at or
    # past [runtime] unfamiliar_percentile: a touch like none the robot knows.
    familiarity: float | None = None
    unfamiliar: bool | None = None
    # A recognition of several presses: each press as it went ({"t": wall-clock start,
    # "press_s": until the arm was back, "encode_s", "result", "topk", "familiarity",
    # "unfamiliar", "agreement": its offsets' agreement}, in order) and how their top-k were
    # fused into ``topk`` ([runtime] fusion); None for one press.
    presses: list[dict[str, Any]] | None = None
    fusion: str | None = None
    # The VLM's part.
    attempts: int = 0
    next_retry_at: float = 0.0
    last_error: str | None = None
    label: str | None = None
    # The VLM's short reason for its label ([vlm] ask_reason; control characters already
    # made spaces by the reader, markup left to whoever shows it to escape).
    reason: str | None = None
    vlm: dict[str, Any] | None = None
    # The structured-output mode of the request that answered (json_schema, json_object, none).
    structured_output: str | None = None
    # Store bookkeeping (wall-clock seconds).
    accepted: float | None = None
    created: float | None = None
    updated: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.extra)
        for f in dataclasses.fields(self):
            if f.name == "extra":
                continue
            value = getattr(self, f.name)
            if f.name == "status":
                value = str(value)
            elif f.name == "topk":
                value = self.topk_json()
            elif f.name == "press" and value is not None:
                value = value.to_json()
            elif value is None and not (f.name in _ALWAYS
                                        or (f.name == "label" and self.vlm is not None)):
                continue  # not reached yet (a failed press has no analysis, ...)
            out[f.name] = value
        return out

    @classmethod
    def from_json(cls, data: Any, where: str = "episode") -> Episode:
        """The episode in ``data``; :class:`StoreError` naming ``where`` and the field if
        it is not one."""
        if not isinstance(data, dict):
            raise StoreError(f"{where}: not a JSON object")
        known = {f.name for f in dataclasses.fields(cls)} - {"extra"}
        kwargs = {k: v for k, v in data.items() if k in known}
        try:
            kwargs["status"] = Status(data.get("status"))
        except ValueError:
            raise StoreError(f"{where}: unknown status {data.get('status')!r}; known: "
                             + ", ".join(s.value for s in Status)) from None
        if not isinstance(kwargs.get("id"), str):
            raise StoreError(f"{where}: 'id' must be a string")
        topk = kwargs.get("topk")
        if topk is not None:
            try:
                kwargs["topk"] = [Neighbour(str(n["label"]), float(n["distance"]))
                                  for n in topk]
            except (TypeError, KeyError, ValueError):
                raise StoreError(f"{where}: 'topk' must be a list of "
                                 "{{label, distance}}") from None
        if kwargs.get("press") is not None:
            kwargs["press"] = PressSummary.from_json(kwargs["press"], f"{where}: 'press'")
        if kwargs.get("timings") is None:
            kwargs["timings"] = {}
        return cls(**kwargs, extra={k: v for k, v in data.items() if k not in known})

    @property
    def why(self) -> str | None:
        """What went wrong, for a reader of its outcome: ``error``, else, unless the
        episode is done, the VLM's last error (why it is pending, or was refused)."""
        return self.error or (self.last_error if self.status != Status.DONE else None)

    def topk_json(self) -> list[dict[str, Any]] | None:
        return None if self.topk is None else [n.to_json() for n in self.topk]

    def press_json(self, keys: tuple[str, ...]) -> dict[str, Any]:
        """``keys`` of the press summary's JSON form (named with :meth:`PressSummary.keys`),
        each null where the episode has no press."""
        if self.press is None:
            return dict.fromkeys(keys)
        press = self.press.to_json()
        return {k: press[k] for k in keys}

    def with_(self, **changes: Any) -> Episode:
        """A copy with ``changes``; an unknown field is a programming error (TypeError)."""
        return dataclasses.replace(self, **changes)


# In the JSON even when unset; other fields appear once they have a value (and ``label``
# once the VLM answered, a null label saying it gave none).
_ALWAYS = frozenset({"id", "status", "candidates", "source"})


# --- events ---------------------------------------------------------------------------
# What the daemon publishes while it runs, for the API's server-sent events, MQTT, the live
# recording and the operator page. Each event's ``to_json`` is its one wire form (``type``
# names it, ``t`` is the wall-clock time it was published); the objects carry what their
# readers need beyond it (the episode as stored).

@dataclass(frozen=True)
class Hello:
    """A subscription's first event: the press's state when it began."""

    kind: ClassVar[str] = "hello"
    state: PressState
    episode: str | None  # the episode whose press runs

    def to_json(self) -> dict[str, Any]:
        return {"type": self.kind, "state": str(self.state), "episode": self.episode}


@dataclass(frozen=True)
class StateChanged:
    """The press entered ``state``."""

    kind: ClassVar[str] = "state"
    state: PressState
    episode: str | None
    t: float = field(default_factory=time.time)

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "type": self.kind, "state": str(self.state),
                "episode": self.episode}


@dataclass(frozen=True)
class EpisodeStarted:
    """A recognition began (its press is about to)."""

    kind: ClassVar[str] = "episode"
    episode_id: str
    t: float = field(default_factory=time.time)

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "type": self.kind, "episode": self.episode_id,
                "status": Status.RUNNING.value}


@dataclass(frozen=True)
class PressAgain:
    """A recognition of several presses will press the object again in ``pause_s``: the
    operator moves it slightly (``message`` says so)."""

    kind: ClassVar[str] = "press_again"
    episode_id: str
    press: int  # the press to come
    presses: int | None  # of how many (None: "auto", a second press asked for)
    pause_s: float
    message: str
    t: float = field(default_factory=time.time)

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "type": self.kind, "episode": self.episode_id,
                "press": self.press, "presses": self.presses, "pause_s": self.pause_s,
                "message": self.message}


# A teaching's steps, in the order they come (each press: pressing, taught, then move
# before the next), and its end.
TeachStep = Literal["pressing", "taught", "move", "done", "failed"]


@dataclass
class TeachRun:
    """One teaching as it goes: its request, and the episodes pressed and references taught
    so far (``status``: running, done, or failed with ``error``)."""

    label: str
    description: str
    presses: int
    append: bool
    source: str
    status: Literal["running", "done", "failed"] = "running"
    episodes: list[str] = field(default_factory=list)
    references: list[str] = field(default_factory=list)
    error: str | None = None
    started: float = field(default_factory=time.time)
    # Seconds from a press's start to its reference written, one per taught press.
    press_s: list[float] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"label": self.label, "description": self.description,
                "presses": self.presses, "append": self.append, "source": self.source,
                "status": self.status, "episodes": list(self.episodes),
                "references": list(self.references), "error": self.error,
                "started": self.started, "press_s": [round(s, 3) for s in self.press_s]}


@dataclass(frozen=True)
class TeachProgress:
    """A teaching's progress: press ``press`` of ``presses`` is ``pressing``, was
    ``taught`` (as ``reference``), the operator is asked to ``move`` the object before
    the next, or the teaching is ``done`` or ``failed`` (``message`` says why)."""

    kind: ClassVar[str] = "teach"
    label: str
    step: TeachStep
    press: int
    presses: int
    episode: str | None = None
    reference: str | None = None
    message: str | None = None
    # The teaching as of this step (its readers need no other look at the teacher).
    run: TeachRun | None = None
    t: float = field(default_factory=time.time)

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "type": self.kind, "label": self.label, "step": self.step,
                "press": self.press, "presses": self.presses, "episode": self.episode,
                "reference": self.reference, "message": self.message}


@dataclass(frozen=True)
class TactileResult:
    """The press's analysis, once the episode holding it is stored."""

    kind: ClassVar[str] = "tactile"
    episode: Episode
    t: float = field(default_factory=time.time)

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "type": self.kind, "episode": self.episode.id,
                "description": self.episode.description,
                "topk": [n.to_json() for n in self.episode.topk or ()],
                "familiarity": self.episode.familiarity,
                "unfamiliar": self.episode.unfamiliar}


@dataclass(frozen=True)
class Label:
    """The VLM answered (``done``, ``invalid_answer``, ``not_configured``; ``failed`` where
    the arm did not return): ``episode`` as stored with its label."""

    kind: ClassVar[str] = "result"
    episode: Episode
    t: float = field(default_factory=time.time)

    def to_json(self) -> dict[str, Any]:
        out = {"t": self.t, "type": self.kind, "episode": self.episode.id,
               "status": self.episode.status.value, "label": self.episode.label}
        if self.episode.reason is not None:
            out["reason"] = self.episode.reason
        return out


@dataclass(frozen=True)
class VLMRefused:
    """The VLM refused the question (``vlm_error``; asking again will not help): ``episode``
    as stored with why (its ``last_error``)."""

    kind: ClassVar[str] = "result"
    episode: Episode
    t: float = field(default_factory=time.time)

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "type": self.kind, "episode": self.episode.id,
                "status": self.episode.status.value, "error": self.episode.last_error}


@dataclass(frozen=True)
class VLMUnreachable:
    """The VLM could not be reached: ``episode`` waits ``pending`` for the retry task, as
    stored with why (its ``last_error``)."""

    kind: ClassVar[str] = "episode"
    episode: Episode
    t: float = field(default_factory=time.time)

    to_json = VLMRefused.to_json  # the same form: the episode, its status and why


@dataclass(frozen=True)
class EpisodeFinished:
    """A recognition ended: ``episode`` as it left it, as stored (or held in memory while
    the store cannot write), or as the recognizer answers for it where not even its failure
    could be kept. Its status may still be ``pending``: the retry task asks again."""

    kind: ClassVar[str] = "episode"
    episode: Episode
    t: float = field(default_factory=time.time)

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "type": self.kind, "episode": self.episode.id,
                "status": "finished"}


Event = (Hello | StateChanged | EpisodeStarted | PressAgain | TeachProgress | TactileResult
         | Label | VLMRefused | VLMUnreachable | EpisodeFinished)
