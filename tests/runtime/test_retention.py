"""Retention on the running daemon: with ``[runtime] store_max_mb`` just above the store's
size, more recognitions keep it under the bound; the oldest finished episodes go, pending ones
never, and /metrics counts what went."""

from __future__ import annotations

from dataclasses import replace

import pytest

from edge.sim.fake_vlm import FakeVLM, Reply
from tests.support.daemon import (
    FOOD,
    LOADED_HOST_ERRORS,
    LOADED_HOST_TRIES,
    QUICK_OBJECT,
    fast_config,
    sim_daemon,
    store_consistent,
)

pytestmark = pytest.mark.asyncio

MORE = 20


async def test_store_max_mb_keeps_the_store_under_it_oldest_finished_first(tmp_path):
    async with FakeVLM(choose=lambda req: QUICK_OBJECT) as fake:
        cfg = fast_config(fake.base_url)
        # A pending episode's next question far away: it stays pending through the test.
        cfg = replace(cfg, runtime=replace(cfg.runtime, vlm_retry_base_s=600.0,
                                           vlm_retry_max_s=600.0, keep_free_mb=0.0))
        fake.script(*[Reply.error(503, "overloaded")] * 2)
        async with sim_daemon(tmp_path, cfg=cfg) as (_, d):
            first = []
            for want in ("pending", "pending", "done", "done"):
                status, ep = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
                assert status == 200 and ep["status"] == want, ep
                first.append(ep["id"])
            await d.wait_idle()
            size = d.store.size()
        bound_mb = (size + 50_000) / 1e6  # just above the store's size
        print(f"store {size / 1e6:.3f} MB after {len(first)} episodes; store_max_mb = "
              f"{bound_mb:.3f}")

        cfg = replace(cfg, runtime=replace(cfg.runtime, store_max_mb=bound_mb))
        async with sim_daemon(tmp_path, cfg=cfg) as (_, d):
            more, done, retries = [], 0, 0
            while done < MORE:
                status, ep = await d.post("/v1/recognize", {"candidates": FOOD, "wait": True})
                more.append(ep["id"])  # a failed episode is a finished one: it counts too
                assert d.store.size() <= bound_mb * 1e6
                if (ep["status"] == "failed" and retries < LOADED_HOST_TRIES
                        and any(e in (ep["error"] or "") for e in LOADED_HOST_ERRORS)):
                    retries += 1  # a press a loaded host failed: pressed again
                    print(f"  a press failed on a loaded host: {ep['error']}")
                    continue
                assert status == 200 and ep["status"] == "done", (ep["status"], ep["error"])
                done += 1
            async with d.http.get(d.url + "/metrics") as resp:
                metrics = await resp.text()
            removed = d.store.removed_episodes
            print(f"{len(more)} more: store {d.store.size() / 1e6:.3f} MB, {removed} episodes "
                  f"removed ({d.store.removed_bytes / 1e6:.2f} MB)")

    kept = [e["id"] for e in store_consistent(d.store.root)]
    # Pending ones never go; the oldest finished go first; the newest stay.
    assert kept[:2] == first[:2]
    assert first[2] not in kept and first[3] not in kept
    gone = [i for i in more if i not in kept]
    assert gone == more[:len(gone)] and kept[2:] == more[len(gone):]
    assert removed == 2 + len(gone) > 2
    assert f'vtzero_store_removed_total{{kind="episode"}} {removed}' in metrics
