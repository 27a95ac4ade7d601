"""What a recognition request may ask for, checked the same way whichever interface it came
through (the HTTP API, MQTT), before anything moves; :class:`BadRequest` says what is
wrong."""

from __future__ import annotations

from typing import Any

from edge.core.errors import BadRequest

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
