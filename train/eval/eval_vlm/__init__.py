"""``vt-train eval-vlm``: the paper's Table I protocol against any OpenAI-compatible VLM.

For every press of each unseen test set (FoodReplica: 22 classes, Cube: 4) the VLM is asked
once per condition to name the object among that set's labels, exactly as the robot asks it:
the offset-0 input through the shipped encoder and reference database
(:func:`edge.core.model.load_model`), the description of the nearest distinct classes, the
shipped prompt templates (:mod:`edge.vlm.prompt`, ``models/prompts``) and the robot's own client
(:class:`edge.vlm.client.OpenAIVLM`: data-URL image, temperature 0, seed, ``[vlm]
structured_output`` with the robot's fallback when a server refuses it, answer checked
against the candidates with one corrective retry, transport retries with backoff). The
picture is :func:`edge.sim.camera.render` of the press's label (a real food and its replica
look the same), or a photo from a user's directory for real data.

Conditions (``CONDITIONS``): ``vision_only`` (the vision_only template: no tactile
sentence), ``vq_top3`` (the proposed method), ``vq_top1`` (only the nearest class's
description), ``beta_top3`` (the beta-VAE's embeddings and its own reference database, built
from the reference recordings: every offset of every press, like the shipped one), and, not
in the default set, ``vq_zeros_top3`` (the VQ-VAE with the zero-input decoder, from its
checkpoint, the same way), ``vq_top3_adjectives`` (the method with the references described
in hand-written tactile adjectives, :mod:`train.eval.ablation`), ``vq_top3_weak`` (the
method, its touch sentence saying the match is weak where the daemon's familiarity flags the
press unfamiliar) and ``tactile_only``.

Every answer is appended to ``answers.jsonl`` in the output directory as soon as it arrives
(one ``write`` of one line, ``O_APPEND``, fsync), keyed by condition, dataset, press, VLM
model and the sha256 of the rendered prompt and of the image: a run that is interrupted (or
stopped by an unreachable server) continues where it stopped and never asks a cached
question again; a changed template, description or picture is a new question. Jobs run in a
fixed order (round-robin over classes, so ``--limit`` keeps every class in play), at most
``concurrency`` requests in flight.

Outputs: ``eval_vlm.json`` (accuracy, invalid answers and confusion matrix per dataset and
condition, every press's answers), ``eval_vlm.md`` (a table like the paper's Table I),
``confusion_<dataset>.png``. An ``invalid_answer`` (not a candidate, even after the
corrective retry) counts as wrong and has its own column: it is never mapped to a label.

The run, in order (:func:`run`): :mod:`.plan` loads the model (:mod:`.tactile`) and the test
sets (:mod:`.sets`), takes each press's picture (:mod:`.images`) and renders every question
under the conditions of :mod:`.config`; :mod:`.ask` asks what :mod:`.cache` does not hold;
:mod:`.report` writes the files. :mod:`.paper` and :mod:`.provenance` name the sets, presses
and models in this report and in Table I's and Fig. 6's.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping
from typing import Any, TextIO

from edge.vlm.client import VLMClient
from train.eval.eval_vlm.ask import EvalProgress, ask_all
from train.eval.eval_vlm.cache import ANSWERS_FILE, AnswerCache
from train.eval.eval_vlm.config import EvalVLMConfig
from train.eval.eval_vlm.plan import prepare
from train.eval.eval_vlm.report import write_report

log = logging.getLogger(__name__)


async def run(cfg: EvalVLMConfig, *, progress: bool = True, stream: TextIO | None = None,
              clients: Mapping[str, VLMClient] | None = None) -> dict[str, Any]:
    """Prepare (off the loop), ask what is not cached, write the report."""
    plan = await asyncio.to_thread(prepare, cfg)
    cache = AnswerCache(cfg.out / ANSWERS_FILE)
    await asyncio.to_thread(cache.load)
    keys = {job.key for job in plan.jobs}
    cached = len(keys & set(cache.records))
    log.info("%d questions (%d sets x %d conditions); %d already answered in %s",
             len(keys), len(plan.sets), len(plan.conditions), cached, cache.path)
    bar = EvalProgress(len(keys), cached, stream, enabled=progress)
    await ask_all(plan, cache, clients=clients, progress=bar)
    return await asyncio.to_thread(write_report, plan, cache.records)
