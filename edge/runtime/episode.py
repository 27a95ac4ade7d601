"""An episode: one recognition as the store keeps it and the API, the CLI and the retry task
read it.

The JSON form (``episode.json`` in the store, the API's answers) keeps the keys it has
always had; keys this version does not know (written by a newer one) are carried through
unchanged in ``extra`` rather than refused or lost.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from edge.core.errors import StoreError
from edge.runtime.state import PressSummary


class Status(StrEnum):
    RUNNING = "running"  # the press or its analysis is under way (never stored)
    PENDING = "pending"  # analysed; the VLM's answer is still due (retried with backoff)
    DONE = "done"  # the VLM answered with one of the candidates
    INVALID_ANSWER = "invalid_answer"  # it answered, but with no candidate, twice
    NOT_CONFIGURED = "not_configured"  # no VLM endpoint configured: the prompt is kept
    VLM_ERROR = "vlm_error"  # the VLM refused the question (asking again will not help)
    CAMERA_ERROR = "camera_error"  # the press worked, the photo the VLM needs did not; ``error``
    FAILED = "failed"  # the press or its analysis failed; ``error`` says why

    @property
    def final(self) -> bool:
        """Nothing more will happen to an episode in this status."""
        return self not in (Status.RUNNING, Status.PENDING)


@dataclass(frozen=True)
class Neighbour:
    """One of the nearest reference classes by touch."""

    label: str
    distance: float


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
    # The VLM's part.
    attempts: int = 0
    next_retry_at: float = 0.0
    last_error: str | None = None
    label: str | None = None
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
            elif f.name == "topk" and value is not None:
                value = [{"label": n.label, "distance": n.distance} for n in value]
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

    def with_(self, **changes: Any) -> Episode:
        """A copy with ``changes``; an unknown field is a programming error (TypeError)."""
        return dataclasses.replace(self, **changes)


# In the JSON even when unset; other fields appear once they have a value (and ``label``
# once the VLM answered, a null label saying it gave none).
_ALWAYS = frozenset({"id", "status", "candidates", "source"})
