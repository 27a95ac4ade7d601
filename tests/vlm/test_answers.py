"""Answer parsing and Retry-After: pure functions, hostile inputs included."""

import email.utils
import json
import string
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.vlm.answer import (
    JSON_REPLY,
    LABEL_ALONE,
    MAX_ANSWER_CHARS,
    Reading,
    ask_for,
    correction_message,
    match_label,
    normalise_label,
    read_answer,
)
from edge.vlm.chat import response_format
from edge.vlm.prompt import load_template
from edge.vlm.transport import parse_retry_after
from tests.vlm.helpers import CANDIDATES

JSON_MODES = ("json_schema", "json_object")
MODES = (*JSON_MODES, "none")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('{"label": "raw_kiri_mochi"}', "raw_kiri_mochi"),
        ('{"label":"Raw Kiri Mochi"}', "raw_kiri_mochi"),
        # markdown fences around JSON are JSON, with or without a language tag:
        ('```json\n{"label": "raw_kabocha_squash"}\n```', "raw_kabocha_squash"),
        ('  ```\n{"label": "boiled_kiri_mochi"}```\n', "boiled_kiri_mochi"),
        ('<think>soft... maybe raw?</think>\n{"label": "boiled_kiri_mochi"}',
         "boiled_kiri_mochi"),
        # JSON, but never a guess:
        ('{"label": "pizza"}', None),
        ('{"label": "raw_kiri"}', None),
        ('{"label": 3}', None),
        ('{"answer": "raw_kiri_mochi"}', None),
        ('{"label": "raw_kiri_mochi"' + " " * 200_000 + "}", None),
    ],
)
@pytest.mark.parametrize("mode", MODES)
def test_json_answers_in_every_mode(text, expected, mode):
    assert read_answer(text, CANDIDATES, mode) == Reading(expected)


@pytest.mark.parametrize(
    "text",
    [
        "raw_kiri_mochi",
        '"raw_kiri_mochi"',
        "The object is most likely the boiled_kiri_mochi because it is soft.",
        'Sure! {"label": "raw_kiri_mochi"} is my answer.',
        '```json\n{"label": "raw_kiri_mochi"}\n``` is my answer',
        "[\"raw_kiri_mochi\"]",
        "",
        "{",
        "[" * 100_000,
    ],
)
@pytest.mark.parametrize("mode", JSON_MODES)
def test_a_json_mode_answered_without_a_json_object_was_ignored(text, mode):
    """The server took the mode and answered something else: no label, step down."""
    assert read_answer(text, CANDIDATES, mode) == Reading(None, honoured=False)


FOOD = ["macaron", "resin_replica_macaron", "melon_pan"]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("macaron", "macaron"),
        ("Resin Replica Macaron", "resin_replica_macaron"),
        ("resin-replica-macaron.", "resin_replica_macaron"),
        ("  MELON_PAN \n", "melon_pan"),
        ('"macaron"', "macaron"),
        ("**Macaron**", "macaron"),
        ("Label: resin replica macaron", "resin_replica_macaron"),
        ('label: "melon_pan".', "melon_pan"),
        ("```\nmelon pan\n```", "melon_pan"),
        ("<think>a macaron? a replica?</think>\nresin_replica_macaron", "resin_replica_macaron"),
        # the negation, never the label it names:
        ("This is not a real macaron; it is a resin replica.", None),
        ("It is not a macaron.", None),
        ("not macaron", None),
        # a list of two candidates:
        ("macaron, resin_replica_macaron", None),
        ("macaron or resin_replica_macaron", None),
        ("macaron\nresin_replica_macaron", None),
        # a candidate inside a longer word, or inside a sentence:
        ("macarons", None),
        ("macaronade", None),
        ("The object is most likely the macaron because it is soft.", None),
        ("Answer: macaron", None),
        ("<think>surely macaron</think> I cannot tell.", None),
        ("", None),
        ("...", None),
    ],
)
def test_free_text_is_one_candidate_alone(text, expected):
    assert read_answer(text, FOOD, "none") == Reading(expected)


def test_ask_for_asks_for_the_label_alone_in_free_text():
    template = load_template("vision_tactile")
    rendered = template.render("wood cube", FOOD)
    assert ask_for(rendered, "json_schema") == ask_for(rendered, "json_object") == rendered
    free = ask_for(rendered, "none")
    assert free == rendered.replace(rendered.splitlines()[-1], LABEL_ALONE)
    assert '{"label"' not in free and "json" not in free.lower()
    print(f"\nfree text asks: {free.splitlines()[-1]}")
    # A template of one's own: JSON mode asks for JSON, free text for the label alone.
    assert ask_for("Which?", "json_object") == f"Which?\n{JSON_REPLY}"
    assert ask_for("Which?", "none") == f"Which?\n{LABEL_ALONE}"
    assert correction_message(FOOD, "none").endswith(LABEL_ALONE)
    assert correction_message(FOOD, "json_schema").endswith(JSON_REPLY)


def test_adversarial_answers_are_parsed_in_linear_time():
    n = MAX_ANSWER_CHARS
    hostile = ["<think>" * (n // 7), "```" * (n // 3), "{" * n, "[" * n, '{"label": ' * (n // 10),
               "```\n" + "{" * (n - 10), "a_" * (n // 2), " " * n, "</think>" * (n // 8)]
    started = time.perf_counter()
    for text in hostile:
        for mode in MODES:
            assert read_answer(text, CANDIDATES, mode).label is None
    took = time.perf_counter() - started
    print(f"\n{len(hostile)} hostile answers of ~{n} chars parsed in {took * 1e3:.1f} ms")
    assert took < 5  # quadratic behaviour would take minutes


def test_ambiguous_variants_are_not_mapped():
    candidates = ["Wood Cube", "wood_cube"]
    assert match_label("Wood Cube", candidates) == "Wood Cube"
    assert match_label("wood_cube", candidates) == "wood_cube"
    assert match_label("WOOD-CUBE", candidates) is None


def test_normalise_label():
    assert normalise_label(" Raw  Kiri-Mochi. ") == "raw_kiri_mochi"
    assert normalise_label("'resin_replica_macaron'") == "resin_replica_macaron"


def test_response_format_is_the_strict_nested_schema():
    assert response_format(["a", "b"]) == {
        "type": "json_schema",
        "json_schema": {"name": "label", "strict": True, "schema": {
            "type": "object",
            "properties": {"label": {"type": "string", "enum": ["a", "b"]}},
            "required": ["label"], "additionalProperties": False}},
    }


labels = st.lists(
    st.text(alphabet=string.ascii_letters + string.digits + "_ -", min_size=1, max_size=20)
    .map(str.strip).filter(bool),
    min_size=1, max_size=8, unique=True,
)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(text=st.text(max_size=300), candidates=labels, mode=st.sampled_from(MODES))
def test_any_answer_never_crashes_and_never_invents(text, candidates, mode):
    result = read_answer(text, candidates, mode).label
    assert result is None or result in candidates


@settings(max_examples=200, deadline=None)
@given(
    junk=st.one_of(
        st.text(alphabet="{}[]\":,`\\ \nlabel<>/think", max_size=200),
        st.recursive(st.none() | st.booleans() | st.floats() | st.text(max_size=10),
                     lambda c: st.lists(c, max_size=3) | st.dictionaries(
                         st.sampled_from(["label", "x"]), c, max_size=2),
                     max_leaves=10).map(json.dumps),
    ),
    candidates=labels,
    mode=st.sampled_from(MODES),
)
def test_hostile_json_never_crashes(junk, candidates, mode):
    result = read_answer(junk, candidates, mode).label
    assert result is None or result in candidates


@settings(max_examples=200, deadline=None)
@given(candidates=labels, index=st.integers(0, 7), style=st.sampled_from(
    ["json", "bare", "upper", "spaces", "fence", "quoted"]), mode=st.sampled_from(MODES))
def test_variants_of_a_candidate_map_back(candidates, index, style, mode):
    label = candidates[index % len(candidates)]
    variant = {
        "json": json.dumps({"label": label}),
        "bare": label,
        "upper": label.upper(),
        "spaces": label.replace("_", " "),
        "fence": f"```json\n{json.dumps({'label': label})}\n```",
        "quoted": json.dumps(label),
    }[style]
    clash = [c for c in candidates if normalise_label(c) == normalise_label(label)]
    reading = read_answer(variant, candidates, mode)
    if mode != "none" and style not in ("json", "fence"):
        assert reading == Reading(None, honoured=False)  # free text answers no JSON mode
    elif len(clash) == 1 and normalise_label(label):
        assert reading == Reading(label)
    else:
        assert reading.label is None or reading.label in candidates


def test_retry_after_forms():
    now = 1_700_000_000.0
    assert parse_retry_after("5", now) == 5.0
    assert parse_retry_after(" 0 ", now) == 0.0
    assert parse_retry_after("1.5", now) == 1.5
    assert parse_retry_after("-3", now) == 0.0
    date = email.utils.formatdate(now + 7, usegmt=True)
    assert parse_retry_after(date, now) == pytest.approx(7.0)
    past = email.utils.formatdate(now - 60, usegmt=True)
    assert parse_retry_after(past, now) == 0.0
    for bad in (None, "", "soon", "nan", "inf", "Mon, 99 Foo 2024 99:99:99 GMT"):
        assert parse_retry_after(bad, now) is None
