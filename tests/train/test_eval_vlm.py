"""``vt-train eval-vlm`` against the local fake VLM: Table I conditions, cache and resume,
invalid answers, the shipped prompts, the CLI. Tiny sets (Cube, 2 presses per class)."""

from __future__ import annotations

import asyncio
import io
import json

import pytest
from PIL import Image

from edge.core.config import VLMConfig
from edge.core.errors import EvalVLMError
from edge.core.model import load_model
from edge.sim.camera import render
from edge.sim.fake_vlm import FakeVLM, Reply
from edge.sim.standin_vlm import StandIn
from edge.vlm.prompt import load_template
from tests.support.vlm_thread import fake_in_thread
from train.eval import eval_vlm
from train.eval.eval_vlm.cache import ANSWERS_FILE, AnswerCache
from train.eval.eval_vlm.config import DEFAULT_CONDITIONS, EvalVLMConfig
from train.eval.eval_vlm.provenance import describe_origin, model_facts, reference_origin
from train.eval.eval_vlm.report import REPORT_JSON, REPORT_MD
from train.eval.eval_vlm.sets import load_test_set, round_robin

from .conftest import PRESSES

MODEL = "fake-vlm"
CUBE = ("raw_kabocha_squash", "boiled_kabocha_squash", "raw_kiri_mochi", "boiled_kiri_mochi")
JOBS = len(CUBE) * PRESSES * len(DEFAULT_CONDITIONS)


@pytest.fixture(autouse=True)
def _no_real_api_key(monkeypatch):
    monkeypatch.delenv("VTZERO_VLM_API_KEY", raising=False)


def settings(released, work, out, url, **kw) -> EvalVLMConfig:
    rec = work / "recordings"
    vlm = VLMConfig(base_url=url, model=MODEL, connect_timeout_s=1.0, total_timeout_s=5.0,
                    max_retries=1, backoff_base_s=0.01, backoff_cap_s=0.02)
    return EvalVLMConfig(vlm=vlm, out=out, unseen=(rec / "cube",), model_dir=released,
                         reference=rec / "reference",
                         beta=work / "run_a" / "beta" / "checkpoint.pt", **kw)


def cache_lines(out) -> list[dict]:
    path = out / ANSWERS_FILE
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_round_robin_order_and_limit(work):
    assert round_robin(["a", "a", "b", "b", "c"], ["b", "a", "c"]) == [2, 0, 4, 3, 1]
    ts = load_test_set(work / "recordings" / "cube", limit=5)
    assert ts.name == "cube" and ts.candidates == CUBE
    assert ts.presses.labels == (*CUBE, CUBE[0])  # every class before any class's second
    assert ts.press_ids[0] == "raw_kabocha_squash/raw_kabocha_squash_000.press.npz"


@pytest.mark.asyncio
async def test_tactile_beats_vision_only_with_the_shipped_prompts(released, work, tmp_path):
    out = tmp_path / "ev"
    async with FakeVLM(model=MODEL, choose=StandIn()) as fake:
        report = await eval_vlm.run(settings(released, work, out, fake.base_url),
                                    progress=False)
    res = report["results"]["cube"]
    acc = {name: r["accuracy"] for name, r in res.items()}
    # The picture shows the pair; without touch the fake answers its first member.
    assert acc["vision_only"] == 0.5
    assert acc["vq_top3"] > acc["vision_only"] and acc["vq_top1"] > acc["vision_only"]
    assert all(r["n"] == len(CUBE) * PRESSES and r["invalid_answer"] == 0
               for r in res.values())

    # One request per question, each with the shipped template rendered by edge.vlm.prompt.
    requests = fake.chat_requests
    records = cache_lines(out)
    assert len(requests) == len(records) == JOBS
    assert len({r["key"] for r in records}) == JOBS
    db = load_model(released).database
    for rec in records:
        template = load_template(rec["mode"])
        assert template.source.endswith(f"models/prompts/{rec['mode']}.txt")
        if rec["condition"] == "vision_only":
            assert rec["description"] == "" and rec["topk"] == []
        else:
            assert len(rec["topk"]) == (1 if rec["condition"] == "vq_top1" else 3)
            if rec["condition"].startswith("vq"):  # the shipped database's sentence
                assert rec["description"] == db.describe(lab for lab, _ in rec["topk"])
        expected = template.render(rec["description"], CUBE)
        assert rec["answer"]["prompt"] == expected
        assert rec["answer"]["request"]["temperature"] == 0
    assert sorted(r.prompt for r in requests) == sorted(r["answer"]["prompt"] for r in records)
    assert sum("By touch" not in r.prompt for r in requests) == len(CUBE) * PRESSES
    assert {r.images[0] for r in requests} == {render(label) for label in CUBE}
    assert all(r.candidates == list(CUBE) for r in requests)

    # Files: Table I in Markdown, confusion matrices as JSON and a picture.
    md = (out / REPORT_MD).read_text()
    assert "| Vision only | 50.0 % (4/8) |" in md
    assert "| Vision + tactile (VQ-VAE, top-3) |" in md and "GPT-4V" in md
    for block in md.split("\n\n"):
        rows = [line for line in block.splitlines() if line.startswith("|")]
        assert len({line.count("|") for line in rows}) <= 1, block
    saved = json.loads((out / REPORT_JSON).read_text())
    conf = saved["results"]["cube"]["vq_top3"]["confusion"]
    assert conf["columns"] == [*CUBE, "invalid_answer"]
    assert [sum(row) for row in conf["matrix"]] == [PRESSES] * len(CUBE)
    assert (out / "confusion_cube.png").stat().st_size > 0
    assert len(saved["presses"]) == len(CUBE) * PRESSES


@pytest.mark.asyncio
async def test_resume_after_a_stop_asks_nothing_twice(released, work, tmp_path):
    out = tmp_path / "ev"
    async with FakeVLM(model=MODEL, choose=StandIn()) as fake:
        cfg = settings(released, work, out, fake.base_url, concurrency=1)
        fake.script(*[Reply()] * 5, Reply.error(400, "refused"))  # 400 is never retried
        with pytest.raises(EvalVLMError, match="run the same command again"):
            await eval_vlm.run(cfg, progress=False)
        assert len(fake.chat_requests) == 6 and len(cache_lines(out)) == 5
        first = await eval_vlm.run(cfg, progress=False)
        assert len(fake.chat_requests) == 6 + JOBS - 5  # only what was not answered
        again = await eval_vlm.run(cfg, progress=False)
        assert len(fake.chat_requests) == 6 + JOBS - 5  # everything cached now
    keys = [r["key"] for r in cache_lines(out)]
    assert len(keys) == len(set(keys)) == JOBS
    assert first == again


@pytest.mark.asyncio
async def test_cancelled_run_keeps_whole_lines_and_continues(released, work, tmp_path):
    out = tmp_path / "ev"
    busy = asyncio.Event()

    def choose(req):
        if len(fake.chat_requests) >= 9:  # 8 sent before, at most 3 of them still open
            busy.set()
        return StandIn()(req)

    async with FakeVLM(model=MODEL, choose=choose, latency_s=0.02) as fake:
        cfg = settings(released, work, out, fake.base_url,
                       conditions=("vision_only", "vq_top3"))
        total = len(CUBE) * PRESSES * 2
        task = asyncio.create_task(eval_vlm.run(cfg, progress=False))
        await asyncio.wait_for(busy.wait(), 30)
        task.cancel()  # Ctrl-C
        with pytest.raises(asyncio.CancelledError):
            await task
        kept = len(cache_lines(out))  # every line parses: none torn
        sent = len(fake.chat_requests)
        assert 1 <= kept < total and sent - kept <= cfg.concurrency
        await eval_vlm.run(cfg, progress=False)
        assert len(fake.chat_requests) - sent == total - kept  # cached ones not asked again
    assert len({r["key"] for r in cache_lines(out)}) == len(cache_lines(out)) == total


@pytest.mark.asyncio
async def test_invalid_answers_are_counted_not_mapped(released, work, tmp_path):
    out = tmp_path / "ev"
    async with FakeVLM(model=MODEL, choose=StandIn()) as fake:
        cfg = settings(released, work, out, fake.base_url, concurrency=1,
                       conditions=("vision_only",))
        # The first question: a non-candidate twice (the answer and the corrective retry).
        fake.script(Reply(content='{"label": "pumpkin"}'), Reply(content="a pumpkin cube"))
        report = await eval_vlm.run(cfg, progress=False)
    r = report["results"]["cube"]["vision_only"]
    assert r["invalid_answer"] == 1 and r["valid"] == r["n"] - 1 == len(CUBE) * PRESSES - 1
    assert r["confusion"]["matrix"][0][-1] == 1  # raw_kabocha_squash's first press
    assert r["correct"] == 3  # raw answers right for the other raw presses
    first = report["presses"][0]
    assert first["answers"]["vision_only"] == {
        "label": None, "status": "invalid_answer", "correct": False, "topk": [],
        "attempts": 2}
    assert "| Vision only | 0 |" not in (out / REPORT_MD).read_text()
    assert len(fake.chat_requests) == len(CUBE) * PRESSES + 1


def test_answer_cache_drops_a_torn_last_line(tmp_path):
    path = tmp_path / "answers.jsonl"
    cache = AnswerCache(path)
    rec = {"key": "a", "answer": {"status": "ok", "label": "x"}}
    cache.append(rec)
    with path.open("ab") as fh:
        fh.write(b'{"key": "b", "answer": {"sta')  # killed mid-write
    again = AnswerCache(path)
    assert list(again.load()) == ["a"]
    again.append({"key": "c", "answer": {"status": "ok", "label": "y"}})
    assert [json.loads(line)["key"] for line in path.read_text().splitlines()] == ["a", "c"]


def png(colour: tuple[int, int, int]) -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (64, 48), colour).save(buf, "PNG")
    return buf.getvalue()


def test_cli_with_key_photos_limit_and_dry_run(released, work, tmp_path, capsys,
                                               monkeypatch):
    from train.cli import main

    rec = work / "recordings"
    photos = tmp_path / "photos"
    (photos / "cube").mkdir(parents=True)
    pictures = {label: png((40 * i, 100, 200)) for i, label in enumerate(CUBE)}
    for label, data in pictures.items():
        (photos / "cube" / f"{label}.png").write_bytes(data)
    key = "sk-test-0123456789"
    monkeypatch.setenv("VTZERO_VLM_API_KEY", key)
    out = tmp_path / "ev"
    with fake_in_thread(model=MODEL, api_key=key, choose=StandIn()) as fake:
        args = ["eval-vlm", "--url", fake.base_url, "--model", MODEL,
                "--model-dir", str(released), "--unseen", str(rec / "cube"),
                "--reference", str(rec / "reference"), "--beta", str(tmp_path / "none.pt"),
                "--images", str(photos), "--out", str(out)]
        assert main([*args, "--dry-run"]) == 0
        dry = capsys.readouterr().out
        assert "beta_top3" not in dry  # no checkpoint: the default set drops it
        assert "Candidates:" in dry and not fake.requests
        assert main([*args, "--limit", "3", "--conditions", "vision_only,vq_top1"]) == 0
        captured = capsys.readouterr()
        assert len(fake.chat_requests) == 6
        assert all(r.headers["Authorization"] == f"Bearer {key}" and r.error is None
                   for r in fake.chat_requests)
        assert {r.images[0] for r in fake.chat_requests} == {pictures[c] for c in CUBE[:3]}
        assert "| Vision + tactile (VQ-VAE, top-1) |" in captured.out
        assert "eval-vlm: 6/6 answers" in captured.err
        assert "0 cached, 6 asked, 0 invalid" in captured.err
        (photos / "cube" / "raw_kiri_mochi.png").unlink()
        assert main([*args, "--conditions", "vision_only"]) == 2  # a photo missing
        assert "no photo of cube/raw_kiri_mochi" in capsys.readouterr().err
        (photos / "raw_kiri_mochi_000.jpg").write_bytes(b"not a picture")  # per press
        assert main([*args, "--conditions", "vision_only"]) == 2
        assert "raw_kiri_mochi_000.jpg: not a usable photo" in capsys.readouterr().err
        assert len(fake.chat_requests) == 6  # refused before asking anything
    for path in out.iterdir():
        assert key not in path.read_bytes().decode("utf-8", "replace"), path


@pytest.mark.asyncio
async def test_a_server_refusing_response_format_is_asked_with_the_robots_fallback(
        released, work, tmp_path):
    """The robot's client, so its fallback: every question answered in free text by a server
    refusing response_format; a question refused for another reason stops the run naming
    the question and the server's reason."""
    out = tmp_path / "ev"
    async with FakeVLM(model=MODEL, choose=StandIn(), structured="none_only") as fake:
        cfg = settings(released, work, out, fake.base_url, concurrency=1,
                       conditions=("vision_only", "vq_top3"))
        report = await eval_vlm.run(cfg, progress=False)
        modes = {r["answer"]["structured_output"] for r in cache_lines(out)}
        refusals = [r for r in fake.chat_requests if r.status == 400]
        assert modes == {"none"} and len(cache_lines(out)) == len(CUBE) * PRESSES * 2
        assert len(refusals) == 2 * 2  # json_schema, json_object: once per prompt mode
        assert report["results"]["cube"]["vq_top3"]["valid"] == len(CUBE) * PRESSES
        fake.script(Reply.error(400, "image too large for this model"))
        with pytest.raises(EvalVLMError) as err:
            await eval_vlm.run(settings(released, work, tmp_path / "ev2", fake.base_url,
                                        concurrency=1, conditions=("vision_only",)),
                               progress=False)
    print(err.value)
    assert str(err.value).startswith(
        "stopped: cube/raw_kabocha_squash/raw_kabocha_squash_000.press.npz (vision_only): ")
    assert "HTTP 400" in str(err.value) and "image too large for this model" in str(err.value)


def test_origin_null_or_absent_reads_as_the_emulated_robot(tmp_path):
    for raw in ({}, {"origin": None}):
        facts = model_facts(raw)
        assert facts["origin"]["kind"] == "emulated" and not facts["built"]
    robot = {"kind": "robot", "recorder": "lab", "robot": "arm-3", "sensor": None}
    assert model_facts({"origin": robot}) == {"decoder": None, "origin": robot,
                                              "built": True, "data": None, "unseen": []}
    (tmp_path / "dataset.json").write_text(json.dumps(
        {"classes": [], "recorder": "the simulated recorder", "origin": None}))
    origin = reference_origin(tmp_path)
    assert origin["kind"] == "emulated" and origin["recorder"] == "the simulated recorder"
    assert "emulated robot" in describe_origin(origin)
