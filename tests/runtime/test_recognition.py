"""Recognition alone: a scripted press controller, the analysis run in-process, a scripted
VLM client and a real store (no emulator, no compute process): every way an episode ends."""

from __future__ import annotations

import asyncio
import json
from dataclasses import dataclass, field, replace
from typing import Any

import pytest

from edge.core.config import Config
from edge.core.errors import (
    BadRequest,
    BusyError,
    ComputeError,
    StoreError,
    VLMConnectionError,
    VLMRejectedError,
)
from edge.core.model import model_ref
from edge.runtime.domain import Hello, PressResult, PressState, Status
from edge.runtime.events import EventBus
from edge.runtime.metrics import Metrics
from edge.runtime.press import PressOutcome
from edge.runtime.recognition import Recognition, Recognizer
from edge.runtime.ring import Window
from edge.runtime.store import EpisodeStore
from edge.sim.fake_vlm import FakeVLM
from edge.vlm.client import OpenAIVLM, VLMAnswer
from tests.support.daemon import ROOT
from tests.support.fakes import FakeCamera
from tests.support.presses import recording_of
from tests.vlm.helpers import MODEL as VLM_MODEL
from tests.vlm.helpers import image_bytes, vlm_config

pytestmark = pytest.mark.asyncio
CANDIDATES = ["macaron", "resin_replica_macaron"]
MODEL = model_ref(ROOT / "models")


def pressed(seed: int = 3) -> PressOutcome:
    """A real press of a macaron (from the simulator) as the controller reports it."""
    rec = recording_of("macaron", seed)
    return PressOutcome(result=PressResult.OK, t_cross=rec.t_stop - 0.001, t_stop=rec.t_stop,
                        stop_latency_s=0.001, tare=rec.tare,
                        window=Window(rec.frames, rec.recv_time, rec.sensor_time, rec.seq))


class ScriptedPress:
    """Returns the next outcome; ``gate`` (when set) holds the press until released, after
    handing its outcome over as the window is complete when ``hand_over`` is set;
    ``check_gate`` (when set) holds its motor check until released."""

    def __init__(self, *outcomes: PressOutcome) -> None:
        self.outcomes = list(outcomes)
        self.gate: asyncio.Event | None = None
        self.check_gate: asyncio.Event | None = None
        self.hand_over = False
        self.state = PressState.IDLE

    async def run(self, window_ready: asyncio.Future | None = None,
                  checked: asyncio.Future | None = None) -> PressOutcome:
        if self.check_gate is not None:
            await self.check_gate.wait()
        if checked is not None:
            checked.set_result(None)
        self.state = PressState.CLOSING
        outcome = self.outcomes.pop(0)
        if self.hand_over and window_ready is not None:
            self.state = PressState.RETURNING
            window_ready.set_result(outcome)
        if self.gate is not None:
            await self.gate.wait()
        self.state = PressState.IDLE
        return outcome


class InProcessCompute:
    """The compute worker's contract, run here; counts round trips."""

    def __init__(self, fail: Exception | None = None) -> None:
        self.calls: list[str] = []
        self.fail = fail

    async def run(self, fn, *args):
        self.calls.append(fn.__name__)
        if self.fail is not None:
            raise self.fail
        return fn(*args)


@dataclass
class ScriptedVLM:
    """Answers (or raises) from a script, one entry per question."""

    script: list[Any]
    asked: list[tuple[Any, str, list[str]]] = field(default_factory=list)
    closed: bool = False
    mode: str = "vision_tactile"
    unreachable: str | None = None

    def image_limits(self) -> tuple[int, int]:
        return 512, 200_000

    async def ask(self, image, description, candidates) -> VLMAnswer:
        self.asked.append((image, description, list(candidates)))
        step = self.script.pop(0)
        if isinstance(step, Exception):
            raise step
        return VLMAnswer(status="ok", label=step, raw=step, prompt="p",
                         candidates=tuple(candidates), model="scripted", request=None,
                         response=None, image=None, attempts=1, latency_s=(0.01,),
                         outcomes=("ok",), elapsed_s=0.01)

    async def close(self) -> None:
        self.closed = True


async def drain(sub) -> list[dict]:
    """The events waiting in a subscription."""
    seen = []
    while True:
        try:
            seen.append((await asyncio.wait_for(sub.get(), 0.01)).to_json())
        except TimeoutError:
            return seen


def recognizer(tmp_path, press, vlm, compute=None, camera=None, cfg: Config | None = None):
    cfg = cfg or Config()
    events = EventBus()
    rec = Recognizer(Recognition(cfg, MODEL, vlm), press,
                     compute or InProcessCompute(), EpisodeStore(tmp_path / "episodes"),
                     events, Metrics(), camera)
    return rec, events


async def test_a_press_is_analysed_once_asked_and_kept_done(tmp_path):
    vlm = ScriptedVLM(["macaron"])
    compute = InProcessCompute()
    camera = FakeCamera(image_bytes(1200, 900))
    rec, events = recognizer(tmp_path, ScriptedPress(pressed()), vlm, compute, camera)
    with events.subscribe(Hello(PressState.IDLE, None)) as sub:
        episode = await rec.recognize(CANDIDATES, None, True, 10, "api")
        seen = await drain(sub)
    assert episode.status == Status.DONE and episode.label == "macaron"
    assert [n.label for n in episode.topk][:1] and len(episode.topk) == 3
    assert episode.description and episode.z and episode.code is not None
    assert set(episode.timings) == {"press_s", "encode_s", "vlm_s"}
    # The compute process: the photo prepared while the press runs, then the analysis on
    # the window; the press itself is serialised after the question has left.
    assert sorted(compute.calls[:2]) == ["analyse_press", "prepare_for_vlm"]
    assert compute.calls[2:] == ["to_bytes"] and camera.captures == 1
    image, description, candidates = vlm.asked[0]
    prepared, data_url = image  # prepared for the VLM, not raw bytes
    assert max(prepared.width, prepared.height) <= 512 and data_url.startswith(b"data:")
    assert description == episode.description and candidates == CANDIDATES
    files = sorted(p.name for p in (tmp_path / "episodes" / episode.id).iterdir())
    assert files == ["episode.json", "image.jpg", "model_io.npz", "press.press.npz"]
    kinds = [e["type"] for e in seen]
    assert kinds[0] == "hello" and "tactile" in kinds and kinds[-1] == "episode"
    assert any(e["type"] == "result" and e["label"] == "macaron" for e in seen)


@pytest.mark.parametrize("uploaded", [False, True], ids=["camera", "uploaded"])
async def test_the_photo_waits_for_the_press_to_check_the_motors(tmp_path, uploaded):
    # The photo's work beside the check's round trips would start the press later.
    camera = FakeCamera(image_bytes(640, 480))
    compute = InProcessCompute()
    press = ScriptedPress(pressed())
    press.check_gate = asyncio.Event()
    rec, _ = recognizer(tmp_path, press, ScriptedVLM(["macaron"]), compute,
                        None if uploaded else camera)
    image = camera.image if uploaded else None
    running = asyncio.create_task(rec.recognize(CANDIDATES, image, True, 10, "api"))
    for _ in range(20):
        await asyncio.sleep(0)
    # An upload was decoded (once, for the VLM) before anything moved; nothing else runs.
    assert camera.captures == 0 and not running.done()
    assert compute.calls == (["prepare_for_vlm"] if uploaded else [])
    press.check_gate.set()
    episode = await running
    assert camera.captures == (0 if uploaded else 1)
    assert compute.calls.count("prepare_for_vlm") == 1
    assert episode.status == Status.DONE


async def test_an_upload_that_does_not_decode_is_refused_before_anything_moves(tmp_path):
    press = ScriptedPress(pressed())
    compute = InProcessCompute()
    rec, _ = recognizer(tmp_path, press, ScriptedVLM([]), compute)
    broken = image_bytes(64, 48)[:40]  # a JPEG's header, its pixels cut off
    with pytest.raises(BadRequest, match="image must be a JPEG or PNG file that decodes"):
        await rec.recognize(CANDIDATES, broken, True, 10, "api")
    assert compute.calls == ["prepare_for_vlm"] and len(press.outcomes) == 1
    assert rec.store.list() == [] and not rec.lock.locked()


async def test_a_press_failing_before_its_check_still_keeps_the_photo(tmp_path):
    # No check, no wait forever: the press's end releases the photo, kept with the failure.
    camera = FakeCamera(image_bytes(640, 480))
    stale = PressOutcome(result=PressResult.STALE, message="tactile stream is stale")

    class Unchecked(ScriptedPress):
        async def run(self, window_ready=None, checked=None):
            return await super().run(window_ready, None)

    rec, _ = recognizer(tmp_path, Unchecked(stale), ScriptedVLM([]), camera=camera)
    episode = await rec.recognize(CANDIDATES, None, True, 10, "api")
    assert episode.status == Status.FAILED and camera.captures == 1
    assert (tmp_path / "episodes" / episode.id / "image.jpg").exists()


async def test_an_unreachable_vlm_leaves_it_pending_then_the_retry_completes_it(tmp_path):
    vlm = ScriptedVLM([VLMConnectionError("connection refused"), "resin_replica_macaron"])
    cfg = Config()
    cfg = replace(cfg, runtime=replace(cfg.runtime, vlm_retry_base_s=0.05))
    rec, _ = recognizer(tmp_path, ScriptedPress(pressed()), vlm, cfg=cfg)
    episode = await rec.recognize(CANDIDATES, image_bytes(), True, 10, "api")
    assert episode.status == Status.PENDING and episode.attempts == 1
    assert episode.last_error == "connection refused" and episode.next_retry_at > 0
    retry = asyncio.create_task(rec.retry_pending())
    try:
        for _ in range(100):
            episode = await rec.episode(episode.id)
            if episode.status.final:
                break
            await asyncio.sleep(0.02)
    finally:
        retry.cancel()
    assert episode.status == Status.DONE and episode.label == "resin_replica_macaron"
    assert episode.attempts == 2
    assert isinstance(vlm.asked[1][0], bytes)  # asked again with the stored photo


async def test_a_refused_question_is_a_vlm_error_not_retried(tmp_path):
    vlm = ScriptedVLM([VLMRejectedError("401 Unauthorized", 401)])
    rec, _ = recognizer(tmp_path, ScriptedPress(pressed()), vlm)
    episode = await rec.recognize(CANDIDATES, image_bytes(), True, 10, "api")
    assert episode.status == Status.VLM_ERROR and "401" in episode.last_error
    assert episode.label is None and vlm.script == []


async def test_a_failed_press_is_kept_failed_and_never_asked(tmp_path):
    vlm = ScriptedVLM([])
    outcome = PressOutcome(result=PressResult.NO_CONTACT,
                           message="no contact: the norm stayed below")
    compute = InProcessCompute()
    rec, _ = recognizer(tmp_path, ScriptedPress(outcome), vlm, compute)
    episode = await rec.recognize(CANDIDATES, None, True, 10, "button")
    assert episode.status == Status.FAILED and episode.error.startswith("no contact")
    assert episode.source == "button" and vlm.asked == [] and compute.calls == []


async def test_a_failed_analysis_keeps_the_raw_press(tmp_path):
    compute = InProcessCompute(fail=ComputeError("the compute worker died during "
                                                 "analyse_press"))
    rec, _ = recognizer(tmp_path, ScriptedPress(pressed()), ScriptedVLM([]), compute)
    episode = await rec.recognize(CANDIDATES, None, True, 10, "api")
    assert episode.status == Status.FAILED
    assert episode.error.startswith("the press worked but its analysis failed")
    assert (tmp_path / "episodes" / episode.id / "press.press.npz").is_file()


async def test_one_press_at_a_time_and_none_while_the_disk_is_full(tmp_path, monkeypatch):
    press = ScriptedPress(pressed(), pressed(4))
    press.gate = asyncio.Event()
    rec, _ = recognizer(tmp_path, press, ScriptedVLM(["macaron"]))
    first = await rec.recognize(CANDIDATES, None, False, None, "api")
    assert first.status == Status.RUNNING
    with pytest.raises(BusyError) as busy:
        await rec.recognize(CANDIDATES, None, False, None, "api")
    assert busy.value.episode_id == first.id
    press.gate.set()
    await asyncio.gather(*rec.work)
    monkeypatch.setattr(rec.store, "space_error", lambda: "disk full (1.0 MiB free)")
    with pytest.raises(StoreError, match="not pressing: the episode could not be kept"):
        await rec.recognize(CANDIDATES, None, False, None, "api")
    assert press.outcomes == [press.outcomes[0]]  # the second press never ran


async def test_after_shutdown_begins_no_press_starts(tmp_path):
    press = ScriptedPress(pressed())
    rec, _ = recognizer(tmp_path, press, ScriptedVLM([]))
    rec.accepting = False
    with pytest.raises(BusyError, match="shutting down"):
        await rec.recognize(CANDIDATES, None, False, None, "api")
    assert len(press.outcomes) == 1


async def test_the_vlm_is_asked_at_the_window_while_the_arm_returns(tmp_path):
    press = ScriptedPress(pressed())
    press.gate, press.hand_over = asyncio.Event(), True
    vlm = ScriptedVLM(["macaron"])
    rec, events = recognizer(tmp_path, press, vlm)
    with events.subscribe(Hello(PressState.IDLE, None)) as sub:
        running = await rec.recognize(CANDIDATES, image_bytes(), False, None, "api")
        for _ in range(200):
            if vlm.asked:
                break
            await asyncio.sleep(0.01)
        # Asked while the arm returns; the next press waits for the arm, the episode for
        # the press.
        assert vlm.asked and press.state == "returning"
        with pytest.raises(BusyError):
            await rec.recognize(CANDIDATES, image_bytes(), False, None, "api")
        assert not [e for e in await drain(sub) if e["type"] in ("tactile", "result")]
        press.gate.set()
        await asyncio.gather(*rec.work)
        seen = await drain(sub)
    episode = await rec.episode(running.id)
    assert episode.status == Status.DONE and episode.label == "macaron"
    assert not rec.lock.locked() and len(vlm.asked) == 1
    kinds = [e["type"] for e in seen]
    assert kinds.index("tactile") < kinds.index("result")


async def test_a_press_to_teach_from_is_analysed_and_kept_with_no_question(tmp_path):
    vlm = ScriptedVLM([])
    compute = InProcessCompute()
    camera = FakeCamera(image_bytes(640, 480))
    rec, events = recognizer(tmp_path, ScriptedPress(pressed()), vlm, compute, camera)
    with events.subscribe(Hello(PressState.IDLE, None)) as sub:
        episode = await rec.recognize([], None, True, 10, "teach", ask=False)
        seen = await drain(sub)
    assert episode.status == Status.PRESSED and episode.status.final
    assert episode.label is None and episode.error is None and len(episode.topk) == 3
    assert episode.press is not None and episode.press.contact
    # No photo, no question: the analysis and the press's recording only.
    assert vlm.asked == [] and camera.captures == 0
    assert compute.calls == ["analyse_press", "to_bytes"]
    files = sorted(p.name for p in (tmp_path / "episodes" / episode.id).iterdir())
    assert files == ["episode.json", "model_io.npz", "press.press.npz"]
    kinds = [e["type"] for e in seen]
    assert "tactile" in kinds and "result" not in kinds and kinds[-1] == "episode"
    assert not rec.lock.locked()


async def test_a_press_to_teach_from_whose_arm_did_not_return_is_failed(tmp_path):
    outcome = pressed()
    press = ScriptedPress(outcome)
    press.gate, press.hand_over = asyncio.Event(), True
    rec, _ = recognizer(tmp_path, press, ScriptedVLM([]))
    running = await rec.recognize([], None, False, None, "teach", ask=False)
    for _ in range(200):
        if press.state == PressState.RETURNING:
            break
        await asyncio.sleep(0.01)
    # Analysed at the window; the return fails after it.
    outcome.result, outcome.message = PressResult.ERROR, "the arm did not return"
    press.gate.set()
    await asyncio.gather(*rec.work)
    episode = await rec.episode(running.id)
    assert episode.status == Status.FAILED and episode.error == "the arm did not return"
    assert episode.topk  # the analysis is kept


async def test_every_analysed_press_carries_its_familiarity_and_a_reload_moves_the_flag(
        tmp_path):
    press = ScriptedPress(pressed(), pressed())
    vlm = ScriptedVLM(["macaron", "macaron"])
    rec, events = recognizer(tmp_path, press, vlm)
    with events.subscribe(Hello(PressState.IDLE, None)) as sub:
        first = await rec.recognize(CANDIDATES, None, True, 10, "api")
        seen = await drain(sub)
    print("familiarity", first.familiarity)
    # A macaron, unlike every reference's nearest other press more than most (the shipped
    # database): familiar at the default 95th percentile.
    assert 50 < first.familiarity < 95 and first.unfamiliar is False
    tactile = next(e for e in seen if e["type"] == "tactile")
    assert tactile["familiarity"] == first.familiarity and tactile["unfamiliar"] is False
    # As a reload swaps it: [runtime] unfamiliar_percentile = 50 from the next press on.
    cfg = Config()
    cfg = replace(cfg, runtime=replace(cfg.runtime, unfamiliar_percentile=50.0))
    rec.setup = Recognition(cfg, MODEL, vlm)
    second = await rec.recognize(CANDIDATES, None, True, 10, "api")
    assert second.familiarity == first.familiarity and second.unfamiliar is True
    stored = (tmp_path / "episodes" / second.id / "episode.json").read_text()
    assert '"unfamiliar": true' in stored
    assert rec.metrics.unfamiliar == 1 and rec.metrics.familiarity.n == 2


async def test_a_press_with_no_question_refuses_a_photo_before_anything_moves(tmp_path):
    press = ScriptedPress(pressed())
    rec, _ = recognizer(tmp_path, press, ScriptedVLM([]))
    with pytest.raises(ValueError, match="no question takes no photo"):
        await rec.recognize([], image_bytes(), True, 10, "teach", ask=False)
    assert len(press.outcomes) == 1 and rec.store.list() == []


@pytest.mark.parametrize("ask_reason", [True, False], ids=["asked", "not asked"])
async def test_the_vlms_reason_is_kept_on_the_episode_and_its_result_when_asked(
        tmp_path, ask_reason):
    # The real client against the fake server, which reasons only when asked.
    hostile = "Soft <script>alert(1)</script> & pale"
    async with FakeVLM(model=VLM_MODEL, explain=lambda req, label: hostile) as fake, \
            OpenAIVLM(vlm_config(fake.base_url, ask_reason=ask_reason)) as vlm:
        rec, events = recognizer(tmp_path, ScriptedPress(pressed()), vlm,
                                 camera=FakeCamera(image_bytes()))
        with events.subscribe(Hello(PressState.IDLE, None)) as sub:
            episode = await rec.recognize(CANDIDATES, None, True, 10, "api")
            seen = await drain(sub)
    assert episode.status == Status.DONE and episode.label == CANDIDATES[0]
    result = next(e for e in seen if e["type"] == "result")
    stored = json.loads((tmp_path / "episodes" / episode.id / "episode.json").read_text())
    if ask_reason:
        # Kept as the reader made it: markup is for the page to escape (textContent).
        assert episode.reason == hostile == result["reason"] == stored["reason"]
        assert rec.store.get(episode.id).reason == hostile
    else:
        assert episode.reason is None and "reason" not in result and "reason" not in stored
