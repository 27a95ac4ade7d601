"""What a VLM is asked to answer, and how an answer is read (docs/method.md, 'The VLM answer').

The daemon's recognitions, doctor's probe and the evaluation all read answers with
:func:`read_answer`, so they cannot disagree about one.

Asked for (:func:`ask_for`): in the JSON modes (``json_schema``, ``json_object``) the shipped
templates' last line asks for ``{"label": "<candidate>"}``; in free-text mode (``none``) that
line asks for the label alone instead (:data:`LABEL_ALONE`). With ``vlm.ask_reason`` that line
asks for a short reason first, then the label (:data:`REASON_JSON_REPLY`,
:data:`REASON_THEN_LABEL`): a model that writes in order gives its reason before it commits
to a label. Without it the prompt is the template's, byte for byte.

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

The reason, when asked: the JSON object's ``reason``, or in free text what comes before the
last ``Label:`` (a leading ``Reason:`` dropped), the label part read by the free-text rule
above (exactly one candidate). A reason is text shown to a person: control characters become
spaces, runs of spaces one, and one longer than :data:`MAX_REASON_CHARS` is cut, ending in
"…"; one that is not text, or empty, is no reason (``Reading.reason_note`` says which). The
label never depends on the reason.

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
# With vlm.ask_reason, what each answer line asks instead: a short reason, then the label.
REASON_JSON_REPLY = ('First give a short reason (one sentence), then exactly one label from '
                     'the candidates, spelled exactly as given. Reply only with JSON: '
                     '{"reason": "<short reason>", "label": "<candidate>"}')
REASON_THEN_LABEL = ('First give a short reason (one sentence) on a line starting "Reason:", '
                     'then exactly one label from the candidates, spelled exactly as given, '
                     'on a last line starting "Label:", and nothing else.')
# A reason longer than this is cut (the whole answer stays in VLMAnswer.raw).
MAX_REASON_CHARS = 500
# Reading.reason_note when a reason was asked for and none came.
NO_REASON = "no reason given"
_ASKS_JSON = re.compile(r'^.*\{"label": "<candidate>"\}.*$', re.M)
# One fence around the whole answer: ```json\n...\n``` (the language tag is optional).
_FENCE = re.compile(r"```[A-Za-z0-9_+-]*[ \t]*\n?(.*?)\n?[ \t]*```", re.S)
_LABEL_PREFIX = re.compile(r"label\s*:", re.I)
# Free text with a reason: "Reason: ... Label: X" (markdown emphasis around either word).
_LABEL_MARK = re.compile(r"\blabel[\s*_]*:", re.I)
_REASON_MARK = re.compile(r"reason[\s*_]*:", re.I)
_MARKUP = " \t\r\n*_`"
_SEPARATORS = re.compile(r"[\s_\-]+")
_WORD = re.compile(r"[^\W_]")


@dataclass(frozen=True)
class Reading:
    """An answer as read: the candidate it names (None: none), whether it honoured the
    structured-output mode it was asked with (False: a JSON mode answered with no JSON
    object; always True in free-text mode), and its reason when one was asked."""

    label: str | None
    honoured: bool = True
    # The reason given, as shown (None: none asked, none given, or none usable), and why a
    # reason given was not used as it came ("" when it was).
    reason: str | None = None
    reason_note: str = ""


def answer_line(mode: str, reason: bool = False) -> str:
    """What the prompt's answer line asks in ``mode``: the label alone (free text), JSON with
    the label, or, with ``reason``, a short reason first."""
    if reason:
        return REASON_THEN_LABEL if mode == "none" else REASON_JSON_REPLY
    return LABEL_ALONE if mode == "none" else JSON_REPLY


def ask_for(prompt: str, mode: str, reason: bool = False) -> str:
    """The rendered template as sent in structured-output ``mode``: free text asks for the
    label alone; JSON mode asks for JSON where the template does not; ``reason`` asks for a
    short reason before the label in every mode. The template's line that asks for JSON is
    replaced, else the line is added."""
    if mode == "none" or reason:
        line = answer_line(mode, reason)
        asked, n = _ASKS_JSON.subn(lambda _: line, prompt)
        return asked if n else f"{prompt}\n{line}"
    if mode == "json_object" and '"label"' not in prompt:
        return f"{prompt}\n{JSON_REPLY}"
    return prompt


def correction_message(candidates: Sequence[str], mode: str, reason: bool = False) -> str:
    """The one corrective retry's question, in the answer form of ``mode``."""
    return ("That answer is not one of the candidates. Answer again with exactly one label "
            f"from the candidates, spelled exactly as given: {format_candidates(candidates)}. "
            f"{answer_line(mode, reason)}")


def read_answer(text: str, candidates: Sequence[str], mode: str,
                reason: bool = False) -> Reading:
    """The candidate ``text`` names when asked in structured-output ``mode``, and with
    ``reason`` the reason it gives, as the module docstring says. Never raises on any answer
    text; linear in its length."""
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
        found = match_label(label, candidates) if isinstance(label, str) else None
        if not reason:
            return Reading(found)
        if "reason" not in value:
            return Reading(found, True, None, NO_REASON)
        return Reading(found, True, *_read_reason(value["reason"]))
    if mode != "none":
        return Reading(None, honoured=False)
    bare = _trim(text)
    if reason and (marks := list(_LABEL_MARK.finditer(bare))):
        said = bare[:marks[-1].start()].strip(_MARKUP)
        if prefix := _REASON_MARK.match(said):
            said = said[prefix.end():]
        said = said.strip(_MARKUP)
        found = match_label(_trim(bare[marks[-1].end():]), candidates)
        if not said:
            return Reading(found, True, None, NO_REASON)
        return Reading(found, True, *_read_reason(said))
    if reason:
        return Reading(match_label(bare, candidates), True, None, NO_REASON)
    if prefix := _LABEL_PREFIX.match(bare):
        bare = _trim(bare[prefix.end():])
    return Reading(match_label(bare, candidates))


def _read_reason(value: object) -> tuple[str | None, str]:
    """(the reason as shown, why the given one was not used as it came)."""
    if not isinstance(value, str):
        return None, f"the reason is {_kind(value)}, not text: no reason kept"
    shown = " ".join("".join(c if c.isprintable() else " " for c in value).split())
    if not shown:
        return None, "the reason is empty" if value == "" else "the reason is only blanks"
    if len(shown) > MAX_REASON_CHARS:
        cut = shown[:MAX_REASON_CHARS - 1].rstrip() + "…"
        return cut, f"the reason is cut to {MAX_REASON_CHARS} of {len(shown)} characters"
    return shown, ""


def _kind(value: object) -> str:
    """A JSON value's kind in words."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int | float):
        return "a number"
    return "an array" if isinstance(value, list) else "an object"


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
