"""The paper's experiments as commands: Table I (two models, the paper's numbers beside
ours) and Fig. 6 (reference-set size), against the simulated VLM and an endpoint; cached
and resumable. Tiny: 2 presses per class, Cube only, 1-epoch trainings."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest

from edge.core.config import VLMConfig
from edge.core.errors import EvalVLMError
from edge.core.model import Familiarity, load_model
from edge.sim.standin_vlm import StandIn
from edge.vlm.prompt import WEAK_MATCH
from tests.support.vlm_thread import fake_in_thread
from train.cli import main
from train.eval import fig6, table1
from train.eval.eval_vlm.config import EvalVLMConfig
from train.eval.eval_vlm.plan import prepare
from train.learn.data import Splits

from .conftest import PRESSES

CUBE = ("raw_kabocha_squash", "boiled_kabocha_squash", "raw_kiri_mochi", "boiled_kiri_mochi")


def lines(path: Path) -> int:
    return len(path.read_text().splitlines()) if path.exists() else 0


def table_config(released, work, tmp_path, **kw) -> table1.Table1Config:
    rec = work / "recordings"
    return table1.Table1Config(
        first=VLMConfig(), out=tmp_path / "out", work=tmp_path / "work", unseen=(rec / "cube",),
        model_dir=released, reference=rec / "reference",
        beta=work / "run_a" / "beta" / "checkpoint.pt",
        zeros=work / "run_a" / "vq_zeros" / "checkpoint.pt", **kw)


@pytest.mark.asyncio
async def test_table1_against_the_simulated_vlm(released, work, tmp_path):
    cfg = table_config(released, work, tmp_path)
    report = await table1.run(cfg, progress=False)
    models = [m["model"] for m in report["models"]]
    assert models == ["simulated-vlm", "simulated-vlm-vision-led"]
    assert [m["beside"] for m in report["models"]] == ["GPT-4V", "LLaVA"]
    rows = {(m["model"], r["condition"]): r for m in report["models"] for r in m["rows"]}
    assert {c for _, c in rows} == {"vision_only", "vq_top3", "vq_top1", "beta_top3",
                                    "vq_zeros_top3", "vq_top3_adjectives", "vq_top3_weak"}
    for row in rows.values():
        cube = row["sets"]["cube"]
        assert cube["n"] == len(CUBE) * PRESSES and cube["invalid_answer"] == 0
        assert sum(map(sum, cube["confusion"]["matrix"])) == cube["n"]
    # Sight alone answers the first of each look-alike pair: right half the time.
    assert rows[("simulated-vlm", "vision_only")]["sets"]["cube"]["accuracy"] == 0.5
    # The paper's numbers beside ours: GPT-4V's four rows, LLaVA's two.
    assert rows[("simulated-vlm", "vq_top3")]["sets"]["cube"]["paper"] == 65.0
    assert rows[("simulated-vlm-vision-led", "vision_only")]["sets"]["cube"]["paper"] == 25.0
    assert rows[("simulated-vlm-vision-led", "vq_top1")]["sets"]["cube"]["paper"] is None
    md = (cfg.out / table1.REPORT_MD).read_text()
    assert md.startswith("# Table I (simulated VLM)") and "not a real model" in md
    assert "| `simulated-vlm` | Vision + tactile (VQ-VAE, top-3) |" in md
    assert "65.0 % (GPT-4V)" in md and "25.0 % (LLaVA)" in md
    for block in md.split("\n\n"):  # every Markdown table has as many cells as its header
        rows_md = [line for line in block.splitlines() if line.startswith("|")]
        assert len({line.count("|") for line in rows_md}) <= 1, block
    for model in models:
        assert (cfg.out / f"confusion_{model}_cube.png").stat().st_size > 0
    saved = json.loads((cfg.out / table1.REPORT_JSON).read_text())
    assert saved["simulated_vlm"] is True and saved["tactile_model"]["decoder"] == "teacher"
    # Cached: a second run asks nothing and writes the same table.
    caches = sorted((cfg.work).glob("*/answers.jsonl"))
    assert len(caches) == 2 and all("@" in p.parent.name for p in caches)
    before = [lines(p) for p in caches]
    again = await table1.run(cfg, progress=False)
    assert [lines(p) for p in caches] == before
    assert again["models"] == report["models"]


def test_the_weak_match_row_says_so_exactly_where_the_daemon_flags_the_press(released, work,
                                                                            tmp_path, capsys):
    # Every question of the row is the paper's, but for the presses the daemon's familiarity
    # flags unfamiliar (at the default 95th percentile), whose touch sentence says the match
    # is weak.
    cfg = EvalVLMConfig(vlm=VLMConfig(), out=tmp_path / "o", model_dir=released,
                        unseen=(work / "recordings" / "cube",),
                        conditions=("vq_top3", "vq_top3_weak"))
    plan = prepare(cfg, endpoint=False)
    model = load_model(released)
    familiarity = Familiarity(model.database)
    x = plan.sets[0].presses.inputs(0)
    flagged = [familiarity.percentile(z, f) >= 95
               for z, f in zip(np.asarray(model.encode(x)[0]), x.mean(axis=1), strict=True)]
    jobs = {(j.press, j.condition.name): j for j in plan.jobs}
    said = []
    for press in plan.sets[0].press_ids:
        paper, weak = jobs[(press, "vq_top3")], jobs[(press, "vq_top3_weak")]
        assert WEAK_MATCH not in paper.prompt and weak.topk == paper.topk
        said.append(WEAK_MATCH in weak.prompt)
        names = f"similar to {paper.description}."
        assert weak.prompt == (paper.prompt.replace(names, f"similar to {paper.description}, "
                                                           f"{WEAK_MATCH}.")
                               if said[-1] else paper.prompt)
    print(f"weak match said for {sum(said)} of {len(said)} presses")
    assert said == flagged
    # Asked for alone, with its twin; an unknown row is refused naming the known ones.
    only = table_config(released, work, tmp_path, rows=("vq_top3", "vq_top3_weak"))
    assert only.conditions() == ("vq_top3", "vq_top3_weak")
    with pytest.raises(EvalVLMError, match=r"unknown Table I row.*vq_top3_weak"):
        table1.validate(table_config(released, work, tmp_path, rows=("vq_top4",)))
    # The command line's --rows reaches the same check, before anything is asked.
    assert main(["table1", "--rows", "vq_top3", "vq_top4", "--out", str(tmp_path / "t1"),
                 "--work", str(tmp_path / "t1w")]) == 2
    assert "unknown Table I row(s) vq_top4; known:" in capsys.readouterr().err
    assert not (tmp_path / "t1").exists()


def test_table1_against_an_endpoint_with_two_models(released, work, tmp_path, capsys):
    from train.cli import main

    with fake_in_thread(model=("big-vlm", "small-vlm"), choose=StandIn()) as fake:
        args = ["table1", "--url", fake.base_url, "--model", "big-vlm", "--second-model",
                "small-vlm", "--model-dir", str(released), "--unseen",
                str(work / "recordings" / "cube"), "--reference",
                str(work / "recordings" / "reference"), "--beta", str(tmp_path / "none.pt"),
                "--no-extras", "--work", str(tmp_path / "w"), "--out", str(tmp_path / "o"),
                "-q"]
        assert main(args) == 0
        asked = {r.body["model"] for r in fake.chat_requests}
        n = len(fake.chat_requests)
    out = capsys.readouterr().out
    assert asked == {"big-vlm", "small-vlm"}
    # 3 conditions (no beta checkpoint: skipped) x 8 presses x 2 models.
    assert n == 3 * len(CUBE) * PRESSES * 2
    assert "# Table I\n" in out and "simulated VLM" not in out
    assert "| `small-vlm` | Vision only |" in out
    assert (tmp_path / "o" / "confusion_big-vlm_cube.png").exists()


def test_fig6_draws_trains_caches_and_resumes(released, work, tmp_path):
    rec = work / "recordings"
    cfg = fig6.Fig6Config(vlm=VLMConfig(), out=tmp_path / "out", work=tmp_path / "work",
                          reference=rec / "reference", unseen=(rec / "cube",),
                          model_dir=released, sizes=(0, 3, 27), draws=2, max_epochs=1,
                          patience=1)
    report = asyncio.run(fig6.run(cfg, progress=False))
    sizes = {row["size"]: row["sets"]["cube"] for row in report["sizes"]}
    assert set(sizes) == {0, 3, 27}
    assert sizes[0]["values"] == [0.5, 0.5] and sizes[0]["std"] == 0.0  # vision only
    assert sizes[0]["paper"] == 50.0 and sizes[27]["paper"] == 65.0
    for row in sizes.values():
        assert len(row["values"]) == 2 and all(0.0 <= v <= 1.0 for v in row["values"])
    runs = {(r["size"], r["draw"]): r for r in report["runs"]}
    # Draws: seeded, different for a small size, all 27 training classes at 27.
    assert runs[(3, 0)]["classes"] != runs[(3, 1)]["classes"]
    assert len(runs[(3, 0)]["classes"]) == 3
    splits = Splits.of_dataset(rec / "reference")
    assert runs[(3, 0)]["classes"] == list(fig6.draw_classes(splits.train, 3, 0, 0))
    assert len(runs[(27, 1)]["classes"]) == 27
    assert report["timings"]["trainings_run"] == 4
    # The database left out the validation classes: no answer's top-k names one.
    val = splits.val
    cache = next((cfg.work).glob("*/answers.jsonl"))
    records = [json.loads(line) for line in cache.read_text().splitlines()]
    assert records and not any(lab in val for r in records for lab, _ in r["topk"])
    assert {r["condition"] for r in records} == {"vision_only", "vq_top3"}
    md = (cfg.out / fig6.REPORT_MD).read_text()
    assert "(simulated VLM)" in md and "| 0 | 50.0 ± 0.0 |" in md
    # The header names the encoder's shape, not its decoder alone.
    assert "z of 16 numbers, metric term weight 1, decoder `teacher`" in md
    assert (cfg.out / fig6.REPORT_PNG).stat().st_size > 0
    # Resumed: nothing trained or asked again, the same figures.
    n_answers = lines(cache)
    again = asyncio.run(fig6.run(cfg, progress=False))
    assert again["timings"]["trainings_run"] == 0 and lines(cache) == n_answers
    assert again["timings"]["trainings"] == 4  # their training times kept from the cache
    assert again["sizes"] == report["sizes"]
    # Another epoch budget is another training: only those draws train again.
    more = fig6.Fig6Config(**{**cfg.__dict__, "max_epochs": 2, "sizes": (3,)})
    assert asyncio.run(fig6.run(more, progress=False))["timings"]["trainings_run"] == 2
