"""What a VLM is asked to answer, and how an answer is read (docs/method.md, 'The VLM answer').

The daemon's recognitions, doctor's probe and the evaluation all read answers with
:func:`read_answer`, so they cannot disagree about one.

Asked for (:func:`ask_for`): in the JSON modes (``json_schema``, ``json_object``) the shipped
templates' last line asks for ``{"label": "<candidate>"}``; in free-text mode (``none``) that
line asks for the label alone instead (:data:`LABEL_ALONE`).

Read (:func:`read_answer`): what follows a reasoning model's ``</think>``, and the inside of
one markdown code fence around the whole answer (```` ```json ... ``` ```` is JSON), then:

- A JSON object is the requested JSON: its ``label`` is the answer when it is a candidate or
  a variant of one (:func:`match_label`); otherwise there is no answer.
- In a JSON mode anything else (prose, a bare label, a JSON string, an object with words
  around it) is not the requested JSON: the server ignored the mode
  (``Reading.honoured`` is False) and the client asks again one mode down.
- In free-text mode the whole answer, stripped of surrounding quotes and punctuation and of
  a leading ``label:``, must be one candidate or a variant of one. "This is not a real
  macaron" is never ``macaron``, nor is "macarons" or "macaron or resin_replica_macaron".

A variant of a candidate is the same label up to case and spacing: runs of spaces, ``_`` and
``-`` count as one ``_`` and surrounding punctuation is ignored ("Raw Kiri-Mochi." is
``raw_kiri_mochi``), as long as only one candidate reads that way. A label is never guessed.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass

from edge.vlm.prompt import format_candidates

# Answers longer than this are not a label (and not worth parsing).
MAX_ANSWER_CHARS = 100_000
# How the shipped templates ask for the answer; JSON mode needs the prompt to ask for JSON
# (OpenAI refuses it otherwise), so a template that does not gets this line.
JSON_REPLY = 'Reply only with JSON: {"label": "<candidate>"}'
# What free-text mode asks instead of each line that asks for JSON.
LABEL_ALONE = ("Answer with exactly one label from the candidates, spelled exactly as given, "
               "and nothing else.")
_ASKS_JSON = re.compile(r'^.*\{"label": "<candidate>"\}.*$', re.M)
# One fence around the whole answer: ```json\n...\n``` (the language tag is optional).
_FENCE = re.compile(r"```[A-Za-z0-9_+-]*[ \t]*\n?(.*?)\n?[ \t]*```", re.S)
_LABEL_PREFIX = re.compile(r"label\s*:", re.I)
_SEPARATORS = re.compile(r"[\s_\-]+")
_WORD = re.compile(r"[^\W_]")


@dataclass(frozen=True)
class Reading:
    """An answer as read: the candidate it names (None: none), and whether it honoured the
    structured-output mode it was asked with (False: a JSON mode answered with no JSON
    object; always True in free-text mode)."""

    label: str | None
    honoured: bool = True


def ask_for(prompt: str, mode: str) -> str:
    """The rendered template as sent in structured-output ``mode``: free text asks for the
    label alone; JSON mode asks for JSON where the template does not."""
    if mode == "none":
        asked, n = _ASKS_JSON.subn(LABEL_ALONE, prompt)
        return asked if n else f"{prompt}\n{LABEL_ALONE}"
    if mode == "json_object" and '"label"' not in prompt:
        return f"{prompt}\n{JSON_REPLY}"
    return prompt


def correction_message(candidates: Sequence[str], mode: str) -> str:
    """The one corrective retry's question, in the answer form of ``mode``."""
    ask = LABEL_ALONE if mode == "none" else JSON_REPLY
    return ("That answer is not one of the candidates. Answer again with exactly one label "
            f"from the candidates, spelled exactly as given: {format_candidates(candidates)}. "
            f"{ask}")


def read_answer(text: str, candidates: Sequence[str], mode: str) -> Reading:
    """The candidate ``text`` names when asked in structured-output ``mode``, as the module
    docstring says. Never raises on any answer text; linear in its length."""
    if not isinstance(text, str) or len(text) > MAX_ANSWER_CHARS:
        return Reading(None)
    end_think = text.lower().rfind("</think>")  # reasoning models: the answer follows
    if end_think >= 0:
        text = text[end_think + len("</think>"):]
    text = text.strip()
    fence = _FENCE.fullmatch(text)
    if fence is not None:
        text = fence.group(1).strip()
    try:
        value = json.loads(text)
    except (ValueError, RecursionError):
        value = None
    if isinstance(value, dict):
        label = value.get("label")
        return Reading(match_label(label, candidates) if isinstance(label, str) else None)
    if mode != "none":
        return Reading(None, honoured=False)
    bare = _trim(text)
    if prefix := _LABEL_PREFIX.match(bare):
        bare = _trim(bare[prefix.end():])
    return Reading(match_label(bare, candidates))


def normalise_label(text: str) -> str:
    """The comparison key of a label: "Raw Kiri-Mochi." -> "raw_kiri_mochi"."""
    return _SEPARATORS.sub("_", _trim(text).casefold())


def match_label(value: str, candidates: Sequence[str]) -> str | None:
    """``value`` as a candidate: exactly, else by :func:`normalise_label` if unambiguous."""
    if value in candidates:
        return value
    key = normalise_label(value)
    if not key:
        return None
    found = [c for c in candidates if normalise_label(c) == key]
    return found[0] if len(found) == 1 else None


def _trim(text: str) -> str:
    """``text`` from its first letter or digit to its last (quotes, punctuation, markdown
    emphasis and spaces around it dropped); linear, unlike a regex anchored at both ends."""
    first = _WORD.search(text)
    if first is None:
        return ""
    last = _WORD.search(text[::-1])
    assert last is not None
    return text[first.start(): len(text) - last.start()]
