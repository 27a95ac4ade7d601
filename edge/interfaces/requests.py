"""What a recognition or teaching request may ask for, checked the same way whichever
interface it came through (the HTTP API, MQTT), before anything moves; :class:`BadRequest`
says what is wrong."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from edge.core.errors import BadRequest
from edge.runtime.recognition import AUTO, MAX_FUSED_PRESSES, Presses
from edge.runtime.teaching import MAX_PAUSE_S, MAX_PRESSES, PAUSE_S

MAX_LABEL_CHARS = 80


def validate_candidates(value: Any, max_candidates: int) -> list[str]:
    if not isinstance(value, list) or not value:
        raise BadRequest("candidates must be a non-empty JSON list of labels")
    if len(value) > max_candidates:
        raise BadRequest(f"too many candidates: {len(value)} (at most {max_candidates})")
    out = []
    for item in value:
        if not isinstance(item, str) or not item.strip():
            raise BadRequest(f"every candidate must be a non-empty string, got {item!r}")
        label = item.strip()
        if len(label) > MAX_LABEL_CHARS or not label.isprintable():
            raise BadRequest(f"candidate {label[:MAX_LABEL_CHARS]!r}... must be printable and "
                             f"at most {MAX_LABEL_CHARS} characters")
        if label in out:
            raise BadRequest(f"duplicate candidate {label!r}")
        out.append(label)
    return out


def validate_presses(body: dict[str, Any]) -> tuple[Presses, float]:
    """A recognition's ``presses`` (1, the paper's, by default; up to MAX_FUSED_PRESSES,
    or "auto": a second only where the first is unfamiliar or its offsets disagree) and the
    ``pause_s`` between them."""
    presses = body.get("presses", 1)
    if presses != AUTO and (type(presses) is not int
                            or not 1 <= presses <= MAX_FUSED_PRESSES):
        raise BadRequest(f"presses must be an integer 1..{MAX_FUSED_PRESSES} or {AUTO!r}, "
                         f"got {presses!r:.40}")
    return presses, _pause_s(body)


def _pause_s(body: dict[str, Any]) -> float:
    pause_s = body.get("pause_s", PAUSE_S)
    if isinstance(pause_s, bool) or not isinstance(pause_s, int | float) \
            or not 0 <= pause_s <= MAX_PAUSE_S:
        raise BadRequest(f"pause_s must be a number of seconds 0..{MAX_PAUSE_S:g} (the "
                         f"operator's time to move the object between presses), got "
                         f"{pause_s!r:.40}")
    return float(pause_s)


# What a teaching request may say (POST /v1/teach, MQTT P/cmd/teach), beside what each
# interface adds (wait, request_id).
TEACH_FIELDS = frozenset({"label", "description", "presses", "append", "pause_s"})
# Of an episode taught as what it really was (POST /v1/episodes/{id}/teach).
TAUGHT_FIELDS = frozenset({"label", "description"})
MAX_DESCRIPTION_CHARS = 200


@dataclass(frozen=True)
class TeachRequest:
    label: str
    description: str | None
    presses: int
    append: bool
    pause_s: float


def validate_teach(body: dict[str, Any], extra: frozenset[str] = frozenset()) -> TeachRequest:
    """A teaching request's fields checked (the reference rules, what the label and
    description may be and whether the class takes them, are the teacher's, before the arm
    moves); ``extra``: the fields the interface itself reads."""
    _known(body, TEACH_FIELDS | extra)
    presses = body.get("presses", 1)
    if type(presses) is not int or not 1 <= presses <= MAX_PRESSES:
        raise BadRequest(f"presses must be an integer 1..{MAX_PRESSES}, got {presses!r:.40}")
    append = body.get("append", False)
    if not isinstance(append, bool):
        raise BadRequest(f"append must be true or false, got {append!r:.40}")
    pause_s = _pause_s(body)
    label, description = validate_taught(body, TEACH_FIELDS | extra)
    return TeachRequest(label, description, presses, append, pause_s)


def validate_taught(body: dict[str, Any], known: frozenset[str] = TAUGHT_FIELDS
                    ) -> tuple[str, str | None]:
    """The label and description of a teaching (the description may be absent for a label
    the database has)."""
    _known(body, known)
    label = body.get("label")
    if not isinstance(label, str) or not label.strip():
        raise BadRequest(f"label must be a non-empty string, got {label!r:.40}")
    if len(label) > MAX_LABEL_CHARS or not label.isprintable():
        raise BadRequest(f"label {label[:MAX_LABEL_CHARS]!r} must be printable and at most "
                         f"{MAX_LABEL_CHARS} characters")
    description = body.get("description")
    if description is not None and (not isinstance(description, str)
                                    or len(description) > MAX_DESCRIPTION_CHARS
                                    or not description.isprintable()):
        raise BadRequest(f"description must be a printable string of at most "
                         f"{MAX_DESCRIPTION_CHARS} characters naming the object, got "
                         f"{description!r:.60}")
    return label.strip(), description or None


def _known(body: dict[str, Any], known: frozenset[str]) -> None:
    unknown = sorted(set(body) - known)
    if unknown:
        raise BadRequest(f"unknown field {unknown[0]!r:.40}; known: " + ", ".join(sorted(known)))
