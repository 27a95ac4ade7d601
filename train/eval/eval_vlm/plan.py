"""Everything decided before the first question: the model and sets loaded, retrieval done,
every prompt rendered into a job keyed by what makes it a new question."""

from __future__ import annotations

import functools
import hashlib
import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from edge.core.config import RuntimeConfig
from edge.core.errors import EvalVLMError
from edge.core.model import ReferenceDatabase, load_model
from edge.vlm.client import VLMAnswer
from edge.vlm.prompt import PromptTemplate, load_template
from train.eval.eval_vlm.cache import CACHE_SCHEMA
from train.eval.eval_vlm.config import CHECKPOINT_VARIANTS, CONDITIONS, Condition, EvalVLMConfig
from train.eval.eval_vlm.images import ImageSource
from train.eval.eval_vlm.sets import UnseenSet, load_sets
from train.eval.eval_vlm.tactile import (
    Tactile,
    checkpoint_tactile,
    describe,
    unfamiliar,
    vq_tactile,
)

log = logging.getLogger(__name__)


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True, eq=False)
class Job:
    """One question: a press under a condition."""

    condition: Condition
    dataset: str
    press: str
    label: str
    candidates: tuple[str, ...]
    topk: tuple[tuple[str, float], ...]
    description: str
    prompt: str
    image: bytes | None
    image_sha256: str | None
    model: str

    @functools.cached_property
    def prompt_sha256(self) -> str:
        return sha256_hex(self.prompt.encode("utf-8"))

    @functools.cached_property
    def key(self) -> str:
        image = (self.image_sha256 or "none")[:16]
        return (f"{self.condition.name}|{self.dataset}|{self.press}|{self.model}|"
                f"prompt:{self.prompt_sha256[:16]}|image:{image}")

    def record(self, answer: VLMAnswer) -> dict[str, Any]:
        return {
            "schema": CACHE_SCHEMA, "key": self.key, "condition": self.condition.name,
            "dataset": self.dataset, "press": self.press, "label": self.label,
            "model": self.model, "mode": self.condition.mode,
            "prompt_sha256": self.prompt_sha256, "image_sha256": self.image_sha256,
            "topk": [[lab, round(d, 6)] for lab, d in self.topk],
            "description": self.description,
            "answer": answer.to_dict(),
        }


@dataclass(frozen=True, eq=False)
class Plan:
    """Everything decided before the first question: the sets, templates and jobs."""

    config: EvalVLMConfig
    sets: tuple[UnseenSet, ...]
    conditions: tuple[Condition, ...]
    templates: dict[str, PromptTemplate]
    jobs: tuple[Job, ...]
    images: str


def prepare(cfg: EvalVLMConfig, endpoint: bool = True) -> Plan:
    """Load the model and test sets, retrieve, render every prompt: no network yet."""
    cfg.validate(endpoint)
    conditions = tuple(CONDITIONS[name] for name in cfg.conditions)
    model = load_model(cfg.model_dir)
    sets = load_sets(cfg.unseen, cfg.limit, model.window)
    tactile: dict[str, Tactile] = {}
    if any(c.variant == "vq" for c in conditions):
        tactile["vq"] = vq_tactile(model)
    checkpoints = {"beta": cfg.beta, "vq_zeros": cfg.zeros}
    for variant in CHECKPOINT_VARIANTS:
        if any(c.variant == variant for c in conditions):
            path = checkpoints[variant]
            assert path is not None and cfg.reference is not None
            tactile[variant] = checkpoint_tactile(variant, path, cfg.reference, model.window)
            _check_same_references(model.database, tactile[variant].database)
    templates = {c.mode: load_template(c.mode, cfg.vlm.prompt_dir) for c in conditions}
    images = ImageSource(cfg.images, cfg.vlm)
    jobs = build_jobs(sets, [(c, tactile.get(c.variant or "")) for c in conditions],
                      templates, images, cfg.vlm.model)
    return Plan(cfg, sets, conditions, templates, tuple(jobs), images.name)


def build_jobs(sets: Sequence[UnseenSet],
               conditions: Sequence[tuple[Condition, Tactile | None]],
               templates: Mapping[str, PromptTemplate], images: ImageSource,
               model: str) -> list[Job]:
    """One question per press of every set and (condition, tactile source), in plan order
    (set, press, condition)."""
    with_image = any(templates[c.mode].uses_image for c, _ in conditions)
    jobs: list[Job] = []
    for ts in sets:
        x = ts.presses.inputs(0)  # the one input the robot computes
        retrieved: dict[int, list[list[tuple[str, float]]]] = {}
        # The daemon's unfamiliar flag of each press, where a condition says a match is weak.
        flagged: dict[int, list[bool]] = {}
        for cond, source in conditions:
            if cond.variant is not None:
                if source is None:
                    raise EvalVLMError(f"{cond.name}: no tactile model given")
                if id(source) not in retrieved:
                    k = max(c.k for c, s in conditions if s is source)
                    retrieved[id(source)] = source.topk(x, k)
                if cond.descriptions == "weak" and id(source) not in flagged:
                    flagged[id(source)] = unfamiliar(source, x,
                                                     RuntimeConfig.unfamiliar_percentile)
        for i, (press, label) in enumerate(zip(ts.press_ids, ts.presses.labels, strict=True)):
            image = images.get(ts.name, press, label, ts.directory / press) \
                if with_image else None
            for cond, source in conditions:
                template = templates[cond.mode]
                topk: tuple[tuple[str, float], ...] = ()
                description = ""
                if cond.variant is not None:
                    assert source is not None
                    topk = tuple(retrieved[id(source)][i][:cond.k])
                    weak = id(source) in flagged and flagged[id(source)][i]
                    description = describe(cond, source.database, [lab for lab, _ in topk],
                                           weak)
                sent = image if template.uses_image else None
                assert not template.uses_image or sent is not None
                jobs.append(Job(
                    condition=cond, dataset=ts.name, press=press, label=label,
                    candidates=ts.candidates, topk=topk, description=description,
                    prompt=template.render(description, ts.candidates), image=sent,
                    image_sha256=sha256_hex(sent) if sent is not None else None,
                    model=model))
    return jobs


def _check_same_references(vq: ReferenceDatabase, other: ReferenceDatabase) -> None:
    if sorted(vq.source.tolist()) != sorted(other.source.tolist()) or vq.labels != other.labels:
        log.warning("the database built from --reference holds other presses or classes "
                    "than the shipped VQ database: the comparison with the shipped model is "
                    "not like for like")


def describe_plan(plan: Plan, records: Iterable[str] = ()) -> str:
    """A dry run: what would be asked, and the first prompt of each condition."""
    keys = set(records)
    lines = [f"{len(plan.jobs)} questions, {sum(j.key in keys for j in plan.jobs)} cached; "
             f"images: {plan.images}"]
    for ts in plan.sets:
        lines.append(f"  {ts.name}: {len(ts.press_ids)} presses, {len(ts.candidates)} "
                     "candidates")
    for cond in plan.conditions:
        job = next(j for j in plan.jobs if j.condition is cond)
        lines += [f"--- {cond.name} ({cond.title}), e.g. {job.dataset}/{job.press}:",
                  job.prompt]
    return "\n".join(lines)
