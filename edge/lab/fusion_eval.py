"""Press again and fuse, measured: top-3 consistency of recognitions of 1 and 3 presses of
the unseen FoodReplica and Cube classes, both fusions, and the time per recognition on the
daemon (``vt-edge sim fusion --out models/eval/fusion``).

Consistency: each class pressed ``--presses`` times by the dataset recorder (the robot's own
press controller on the virtual clock), the presses grouped into recognitions (1 press each,
or 3), each recognition's top-3 classes from the daemon's code (``analyse_press`` for one
press as the daemon has it, ``fuse_presses`` for the fusions), and the project's measure
(:func:`edge.core.consistency.consistency`: the share of same-class pairs of recognitions with the
same top-3 set). Time: ``--daemon`` recognitions of 1 and of 3 presses (``pause_s`` 0)
through ``POST /v1/recognize`` on ``vt-edge run`` on the emulated robot with no VLM endpoint
configured (episodes ``not_configured``: the press, analysis, fusion and store, not the
VLM's answer), wall clock per recognition. Writes fusion.md and fusion.json.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

from edge.core.atomic import atomic_write_text
from edge.core.consistency import consistency
from edge.core.model import model_ref
from edge.lab.record import record_press
from edge.lab.stack import http_json, sim_stack
from edge.lab.teaching_eval import candidates_of, unseen_classes
from edge.runtime.compute import analyse_press, fuse_presses
from edge.sim.camera import render
from edge.sim.standin_vlm import DEFAULT as VLM_PROFILE
from edge.sim.standin_vlm import decide

SEED = 7000


def top3s(ref, classes, presses: int) -> dict[str, tuple[list[list[str]], list[str], list[bool]]]:
    """Per way of recognising: the recognitions' top-3 labels, their classes and whether
    the simulated VLM (Table I's candidates, the simulated photo, the touch sentence) named
    the class."""
    rows: dict[str, tuple[list[list[str]], list[str], list[bool]]] = {
        k: ([], [], []) for k in ("1 press (offset 0, as today)", "1 press, votes over offsets",
                              "1 press, mean over offsets", "3 presses, votes",
                              "3 presses, mean")}
    for c, name in enumerate(classes):
        recs = [record_press(name, SEED + 1000 * c + i).recording for i in range(presses)]
        photo, candidates = render(name), candidates_of(name)

        def keep(key: str, analysis, name=name, photo=photo, candidates=candidates) -> None:
            rows[key][0].append([label for label, _ in analysis.topk])
            rows[key][1].append(name)
            answer = decide(VLM_PROFILE, photo, analysis.description, candidates).label
            rows[key][2].append(answer == name)

        for rec in recs:
            keep("1 press (offset 0, as today)", analyse_press(ref, rec))
            keep("1 press, votes over offsets", fuse_presses(ref, [rec], "votes"))
            keep("1 press, mean over offsets", fuse_presses(ref, [rec], "mean"))
        for g in range(0, presses - 2, 3):
            for fusion in ("votes", "mean"):
                keep(f"3 presses, {fusion}", fuse_presses(ref, recs[g:g + 3], fusion))
        print(f"  {name}: {presses} presses", flush=True)
    return rows


def daemon_times(n: int, classes: list[str]) -> dict[str, list[float]]:
    times: dict[str, list[float]] = {"1": [], "3": []}
    with sim_stack(first_object=classes[0]) as stack:
        for i in range(n):
            for presses in (1, 3):
                stack.place(classes[i % len(classes)])
                t = time.monotonic()
                ep = http_json("POST", f"{stack.api}/v1/recognize",
                               {"candidates": classes[:5], "wait": True, "timeout_s": 120,
                                "presses": presses, "pause_s": 0}, timeout=130)
                took = time.monotonic() - t
                ok = "http_status" not in ep and ep.get("status") != "failed"
                print(f"  {presses} press(es): {took:.1f} s, {ep.get('status')} "
                      f"{ep.get('error') or ''}", flush=True)
                if ok:
                    times[str(presses)].append(took)
    return times


def run_fusion(models: str | Path, presses: int, daemon: int, out: str | Path | None,
               classes: list[str] | None = None, command: str = "vt-edge sim fusion") -> str:
    """Measure, write fusion.md and fusion.json into ``out`` (when given) and return the
    Markdown."""
    ref = model_ref(models)
    classes = classes or unseen_classes(ref)
    t0 = time.monotonic()
    rows = top3s(ref, classes, presses)
    figures = {k: consistency(r, labels) for k, (r, labels, _) in rows.items()}
    times = daemon_times(daemon, classes) if daemon else {}
    report = {
        "classes": classes, "presses_per_class": presses, "seed": SEED,
        "consistency": {k: {m: f[m] for m in ("top3_consistency", "top1_consistency",
                                              "top3_overlap")}
                        for k, f in figures.items()},
        "recognitions": {k: len(r[0]) for k, r in rows.items()},
        "simulated_vlm_accuracy": {k: sum(r[2]) / len(r[2]) for k, r in rows.items()},
        "simulated_vlm": "edge/sim/standin_vlm.py: a stand-in, not a real VLM",
        "daemon_s": times, "elapsed_s": time.monotonic() - t0}
    lines = ["# Press again and fuse", "",
             f"{len(classes)} unseen FoodReplica and Cube classes, {presses} recorder "
             "presses each (the daemon's analysis and fusion code), the shipped model. "
             f"Command: `{command}`.", "",
             "| recognition | recognitions | pairs | top-3 consistency (± binomial SE) | "
             "top-1 consistency | top-3 overlap | simulated VLM accuracy |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for k, f in report["consistency"].items():
        per_class = report["recognitions"][k] // len(classes)
        pairs = len(classes) * per_class * (per_class - 1) // 2
        se = (f["top3_consistency"] * (1 - f["top3_consistency"]) / max(pairs, 1)) ** 0.5
        lines.append(f"| {k} | {report['recognitions'][k]} | {pairs} | "
                     f"{f['top3_consistency']:.3f} ± {se:.3f} | "
                     f"{f['top1_consistency']:.3f} | {f['top3_overlap']:.3f} | "
                     f"{report['simulated_vlm_accuracy'][k]:.3f} |")
    lines += ["", "The pairs share presses, so the binomial standard error is a lower bound on "
              "the noise. A recognition of 3 presses is the votes or mean fusion of 3 of the "
              "class's presses (disjoint groups); of 1 press, offset 0 as the daemon reads "
              "one press, or all 5 subsampling offsets fused. Simulated VLM accuracy: "
              "Table I style, each recognition's touch sentence asked of "
              "`edge/sim/standin_vlm.py` in this process with its set's labels as candidates "
              "and the simulated camera's photo; **the VLM here is simulated, not a real "
              "one**."]
    if times:
        lines += ["", "Seconds per recognition on `vt-edge run` (emulated robot, no VLM "
                  "endpoint: the VLM's answer not included, pause_s 0, median of the "
                  "recognitions that worked, min-max): "
                  + ", ".join(f"{p} press(es) {statistics.median(v):.1f} s "
                              f"({min(v):.1f}-{max(v):.1f}, n = {len(v)})"
                              for p, v in times.items() if v) + "."]
    text = "\n".join(lines) + "\n"
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
        atomic_write_text(Path(out) / "fusion.json", json.dumps(report, indent=1) + "\n")
        atomic_write_text(Path(out) / "fusion.md", text)
    return text
