"""The label phase: how soon a person at the robot gets the label.

The daemon as ``vt-edge run`` assembles it, in this process, against the emulated robot and
the bench's fake VLM (own processes) answering after ``Settings.vlm_latency_s``, with the
arm's moves as long as on the real arm (``runtime.move_time_s`` of configs/robot.toml). For
each press: when its crop window was complete (the stop + its last sample's time), when its
VLM request arrived at the fake VLM, and when the label's ``result`` event came.
``python -m edge.bench.label [--presses N]`` prints the figures as JSON (to measure a
checkout on its own).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import time
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from edge.bench.controllers import BenchController
from edge.bench.figures import figure, stats, target
from edge.bench.load import Helper
from edge.bench.results import PhaseResult, progress
from edge.bench.settings import CUBE, MODELS, OBJECTS, ROOT, SIM_CONFIG, Settings
from edge.runtime.domain import EpisodeFinished, Label, PressState, VLMRefused

ROBOT_CONFIG = ROOT / "configs" / "robot.toml"
LABEL_TIMEOUT_S = 60.0
READY_TIMEOUT_S = 30.0
# Targets (issue: ask while the arm returns): the request leaves this soon after the window.
AFTER_WINDOW_P50_MS = 30.0
AFTER_WINDOW_P99_MS = 60.0


def robot_move_time_s() -> float:
    with ROBOT_CONFIG.open("rb") as f:
        return float(tomllib.load(f)["runtime"]["move_time_s"])


async def _presses(robot: dict[str, Any], vlm: dict[str, Any], state: Path, presses: int,
                   move_time_s: float, vlm_latency_s: float, warmup: bool
                   ) -> list[dict[str, float]]:
    import aiohttp

    from edge.app import assemble, running
    from edge.core.config import load_config

    cfg = load_config(SIM_CONFIG)
    cfg = replace(
        cfg, sensor=replace(cfg.sensor, url=robot["xela_url"]),
        bus=replace(cfg.bus, port=robot["dxl_port"]),
        camera=replace(cfg.camera, kind="http", url=f"{robot['control_url']}/camera.jpg"),
        runtime=replace(cfg.runtime, models_dir=str(MODELS), state_dir=str(state),
                        move_time_s=move_time_s),
        api=replace(cfg.api, port=0),
        vlm=replace(cfg.vlm, base_url=vlm["base_url"], model="fake-vlm", max_retries=0,
                    total_timeout_s=60.0))
    rows: list[dict[str, float]] = []
    async with assemble(cfg, controller_factory=BenchController) as daemon, \
            running(daemon, READY_TIMEOUT_S):
        runtime = daemon.runtime
        ctl = runtime.press
        assert isinstance(ctl, BenchController)
        api = f"http://127.0.0.1:{daemon.api.port}"
        last_s = ctl.window.last_sample_s
        async with aiohttp.ClientSession() as http:
            # One press more, first and not counted: it loads the encoder.
            for i in range(-1 if warmup else 0, presses):
                async with http.post(f"{robot['control_url']}/object",
                                     json={"name": OBJECTS[i % len(OBJECTS)]}) as r:
                    r.raise_for_status()
                marker = f"label_{i + 1:03d}"
                with runtime.subscribe() as events:
                    t_trigger = time.monotonic()
                    async with http.post(f"{api}/v1/recognize",
                                         json={"candidates": [*CUBE, marker]}) as r:
                        ep = await r.json()
                        if r.status != 202:
                            raise RuntimeError(f"recognize answered {r.status}: {ep}")
                    t_label = None
                    async with asyncio.timeout(LABEL_TIMEOUT_S):
                        async for event in events:
                            # The label, or the episode's end without one (a failed
                            # press: said below, and the next press goes on).
                            if (isinstance(event, Label | VLMRefused | EpisodeFinished)
                                    and event.episode.id == ep["id"]):
                                if not isinstance(event, EpisodeFinished):
                                    t_label = time.monotonic()
                                break
                outcome = await asyncio.wait_for(ctl.outcomes.get(), LABEL_TIMEOUT_S)
                async with http.get(f"{vlm['bench_url']}/received") as r:
                    arrivals = await r.json()
                t_vlm = next((a["t"] for a in arrivals
                              if a["candidates"] and a["candidates"][-1] == marker), None)
                if outcome.t_stop is None or t_vlm is None or t_label is None:
                    progress(f"label press {i + 1}: {outcome.result}: {outcome.message}")
                    continue
                t_window = outcome.t_stop + last_s
                # The frame that completed the window: the first received at or past it
                # (the recording reaches past it by its margin).
                recv = outcome.window.recv_time
                t_complete = float(recv[np.searchsorted(recv, t_window)])
                states = dict(outcome.states)
                # What the label waited for, from the stop: the VLM's answer (its request's
                # arrival plus the fake's fixed latency) or the arm back above the object
                # (the press enters idle once it is).
                row = {"label_after_window_ms": 1e3 * (t_vlm - t_window),
                       "frame_wait_ms": 1e3 * (t_complete - t_window),
                       "trigger_to_label_s": t_label - t_trigger,
                       "pre_press_ms": 1e3 * (states[PressState.ABOVE] - t_trigger),
                       "answer_after_stop_s": t_vlm + vlm_latency_s - outcome.t_stop,
                       "arm_back_after_stop_s": states[PressState.IDLE] - outcome.t_stop,
                       "label_after_stop_s": t_label - outcome.t_stop}
                progress(f"label press {i + 1}/{presses}: request "
                         f"{row['label_after_window_ms']:.1f} ms after the window (its "
                         f"last frame {row['frame_wait_ms']:.1f} ms after it), "
                         f"label {row['trigger_to_label_s']:.2f} s after the trigger; after "
                         f"the stop: answer {row['answer_after_stop_s']:.2f} s, arm back "
                         f"{row['arm_back_after_stop_s']:.2f} s, label "
                         f"{row['label_after_stop_s']:.2f} s"
                         + (" (warm-up, not counted)" if i < 0 else ""))
                if i >= 0:
                    rows.append(row)
                await asyncio.sleep(0.2)  # the arm settles; the lock is free
    return rows


def measure(s: Settings, tmp: Path, presses: int) -> tuple[list[dict[str, float]], float]:
    from edge.app import new_event_loop

    move_time_s = robot_move_time_s()
    progress(f"label: {presses} presses, arm moves {move_time_s} s (configs/robot.toml), "
             f"fake VLM answering after {s.vlm_latency_s} s")
    robot = Helper("robot", "--config", str(SIM_CONFIG), "--object", OBJECTS[0])
    vlm = None
    quiet = [logging.getLogger(n) for n in ("edge", "aiohttp")]
    levels = [lg.level for lg in quiet]
    try:
        vlm = Helper("vlm", "--latency-s", str(s.vlm_latency_s))
        for lg in quiet:
            lg.setLevel(logging.WARNING)
        with asyncio.Runner(loop_factory=new_event_loop) as runner:
            rows = runner.run(_presses(robot.info, vlm.info, tmp / "label-state", presses,
                                       move_time_s, s.vlm_latency_s, s.label_warmup))
    finally:
        for lg, level in zip(quiet, levels, strict=True):
            lg.setLevel(level)
        if vlm is not None:
            vlm.stop()
        robot.stop()
    return rows, move_time_s


WAITED_FOR = ("answer_after_stop_s", "arm_back_after_stop_s", "label_after_stop_s")


def label_phase(s: Settings, tmp: Path) -> PhaseResult:
    presses = s.label_presses
    rows, move_time_s = measure(s, tmp, presses)

    def p50(key: str) -> float:
        return stats([r[key] for r in rows])["p50"]

    figs = {
        "label_after_window_ms": figure(
            [r["label_after_window_ms"] for r in rows], "ms",
            target(("p50", "<=", AFTER_WINDOW_P50_MS), ("p99", "<=", AFTER_WINDOW_P99_MS)),
            frame_wait_ms=p50("frame_wait_ms"),
            what="the press's crop window complete (the stop + its last sample's time) -> "
                 "its VLM request received by the fake VLM; the wait for the first frame at "
                 "or past that sample is in it (frame_wait_ms, p50)"),
        "trigger_to_label_s": figure(
            [r["trigger_to_label_s"] for r in rows], "s", None,
            move_time_s=move_time_s, vlm_latency_s=s.vlm_latency_s,
            **{k: p50(k) for k in WAITED_FOR},
            what="POST /v1/recognize -> the label's result event, arm moves as on the real "
                 "arm, fake VLM at a fixed latency; after the stop (p50): the VLM's answer, "
                 "the arm back above the object, the label, which waits for the later of "
                 "the two"),
    }
    notes = [] if len(rows) == presses else [f"label: {presses - len(rows)} presses failed"]
    return PhaseResult(figs, notes)


def main() -> None:
    import tempfile

    from edge.bench.settings import FULL

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--presses", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="vtzero-label-") as tmp:
        rows, move_time_s = measure(FULL, Path(tmp), args.presses)
    print(json.dumps({"move_time_s": move_time_s, "presses": rows}))


if __name__ == "__main__":
    main()
