"""Prompt templates: the shipped files, slot checks, unambiguous candidates."""

import json
import re

import pytest

from edge.core.errors import EdgeError, PromptError
from edge.vlm.prompt import (
    DEFAULT_PROMPT_DIR,
    MODES,
    PromptTemplate,
    check_candidates,
    format_candidates,
    load_template,
)
from tests.vlm.helpers import CANDIDATES, DESCRIPTION

TACTILE_WORDS = re.compile(r"touch|tactile|feel|felt|push|press|similar", re.I)


@pytest.mark.parametrize("mode", MODES)
def test_shipped_templates_load_and_render(mode):
    template = load_template(mode)
    assert template.source == str(DEFAULT_PROMPT_DIR / f"{mode}.txt")
    prompt = template.render(DESCRIPTION, CANDIDATES)
    assert "$" not in prompt
    for label in CANDIDATES:
        assert json.dumps(label) in prompt
    assert ('{"label": "<candidate>"}' in prompt) and "exactly one label" in prompt
    assert (DESCRIPTION in prompt) == (mode != "vision_only")
    assert template.uses_image == (mode != "tactile_only")
    print(f"\n--- {mode} ---\n{prompt}")


def test_vision_only_is_the_same_template_without_the_tactile_sentences():
    full = load_template("vision_tactile").text.splitlines()
    vision = load_template("vision_only").text.splitlines()
    assert set(vision) <= set(full)
    assert vision == [line for line in full if line in vision]  # same order
    assert not any(TACTILE_WORDS.search(line) for line in vision)
    removed = [line for line in full if line not in vision]
    assert removed and all(TACTILE_WORDS.search(line) for line in removed)


# What a prompt must not tell the VLM: the structure of the test sets (that look-alikes are
# replicas, or raw and cooked foods, and that they differ in hardness).
TEST_SET_HINTS = re.compile(r"replica|resin|\braw\b|cook|boil|real food|look(s)? alike|"
                            r"hard|soft|fake|imitation", re.I)


@pytest.mark.parametrize("mode", MODES)
def test_shipped_templates_say_nothing_about_the_test_sets(mode):
    text = load_template(mode).text
    assert not TEST_SET_HINTS.search(text), TEST_SET_HINTS.search(text)


def test_the_method_template_has_exactly_the_papers_two_slots():
    template = load_template("vision_tactile")
    assert template.slots == {"topk_refs", "test_time_classes"}
    assert template.text.count("${topk_refs}") == 1
    assert template.text.count("${test_time_classes}") == 1
    # It asks to weigh the photo and the touch together.
    assert re.search(r"photo.*touch.*together", template.text)
    assert load_template("vision_only").slots == {"test_time_classes"}


def test_tactile_only_does_not_mention_a_photo_as_present():
    text = load_template("tactile_only").text
    assert "no photo" in text and "photo shows" not in text


def test_candidates_are_rendered_exactly_and_unambiguously():
    labels = ["a, b", "c d", "resin_replica_macaron", 'quote"d']
    rendered = format_candidates(labels)
    assert json.loads(f"[{rendered}]") == labels


def test_description_is_inserted_literally():
    template = load_template("vision_tactile")
    prompt = template.render("a $strange ${desc}\n  with  spaces", ["x"])
    assert "a $strange ${desc} with spaces" in prompt


@pytest.mark.parametrize(
    ("text", "mode", "needle"),
    [
        ("Is it ${topk_refs}? ${test_time_classes} ${colour}", "vision_tactile",
         "unknown slot(s) ${colour}"),
        ("Which of ${test_time_classes}?", "vision_tactile", "lacks slot(s) ${topk_refs}"),
        ("Touch: ${topk_refs}", "tactile_only", "lacks slot(s) ${test_time_classes}"),
        ("Costs $5: ${test_time_classes}", "vision_only", "invalid placeholder"),
        ("${topk_refs} ${test_time_classes}", "vision_only", "must not use ${topk_refs}"),
        ("${test_time_classes}", "audio_only", "unknown prompt mode"),
    ],
)
def test_bad_templates_are_refused_clearly(text, mode, needle):
    with pytest.raises(PromptError) as err:
        PromptTemplate(mode=mode, text=text, source="t.txt")
    assert needle in str(err.value)
    assert isinstance(err.value, EdgeError) and isinstance(err.value, ValueError)


def test_dollar_escape_is_allowed():
    template = PromptTemplate("vision_only", "Costs $$5. ${test_time_classes}")
    assert template.render("", ["x"]) == 'Costs $5. "x"'


def test_template_files_are_checked(tmp_path):
    with pytest.raises(PromptError, match="does not exist"):
        load_template("vision_tactile", tmp_path)
    (tmp_path / "vision_tactile.txt").write_text("${topk_refs} ${candidates}")
    with pytest.raises(PromptError, match=r"vision_tactile\.txt: unknown slot"):
        load_template("vision_tactile", tmp_path)
    with pytest.raises(PromptError, match="unknown prompt mode"):
        load_template("smell")


@pytest.mark.parametrize(
    ("candidates", "needle"),
    [
        ([], "no candidate"),
        ("wood_cube", "not one string"),
        (["a", "a"], "duplicate candidate labels: a"),
        (["a", ""], "non-empty string"),
        (["a", 3], "non-empty string"),
        ([" a"], "surrounding spaces"),
        (["a\nb"], "printable"),
        (["x" * 500], "at most 200"),
    ],
)
def test_bad_candidates_are_refused(candidates, needle):
    with pytest.raises(PromptError, match=re.escape(needle)):
        check_candidates(candidates)


def test_tactile_modes_need_a_description():
    with pytest.raises(PromptError, match="needs a tactile description"):
        load_template("vision_tactile").render("  ", CANDIDATES)
    assert load_template("vision_only").render("", CANDIDATES)
