"""The VLM's reason, when asked (vlm.ask_reason): the schema and the prompt ask for it before
the label, the one answer reader returns it (JSON, free text, the step-down path), hostile
reasons are shown safely or not at all, and with the option off every request is the
label-only one, byte for byte."""

import hashlib
import json
import logging
import string

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.core.config import from_dict
from edge.core.errors import ConfigError
from edge.sim.fake_vlm import FakeVLM, Reply, plain_reason
from edge.vlm.answer import (
    JSON_REPLY,
    LABEL_ALONE,
    MAX_REASON_CHARS,
    REASON_JSON_REPLY,
    REASON_THEN_LABEL,
    Reading,
    ask_for,
    correction_message,
    read_answer,
)
from edge.vlm.chat import response_format
from edge.vlm.client import OpenAIVLM, VLMConfig
from edge.vlm.prompt import MODES as PROMPT_MODES
from edge.vlm.prompt import load_template
from tests.vlm.helpers import CANDIDATES, DESCRIPTION, MODEL, vlm_config

JSON_MODES = ("json_schema", "json_object")
MODES = (*JSON_MODES, "none")
SHIPPED_LINE = '{"label": "<candidate>"}'


def reading(text, mode="json_schema"):
    return read_answer(text, CANDIDATES, mode, reason=True)


# --- read_answer -------------------------------------------------------------------------

@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize(("text", "label", "reason"), [
    ('{"reason": "Soft and pale.", "label": "raw_kiri_mochi"}', "raw_kiri_mochi",
     "Soft and pale."),
    # the label first is still JSON; the order matters for writing, not for reading
    ('{"label": "Boiled Kiri Mochi", "reason": "It sags."}', "boiled_kiri_mochi", "It sags."),
    ('```json\n{"reason": "Orange rind.", "label": "raw_kabocha_squash"}\n```',
     "raw_kabocha_squash", "Orange rind."),
    ('<think>hmm</think>{"reason": "Looks cooked.", "label": "boiled_kabocha_squash"}',
     "boiled_kabocha_squash", "Looks cooked."),
    # a reason never rescues a label that is not a candidate
    ('{"reason": "It is mochi.", "label": "mochi"}', None, "It is mochi."),
])
def test_json_answers_carry_their_reason_in_every_mode(mode, text, label, reason):
    assert reading(text, mode) == Reading(label, True, reason)


@pytest.mark.parametrize("mode", MODES)
def test_a_json_answer_without_a_reason_keeps_its_label_and_says_so(mode):
    assert reading('{"label": "raw_kiri_mochi"}', mode) == Reading(
        "raw_kiri_mochi", True, None, "no reason given")


@pytest.mark.parametrize("mode", MODES)
def test_not_asked_a_reason_is_not_read(mode):
    """Off, the answer reads as the paper's label-only one, whatever the model adds."""
    text = '{"reason": "It is soft.", "label": "raw_kiri_mochi"}'
    assert read_answer(text, CANDIDATES, mode) == Reading("raw_kiri_mochi")


@pytest.mark.parametrize(("text", "label", "reason"), [
    ("Reason: It is pale and soft.\nLabel: raw_kiri_mochi", "raw_kiri_mochi",
     "It is pale and soft."),
    ("**Reason:** It sags, so it was boiled.\n**Label:** Boiled Kiri-Mochi.",
     "boiled_kiri_mochi", "It sags, so it was boiled."),
    ("reason: the label on the box: squash\nlabel: raw_kabocha_squash", "raw_kabocha_squash",
     "the label on the box: squash"),
    ("Orange and hard. Label: raw_kabocha_squash", "raw_kabocha_squash", "Orange and hard."),
    # the label part keeps the strict rule: exactly one candidate, nothing else
    ("Reason: soft.\nLabel: raw_kiri_mochi or boiled_kiri_mochi", None, "soft."),
    ("Reason: soft.\nLabel: probably raw_kiri_mochi", None, "soft."),
    ("Reason: soft.\nLabel: raw_kiri_mochis", None, "soft."),
    ("Label: raw_kiri_mochi\nReason: it is soft.", None, None),
])
def test_free_text_reason_then_label(text, label, reason):
    got = reading(text, "none")
    assert (got.label, got.reason, got.honoured) == (label, reason, True)


@pytest.mark.parametrize(("text", "label"), [
    ("raw_kiri_mochi", "raw_kiri_mochi"),
    ("Label: raw_kiri_mochi", "raw_kiri_mochi"),
    # a reason with no label part names no candidate, even one it mentions
    ("Reason: it is raw_kiri_mochi", None),
    ("The object is most likely the raw_kiri_mochi because it is soft.", None),
])
def test_free_text_without_a_reason(text, label):
    assert reading(text, "none") == Reading(label, True, None, "no reason given")


@pytest.mark.parametrize("mode", JSON_MODES)
def test_a_json_mode_answered_in_free_text_steps_down_even_with_a_reason(mode):
    assert reading("Reason: soft.\nLabel: raw_kiri_mochi", mode) == Reading(
        None, honoured=False)


@pytest.mark.parametrize(("value", "note"), [
    (42, "the reason is a number, not text"),
    (True, "the reason is a boolean, not text"),
    (None, "the reason is null, not text"),
    (["soft", "pale"], "the reason is an array, not text"),
    ({"why": "soft"}, "the reason is an object, not text"),
    ("", "the reason is empty"),
    (" \n\t\u200b\x00 ", "the reason is only blanks"),
])
@pytest.mark.parametrize("mode", MODES)
def test_a_reason_that_is_not_text_is_no_reason_and_the_label_stands(value, note, mode):
    got = reading(json.dumps({"reason": value, "label": "raw_kiri_mochi"}), mode)
    assert (got.label, got.reason) == ("raw_kiri_mochi", None)
    assert got.reason_note.startswith(note), got.reason_note


def test_a_reason_is_made_safe_to_show():
    hostile = "Soft\x1b[31m red\x1b[0m\n\n\tline\u202etxt.exe\x00 <b>x</b>  end"
    got = reading(json.dumps({"reason": hostile, "label": "raw_kiri_mochi"}))
    # control characters are spaces, runs of spaces one; markup is the page's to escape
    assert got.reason == "Soft [31m red [0m line txt.exe <b>x</b> end"
    assert got.reason.isprintable() and got.reason_note == ""


@pytest.mark.parametrize("n", [MAX_REASON_CHARS, MAX_REASON_CHARS + 1, 50_000])
def test_a_long_reason_is_cut_with_a_mark_and_a_note(n):
    text = ("because " * n)[:n]
    got = reading(json.dumps({"reason": text, "label": "raw_kiri_mochi"}))
    print(f"reason of {n} characters shown as {len(got.reason)}: {got.reason_note!r}")
    assert got.label == "raw_kiri_mochi"
    if n <= MAX_REASON_CHARS:
        assert got.reason == text.strip() and got.reason_note == ""
    else:
        assert len(got.reason) <= MAX_REASON_CHARS and got.reason.endswith("…")
        assert text.startswith(got.reason[:-1].rstrip())
        assert got.reason_note == (f"the reason is cut to {MAX_REASON_CHARS} of "
                                   f"{len(text.strip())} characters")


labels = st.lists(
    st.text(alphabet=string.ascii_letters + string.digits + "_ -", min_size=1, max_size=20)
    .map(str.strip).filter(bool),
    min_size=1, max_size=8, unique=True,
)


@settings(max_examples=200, deadline=None)
@given(why=st.one_of(st.text(max_size=1200), st.integers(), st.none(), st.booleans(),
                     st.lists(st.text(max_size=5), max_size=3)),
       candidates=labels, index=st.integers(0, 7), mode=st.sampled_from(MODES))
def test_the_label_never_depends_on_the_reason(why, candidates, index, mode):
    label = candidates[index % len(candidates)]
    got = read_answer(json.dumps({"reason": why, "label": label}), candidates, mode, True)
    assert got.label == read_answer(json.dumps({"label": label}), candidates, mode).label
    assert got.reason is None or (got.reason.isprintable() and got.reason == got.reason.strip()
                                  and 0 < len(got.reason) <= MAX_REASON_CHARS)
    assert (got.reason is None) == bool(got.reason_note) or got.reason.endswith("…")


@settings(max_examples=300, deadline=None)
@given(text=st.lists(st.sampled_from([*"Reason:Label*_ \n.\x1b", "raw_kiri_mochi",
                                      "boiled_kiri_mochi", "x"]), max_size=40).map("".join),
       mode=st.sampled_from(MODES))
def test_any_free_text_never_crashes_and_never_invents(text, mode):
    got = read_answer(text, CANDIDATES, mode, True)
    assert got.label is None or got.label in CANDIDATES
    assert got.reason is None or got.reason.isprintable()


# --- what is asked -------------------------------------------------------------------------

@pytest.mark.parametrize("prompt_mode", PROMPT_MODES)
@pytest.mark.parametrize(("mode", "line"), [("json_schema", REASON_JSON_REPLY),
                                            ("json_object", REASON_JSON_REPLY),
                                            ("none", REASON_THEN_LABEL)])
def test_the_prompt_asks_for_the_reason_in_place_of_the_shipped_answer_line(prompt_mode, mode,
                                                                            line):
    rendered = load_template(prompt_mode).render(DESCRIPTION, CANDIDATES)
    asked = ask_for(rendered, mode, reason=True)
    *body, last = rendered.splitlines()
    assert SHIPPED_LINE in last and SHIPPED_LINE not in asked
    assert asked.splitlines() == [*body, line]
    assert ask_for("Which?", mode, reason=True) == f"Which?\n{line}"  # a template without it
    assert correction_message(CANDIDATES, mode, reason=True).endswith(line)
    # the reason comes first in what is asked, as in the schema
    assert 0 <= line.index("eason") < line.index("abel")


@pytest.mark.parametrize("prompt_mode", PROMPT_MODES)
def test_off_the_prompt_is_the_shipped_template_byte_for_byte(prompt_mode):
    rendered = load_template(prompt_mode).render(DESCRIPTION, CANDIDATES)
    for mode in JSON_MODES:
        assert ask_for(rendered, mode) == ask_for(rendered, mode, False) == rendered
    assert ask_for(rendered, "none", False).endswith(LABEL_ALONE)
    assert correction_message(CANDIDATES, "json_schema", False).endswith(JSON_REPLY)


def test_the_schema_asks_for_the_reason_before_the_label():
    rf = response_format(["a", "b"], reason=True)
    schema = rf["json_schema"]["schema"]
    assert rf["json_schema"]["strict"] is True and schema["additionalProperties"] is False
    assert list(schema["properties"]) == ["reason", "label"] == schema["required"]
    assert schema["properties"]["reason"] == {"type": "string"}
    assert schema["properties"]["label"] == {"type": "string", "enum": ["a", "b"]}
    # written in that order on the wire too
    wire = json.dumps(rf)
    assert wire.index('"reason"') < wire.index('"label": {')
    assert response_format(["a", "b"], reason=False) == response_format(["a", "b"])


# --- the option ----------------------------------------------------------------------------

def test_the_option_is_off_by_default_and_read_from_toml():
    assert VLMConfig().ask_reason is False
    assert from_dict(VLMConfig, {"ask_reason": True}, "vlm").ask_reason is True


@pytest.mark.parametrize("value", ["yes", 1, "true"])
def test_a_bad_option_names_the_field(value):
    with pytest.raises(ConfigError, match=r"vlm\.ask_reason = .*must be true or false"):
        from_dict(VLMConfig, {"ask_reason": value}, "vlm")
    with pytest.raises(ConfigError, match=r"vlm\.ask_reason = .*must be true or false"):
        VLMConfig(ask_reason=value).validate("vlm")


# --- through the client and the fake server ------------------------------------------------

def _sent(body: dict) -> str:
    """A request body as sent, but for the image's data (its encoding is PIL's)."""
    texts = [m["content"] if isinstance(m["content"], str)
             else [p["text"] for p in m["content"] if p["type"] == "text"]
             for m in body["messages"]]
    return json.dumps({**{k: v for k, v in body.items() if k != "messages"}, "texts": texts},
                      sort_keys=True, ensure_ascii=False)


# sha256 of _sent() for every prompt mode and structured-output mode, and for the corrective
# retry's conversation, taken from the client before vlm.ask_reason existed.
LABEL_ONLY = {
    ("vision_tactile", "json_schema"):
        "9c443e8682c3ffb2bb153efbcebab9bdea6101256a7efba4bf04310fd59fd26a",
    ("vision_tactile", "json_object"):
        "218146af7714c7738a3a109cbc7d0c553207491183d504798310d508704cec37",
    ("vision_tactile", "none"):
        "dc66aa3fd7fa68dad41157fa5a9a0f67e88b44cfeb803cbedad5bb267ed9d7f2",
    ("vision_only", "json_schema"):
        "7776fde193017405bc99a2a4859ab04199c7254e9293c9b332d35678ed424f15",
    ("vision_only", "json_object"):
        "19a56423724c5e325480d282b31f76b93aa28562a2d42ddae1137c520f75d502",
    ("vision_only", "none"):
        "0742960b44f2cfebc9003892183f88b9fcadce4176b10c2442160486bf76ab65",
    ("tactile_only", "json_schema"):
        "49dd38642026a444b77af61f32ff26b660e3dfc03a88d1f1ed60b8bd697076a8",
    ("tactile_only", "json_object"):
        "4677a08a4d8a641fc88680257bf321a8ffa7d3a9c69b315c1a5adf54a2da2db8",
    ("tactile_only", "none"):
        "6da03d7b7b762c4b2d0b0ad401d92604e5cf209078a5b8593f9b5a161446de01",
}
CORRECTION = {
    "json_schema": "d127890da97c74916e4176e8f0356c2d4c401c11a89619a5fc314539ce2123f9",
    "json_object": "a5a495b794e68e61b49a6b5e8a367fdc94838f7ba1b2cddb26a5c03f07d5866a",
    "none": "352a106ec6b55511b297cb9af8fb04245478add8ef1176c57eea86097202f478",
}


def _digest(body: dict) -> str:
    return hashlib.sha256(_sent(body).encode()).hexdigest()


@pytest.mark.asyncio
async def test_off_every_request_is_the_label_only_one_byte_for_byte(fake, jpeg):
    for (prompt_mode, mode), expected in LABEL_ONLY.items():
        for cfg in (vlm_config(fake.base_url, mode=prompt_mode, structured_output=mode),
                    vlm_config(fake.base_url, mode=prompt_mode, structured_output=mode,
                               ask_reason=False)):
            async with OpenAIVLM(cfg) as vlm:
                answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
            assert _digest(fake.chat_requests[-1].body) == expected, (prompt_mode, mode)
            assert answer.reason is None and answer.label == CANDIDATES[0]
    for mode, expected in CORRECTION.items():
        fake.script(Reply(content="pizza" if mode == "none" else '{"label": "pizza"}'))
        async with OpenAIVLM(vlm_config(fake.base_url, structured_output=mode)) as vlm:
            answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
        assert answer.attempts == 2 and _digest(fake.chat_requests[-1].body) == expected, mode


@pytest.mark.asyncio
@pytest.mark.parametrize("mode", MODES)
async def test_asked_the_fake_server_answers_a_reason_through_the_client(fake, jpeg, mode):
    cfg = vlm_config(fake.base_url, structured_output=mode, ask_reason=True)
    async with OpenAIVLM(cfg) as vlm:
        answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
    [req] = fake.chat_requests
    label = CANDIDATES[0]
    assert (answer.status, answer.label, answer.structured_output) == ("ok", label, mode)
    assert answer.reason == plain_reason(req, label)
    assert req.body.get("response_format") == {
        "json_schema": response_format(CANDIDATES, reason=True),
        "json_object": {"type": "json_object"}, "none": None}[mode]
    line = REASON_THEN_LABEL if mode == "none" else REASON_JSON_REPLY
    assert req.prompt.endswith(line) and SHIPPED_LINE not in req.prompt
    # the prompt stored is the rendered template; the reason line is in the request
    assert answer.prompt == load_template("vision_tactile").render(DESCRIPTION, CANDIDATES)
    assert answer.to_dict()["reason"] == answer.reason


@pytest.mark.asyncio
@pytest.mark.parametrize(("structured", "answered"), [("json_object_only", "json_object"),
                                                      ("none_only", "none")])
async def test_the_reason_survives_the_step_down(jpeg, structured, answered):
    async with FakeVLM(model=MODEL, structured=structured) as fake, \
            OpenAIVLM(vlm_config(fake.base_url, ask_reason=True)) as vlm:
        answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
        req = fake.chat_requests[-1]
    assert (answer.status, answer.structured_output) == ("ok", answered)
    assert answer.reason == plain_reason(req, CANDIDATES[0])
    if answered == "none":
        assert answer.raw == f"Reason: {answer.reason}\nLabel: {CANDIDATES[0]}"


@pytest.mark.asyncio
async def test_the_corrective_retry_asks_for_a_reason_too(fake, jpeg):
    fake.script(Reply(content='{"reason": "Looks like a rice cake.", "label": "rice_cake"}'))
    async with OpenAIVLM(vlm_config(fake.base_url, ask_reason=True)) as vlm:
        answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
    first, second = fake.chat_requests
    assert second.body["messages"][0] == first.body["messages"][0]
    assert second.body["messages"][-1]["content"].endswith(REASON_JSON_REPLY)
    assert (answer.status, answer.attempts) == ("ok", 2)
    assert answer.reason == plain_reason(second, CANDIDATES[0])  # the answer that counted


@pytest.mark.asyncio
@pytest.mark.parametrize(("content", "reason", "note"), [
    ('{"reason": 42, "label": "raw_kiri_mochi"}', None, "the reason is a number, not text"),
    ('{"label": "raw_kiri_mochi"}', None, "no reason given"),
    (json.dumps({"reason": "x" * 5000, "label": "raw_kiri_mochi"}), "x" * 499 + "…",
     "cut to 500 of 5000 characters"),
])
async def test_a_hostile_reason_keeps_the_label_and_is_logged(fake, jpeg, caplog, content,
                                                              reason, note):
    caplog.set_level(logging.WARNING, "edge.vlm.client")
    fake.script(Reply(content=content))
    async with OpenAIVLM(vlm_config(fake.base_url, ask_reason=True)) as vlm:
        answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
    assert (answer.status, answer.label, answer.reason) == ("ok", "raw_kiri_mochi", reason)
    assert answer.raw == content and answer.attempts == 1
    assert any(note in r.getMessage() for r in caplog.records), caplog.text


@pytest.mark.asyncio
async def test_a_reason_never_shows_the_api_key_even_cut(monkeypatch, jpeg):
    planted = "sk-PLANTED-secret-0123456789abcdef"
    monkeypatch.setenv("VTZERO_VLM_API_KEY", planted)
    # The key straddles the cut: a reason cut first and redacted after would show its head.
    said = "y" * (MAX_REASON_CHARS - 10) + planted + " and more"
    async with FakeVLM(model=MODEL, api_key=planted) as fake:
        fake.script(Reply(content=json.dumps({"reason": said, "label": "raw_kiri_mochi"})))
        async with OpenAIVLM(vlm_config(fake.base_url, ask_reason=True)) as vlm:
            answer = await vlm.ask(jpeg, DESCRIPTION, CANDIDATES)
    assert answer.label == "raw_kiri_mochi" and answer.reason.startswith("y" * 100)
    assert planted[:8] not in answer.reason and planted not in json.dumps(answer.to_dict())
