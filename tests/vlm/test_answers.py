"""Answer parsing and Retry-After: pure functions, hostile inputs included."""

import email.utils
import json
import string
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.vlm.client import (
    MAX_ANSWER_CHARS,
    match_label,
    normalise_label,
    parse_label,
    parse_retry_after,
    response_format,
)
from tests.vlm.helpers import CANDIDATES


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('{"label": "raw_kiri_mochi"}', "raw_kiri_mochi"),
        ('{"label":"Raw Kiri Mochi"}', "raw_kiri_mochi"),
        ("Raw Kiri Mochi", "raw_kiri_mochi"),
        ("raw-kiri-mochi.", "raw_kiri_mochi"),
        ("  BOILED_KIRI_MOCHI \n", "boiled_kiri_mochi"),
        ('"boiled_kabocha_squash"', "boiled_kabocha_squash"),
        ('```json\n{"label": "raw_kabocha_squash"}\n```', "raw_kabocha_squash"),
        ("```\nboiled kiri mochi\n```", "boiled_kiri_mochi"),
        ('<think>soft... maybe raw?</think>\n{"label": "boiled_kiri_mochi"}',
         "boiled_kiri_mochi"),
        ('Sure! {"label": "raw_kiri_mochi"} is my answer.', "raw_kiri_mochi"),
        # free text naming exactly one candidate, spelled as given:
        ("The object is most likely the boiled_kiri_mochi because it is soft.",
         "boiled_kiri_mochi"),
        ("It looks like raw_kabocha_squash.\nThe touch agrees.", "raw_kabocha_squash"),
        # never a guess:
        ('{"label": "pizza"}', None),
        ('{"label": "raw_kiri"}', None),
        ('{"label": 3}', None),
        ('{"answer": "raw_kiri_mochi"}', None),
        ("I think it is raw kiri mochi", None),
        ("raw_kiri_mochi\nor boiled_kiri_mochi", None),
        ("Either raw_kiri_mochi or boiled_kiri_mochi, hard to say.", None),
        ("It is a raw_kiri_mochi_cake.", None),
        ("<think>maybe raw_kiri_mochi</think> I cannot tell.", None),
        ("", None),
        ("{", None),
        ("[" * 100_000, None),
        ('{"label": "raw_kiri_mochi"' + " " * 200_000 + "}", None),
    ],
)
def test_parse_label(text, expected):
    assert parse_label(text, CANDIDATES) == expected


def test_adversarial_answers_are_parsed_in_linear_time():
    n = MAX_ANSWER_CHARS
    hostile = ["<think>" * (n // 7), "```" * (n // 3), "{" * n, "[" * n, '{"label": ' * (n // 10),
               "```\n" + "{" * (n - 10), "a_" * (n // 2), " " * n, "</think>" * (n // 8)]
    started = time.perf_counter()
    for text in hostile:
        assert parse_label(text, CANDIDATES) is None
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
@given(text=st.text(max_size=300), candidates=labels)
def test_any_answer_never_crashes_and_never_invents(text, candidates):
    result = parse_label(text, candidates)
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
)
def test_hostile_json_never_crashes(junk, candidates):
    result = parse_label(junk, candidates)
    assert result is None or result in candidates


@settings(max_examples=200, deadline=None)
@given(candidates=labels, index=st.integers(0, 7), style=st.sampled_from(
    ["json", "bare", "upper", "spaces", "fence", "quoted"]))
def test_variants_of_a_candidate_map_back(candidates, index, style):
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
    result = parse_label(variant, candidates)
    if len(clash) == 1 and normalise_label(label):
        assert result == label
    else:
        assert result is None or result in candidates


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
