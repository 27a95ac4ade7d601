"""The typed state's JSON forms: documented field for field, read by the operator page by
the documented keys only, and on the wire as they have always been."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import re
import time
import typing
from pathlib import Path
from types import SimpleNamespace

import pytest

from edge.core.errors import StoreError
from edge.hw.contracts import GripperState
from edge.interfaces.http import webui
from edge.runtime.domain import (
    Episode,
    EpisodeFinished,
    EpisodeStarted,
    Event,
    Health,
    Hello,
    Label,
    Neighbour,
    PressAgain,
    PressResult,
    PressState,
    PressSummary,
    StateChanged,
    Status,
    TactileResult,
    TeachProgress,
    TeachRun,
    VLMRefused,
    VLMUnreachable,
)
from edge.runtime.events import EventBus
from edge.runtime.metrics import Metrics
from edge.runtime.press import PressOutcome
from edge.runtime.sensor import SamplerStats

APP_JS = Path(webui.__file__).parent / "static" / "app.js"
HEALTH_KEYS = {f.name for f in dataclasses.fields(Health)}
PRESS_KEYS = {f.name for f in dataclasses.fields(PressSummary)} - {"extra"}


def _function_body(source: str, marker: str) -> str:
    """The braces-balanced body of the function whose text holds ``marker``."""
    at = source.index(marker)
    start = source.rindex("function ", 0, at)
    depth, i = 0, source.index("{", start)
    for j in range(i, len(source)):
        depth += {"{": 1, "}": -1}.get(source[j], 0)
        if depth == 0:
            return source[i:j + 1]
    raise AssertionError(f"unbalanced braces after {marker!r}")


def page_reads(source: str) -> tuple[set[str], set[str]]:
    """The keys the page reads from /healthz's answer and from an episode's ``press``."""
    health = set(re.findall(r"\bdata\.(\w+)", _function_body(source, 'call("/healthz")')))
    press = set(re.findall(r"\.press\.(\w+)", source))
    return health, press


def unknown_page_keys(source: str) -> list[str]:
    health, press = page_reads(source)
    return ([f"health.{k}" for k in sorted(health - HEALTH_KEYS)]
            + [f"press.{k}" for k in sorted(press - set(webui.LISTED_PRESS))])


def test_the_page_reads_only_documented_keys():
    source = APP_JS.read_text()
    health, press = page_reads(source)
    print(f"app.js reads health {sorted(health)}, press {sorted(press)}")
    # The page shows the verdict, every reason and the state: all of them are read.
    assert {"ok", "ready", "sensor_fresh", "sensor_error", "bus_error", "store_error",
            "vlm_error", "state", "episode", "version"} <= health
    assert press == {"stop_latency_ms"}
    assert unknown_page_keys(source) == []
    # The episode list carries keys of the summary only (a rename fails at import).
    assert set(webui.LISTED_PRESS) <= PRESS_KEYS


def test_a_renamed_key_in_the_page_is_caught():
    source = APP_JS.read_text()
    renamed = source.replace("data.sensor_fresh", "data.sensor_is_fresh").replace(
        "ep.press.stop_latency_ms", "ep.press.stop_latency")
    assert unknown_page_keys(renamed) == ["health.sensor_is_fresh", "press.stop_latency"]


def test_a_subset_of_unknown_keys_is_refused():
    with pytest.raises(ValueError, match="not keys of a press summary: stop_ms"):
        PressSummary.keys("result", "stop_ms")


@pytest.mark.parametrize("cls", [Health, PressSummary])
def test_the_docstring_documents_every_field(cls):
    documented = re.findall(r'^\s*[{ ]\s*"(\w+)":', cls.__doc__ or "", re.MULTILINE)
    fields = [f.name for f in dataclasses.fields(cls) if f.name != "extra"]
    assert documented == fields


def _outcome() -> PressOutcome:
    outcome = PressOutcome(result=PressResult.OK, t_cross=10.25, t_stop=10.2503,
                           stop_latency_s=0.0003, peak_level=0.0051, level_at_cross=0.0042,
                           lowering_level=0.0004)
    outcome.gripper_trace = [GripperState(10.1, 0.03, 40.0, 1900),
                             GripperState(10.3, 0.02, 95.5, 2000)]
    outcome.states = [(PressState.ABOVE, 8.0), (PressState.CLOSING, 9.5),
                      (PressState.IDLE, 12.0)]
    return outcome


def test_the_summary_on_the_wire_is_the_plain_json_it_always_was():
    summary = _outcome().summary()
    wire = json.loads(json.dumps(summary.to_json()))
    assert wire == {
        "result": "ok", "message": "", "contact": True, "t_cross": 10.25, "t_stop": 10.2503,
        "stop_latency_ms": pytest.approx(0.3), "peak_level": 0.0051, "level_at_cross": 0.0042,
        "peak_squeeze_ma": 95.5,
        "states": [["above", 8.0], ["closing", 9.5], ["idle", 12.0]], "lowering_level": 0.0004,
        "window_rate_hz": None, "press_rate_hz": None}  # (no frames kept)
    assert list(wire) == [f.name for f in dataclasses.fields(PressSummary)][:-1]
    back = PressSummary.from_json(wire)
    assert back == summary and back.result is PressResult.OK
    assert back.entered(PressState.CLOSING) == 9.5 and back.entered(PressState.HOLDING) is None


def test_a_press_stored_before_the_lowering_check_reads_without_its_level():
    wire = _outcome().summary().to_json()
    del wire["lowering_level"]
    press = PressSummary.from_json(wire)
    assert press.lowering_level is None and press.extra == {}
    assert press.to_json()["lowering_level"] is None


def test_an_episode_keeps_its_press_typed_and_carries_unknown_keys():
    wire = _outcome().summary().to_json() | {"newer_key": [1, 2]}
    episode = Episode.from_json({"id": "e1", "status": "done", "candidates": ["a"],
                                 "source": "api", "press": wire})
    assert isinstance(episode.press, PressSummary) and episode.press.contact
    assert episode.to_json()["press"] == wire


@pytest.mark.parametrize(("change", "message"), [
    ({"result": "crushed"}, "'press': unknown result 'crushed'; known: ok, no_contact"),
    ({"states": [["squeezing", 1.0]]}, "'press': 'states' must be a list of [state, time]"),
    ({"t_stop": ...}, "'press': missing t_stop"),
])
def test_a_bad_stored_press_names_the_episode_and_the_key(change, message):
    wire = _outcome().summary().to_json() | change
    wire = {k: v for k, v in wire.items() if v is not ...}
    with pytest.raises(StoreError, match=re.escape("episode e1: " + message)):
        Episode.from_json({"id": "e1", "status": "done", "press": wire}, "episode e1")


def test_health_on_the_wire_says_the_state_as_a_string():
    health = Health(ok=False, ready=True, sensor_fresh=False, bus_error=None, store_error=None,
                    sensor_error=None, vlm_error=None, torque_on=True,
                    state=PressState.CLOSING, episode="e1", last_frame_age_s=1.5,
                    model_digest="abc", version="1")
    wire = json.loads(json.dumps(health.to_json()))
    assert wire["state"] == "closing" and set(wire) == HEALTH_KEYS
    assert type(health.to_json()["state"]) is str


def test_the_events_on_the_wire_are_the_json_they_always_were():
    done = Episode("e1", Status.DONE, ["a", "b"], "api", label="a", description="soft",
                   topk=[Neighbour("a", 0.25), Neighbour("b", 0.5)], familiarity=97.5,
                   unfamiliar=True)
    refused = done.with_(status=Status.VLM_ERROR, label=None, last_error="HTTP 400")
    pending = done.with_(status=Status.PENDING, label=None, last_error="unreachable")
    t = 1700000000.5
    events = (
        Hello(PressState.IDLE, None), StateChanged(PressState.CLOSING, "e1", t),
        EpisodeStarted("e1", t), PressAgain("e1", 2, 3, 5.0, "move it", t),
        TeachProgress("lab_macaron", "taught", 1, 2, "e1", "r1", None,
                      TeachRun("lab_macaron", "lab macaron", 2, False, "api"), t),
        TactileResult(done, t), Label(done, t), VLMRefused(refused, t),
        VLMUnreachable(pending, t), EpisodeFinished(done, t))
    assert {type(event) for event in events} == set(typing.get_args(Event))
    wires = [json.loads(json.dumps(event.to_json())) for event in events]
    print(wires)
    assert wires == [
        {"type": "hello", "state": "idle", "episode": None},
        {"t": t, "type": "state", "state": "closing", "episode": "e1"},
        {"t": t, "type": "episode", "episode": "e1", "status": "running"},
        {"t": t, "type": "press_again", "episode": "e1", "press": 2, "presses": 3,
         "pause_s": 5.0, "message": "move it"},
        {"t": t, "type": "teach", "label": "lab_macaron", "step": "taught", "press": 1,
         "presses": 2, "episode": "e1", "reference": "r1", "message": None},
        {"t": t, "type": "tactile", "episode": "e1", "description": "soft",
         "topk": [{"label": "a", "distance": 0.25}, {"label": "b", "distance": 0.5}],
         "familiarity": 97.5, "unfamiliar": True},
        {"t": t, "type": "result", "episode": "e1", "status": "done", "label": "a"},
        {"t": t, "type": "result", "episode": "e1", "status": "vlm_error",
         "error": "HTTP 400"},
        {"t": t, "type": "episode", "episode": "e1", "status": "pending",
         "error": "unreachable"},
        {"t": t, "type": "episode", "episode": "e1", "status": "finished"}]
    # Stamped when made, on the wall clock (what the page and MQTT's P/state show).
    assert abs(StateChanged(PressState.IDLE, None).t - time.time()) < 60


@pytest.mark.asyncio
async def test_a_slow_subscriber_loses_its_oldest_events_never_the_publisher_its_pace():
    bus = EventBus()
    with bus.subscribe(Hello(PressState.IDLE, None)) as sub:
        assert await sub.get() == Hello(PressState.IDLE, None)
        for i in range(300):
            bus.publish(EpisodeStarted(f"e{i}"))
        queued = []
        with contextlib.suppress(TimeoutError):
            while True:
                queued.append(await asyncio.wait_for(sub.get(), 0.01))
    print(f"{len(queued)} of 300 events kept")
    assert [e.episode_id for e in queued] == [f"e{i}" for i in range(300 - 256, 300)]


def test_only_running_and_pending_are_not_final():
    assert {s for s in Status if not s.final} == {Status.RUNNING, Status.PENDING}


def test_metrics_count_presses_by_result_value():
    metrics = Metrics()
    for result in (PressResult.OK, PressResult.OK, PressResult.NO_CONTACT):
        metrics.observe_press(PressOutcome(result=result))
    assert metrics.presses == {"ok": 2, "no_contact": 1}
    sensor = SimpleNamespace(frames=0, stale_events=0)
    text = metrics.render(SamplerStats(), sensor)
    assert 'vtzero_presses_total{result="ok"} 2' in text
    assert 'vtzero_presses_total{result="no_contact"} 1' in text
    assert 'vtzero_presses_total{result="ok"} 0' in Metrics().render(SamplerStats(), sensor)
