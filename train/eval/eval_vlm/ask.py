"""Asking: the jobs not cached, ``concurrency`` at a time through the robot's own client,
each answer cached as it arrives, with progress on stderr."""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Mapping
from typing import TextIO

import aiohttp

from edge.core.errors import EdgeError, EvalVLMError
from edge.core.progress import PLAIN_EVERY_S
from edge.core.progress import Progress as Bar
from edge.vlm.client import OpenAIVLM, VLMAnswer, VLMClient
from train.eval.eval_vlm.cache import AnswerCache
from train.eval.eval_vlm.config import INVALID
from train.eval.eval_vlm.plan import Plan


class EvalProgress:
    """Progress on stderr (:mod:`edge.core.progress`): a tqdm bar on a terminal, else a
    whole line every few seconds."""

    def __init__(self, total: int, cached: int, stream: TextIO | None = None,
                 enabled: bool = True, every_s: float = PLAIN_EVERY_S) -> None:
        self.total, self.cached = total, cached
        self.asked = self.invalid = 0
        self.started = time.monotonic()
        self.bar = Bar("eval-vlm", total, "answers", stream=stream, every_s=every_s,
                       enabled=enabled, initial=cached)

    def note(self) -> str:
        done = self.cached + self.asked
        text = f"{self.cached} cached, {self.asked} asked, {self.invalid} invalid"
        if self.asked:
            rate = (time.monotonic() - self.started) / self.asked
            text += f", {rate:.2f} s per answer, ~{rate * (self.total - done) / 60:.1f} min left"
        return text

    def update(self, answer: VLMAnswer | None = None, final: bool = False) -> None:
        if answer is not None:
            self.asked += 1
            self.invalid += answer.status == INVALID
            self.bar.update(1, self.note())
        if final:
            self.bar.close(self.note())


async def ask_all(plan: Plan, cache: AnswerCache, *,
                  clients: Mapping[str, VLMClient] | None = None,
                  progress: EvalProgress | None = None) -> int:
    """Ask every job not in ``cache`` (in plan order, ``concurrency`` at a time); returns
    the number asked. The first failure (server unreachable after retries, a refused
    request) stops the run; the answers already cached stay for the next run."""
    cfg = plan.config
    cached = cache.records or cache.load()
    # One question per key: two jobs with the same key (the same prompt and photo) share
    # their answer at temperature 0.
    todo = list({job.key: job for job in plan.jobs if job.key not in cached}.values())
    unique = len({job.key for job in plan.jobs})
    progress = progress or EvalProgress(unique, unique - len(todo), enabled=False)
    if not todo:
        progress.update(final=True)
        return 0
    session: aiohttp.ClientSession | None = None
    owned: list[VLMClient] = []
    if clients is None:
        session = aiohttp.ClientSession(
            connector=aiohttp.TCPConnector(limit=cfg.concurrency), trust_env=False)
        clients = {}
        for mode, template in plan.templates.items():
            client = OpenAIVLM(dataclasses.replace(cfg.vlm, mode=mode), template=template,
                               session=session)
            clients[mode] = client
            owned.append(client)
    pending = iter(todo)
    asked = 0

    async def worker() -> None:
        nonlocal asked
        for job in pending:  # shared: each worker takes the next job in plan order
            try:
                answer = await clients[job.condition.mode].ask(
                    job.image, job.description, job.candidates)
            except (EdgeError, ValueError) as exc:
                raise EvalVLMError(
                    f"{job.dataset}/{job.press} ({job.condition.name}): {exc}") from exc
            if answer.prompt != job.prompt:  # the client renders the same template
                raise EvalVLMError(f"{job.key}: the client rendered another prompt")
            write = asyncio.ensure_future(asyncio.to_thread(cache.append, job.record(answer)))
            try:
                await asyncio.shield(write)
            except asyncio.CancelledError:
                await write  # a cancelled run still finishes the line it is writing
                raise
            asked += 1
            progress.update(answer)

    try:
        async with asyncio.TaskGroup() as tg:
            for i in range(min(cfg.concurrency, len(todo))):
                tg.create_task(worker(), name=f"eval-vlm-worker-{i}")
    except BaseExceptionGroup as group:
        first = _first_error(group)
        if isinstance(first, EvalVLMError):
            keys = {j.key for j in plan.jobs}
            missing = len(keys - set(cache.records))
            raise EvalVLMError(f"stopped: {first}; {missing} of {len(keys)} answers "
                               f"still missing (cached in {cache.path}: run the same "
                               "command again to continue)") from first.__cause__
        raise
    finally:
        for client in owned:
            await client.close()
        if session is not None:
            await session.close()
    progress.update(final=True)
    return asked


def _first_error(group: BaseExceptionGroup) -> BaseException:
    for exc in group.exceptions:
        if isinstance(exc, BaseExceptionGroup):
            return _first_error(exc)
        return exc
    return group
