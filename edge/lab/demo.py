"""The main job (``make run``): the emulated robot, the daemon, recognitions over HTTP.

Three processes, as on a robot: ``vt-edge sim serve`` (the emulated arm and pads),
``vt-edge run`` (the daemon, unchanged but for device addresses), and this client, which
places objects on the emulated table and asks the daemon's HTTP API to recognise them.

The VLM: the endpoint in ``$VTZERO_VLM_URL`` (and ``$VTZERO_VLM_MODEL``) when set; else a
fourth process, the simulated VLM (``python -m edge.sim.standin_vlm``: it knows only object
names and pictures, never the simulator's physics), and every label it gives is printed as
coming from it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from edge.lab.stack import Stack, http_json, sim_stack, stop, wait_for
from edge.runtime.domain import PressState, PressSummary
from edge.sim.catalogue import names

CUBE = ("raw_kiri_mochi", "boiled_kiri_mochi", "raw_kabocha_squash", "boiled_kabocha_squash")
FOOD = ("macaron", "resin_replica_macaron", "canele", "resin_replica_konjac")
START_TIMEOUT_S = 60.0
RECOGNIZE_TIMEOUT_S = 60.0
STANDIN_MODEL = "simulated-vlm"  # edge.sim.standin_vlm.DEFAULT.model
STANDIN_TAG = "simulated VLM"

VLM_HELP = """\
No VLM is configured, so no label is given (none is ever invented). Point the daemon at any
OpenAI-compatible endpoint and run again:
  OpenAI:  VTZERO_VLM_URL=https://api.openai.com/v1 VTZERO_VLM_MODEL=gpt-4o \\
           VTZERO_VLM_API_KEY=sk-... make run
  Ollama:  VTZERO_VLM_URL=http://localhost:11434/v1 VTZERO_VLM_MODEL=llama3.2-vision make run
  vLLM:    VTZERO_VLM_URL=http://localhost:8000/v1 VTZERO_VLM_MODEL=Qwen/Qwen2-VL-7B-Instruct \\
           make run"""


STANDIN_NOTE = """\
The labels above come from the simulated VLM (edge/sim/standin_vlm.py), not a real model: it
compares the photo with each candidate's picture and reads the touch sentence's object names
through a small table of common sense (edge/sim/common_sense.py). For a real VLM:"""


def _start_standin(tmp: Path, env: dict) -> tuple[subprocess.Popen, str]:
    """The simulated VLM on a free loopback port; returns the process and its base URL."""
    log_path = tmp / "simulated-vlm.log"
    with log_path.open("w") as log_file:
        proc = subprocess.Popen([sys.executable, "-m", "edge.sim.standin_vlm", "--port", "0"],
                                stdout=log_file, stderr=subprocess.STDOUT, env=env)
    url: list[str] = []

    def ready() -> bool:
        for line in log_path.read_text().splitlines():
            if line.startswith("simulated VLM at "):
                url.append(line.split()[3])
                return True
        return False

    wait_for(ready, START_TIMEOUT_S, "simulated VLM", proc)
    return proc, url[0]


def _print_episode(name: str, ep: dict, peak_n: float | None) -> None:
    print(f"\n== {name}")
    if ep.get("status") == "failed":
        print(f"   press failed: {ep.get('error')}")
        return
    press = PressSummary.from_json(ep["press"], f"episode {ep.get('id')}: 'press'")
    closing = press.entered(PressState.CLOSING)
    if closing is None:
        closing = press.t_stop
    print(f"   press: x_th crossed after {press.t_cross - closing:.2f} s of closing, stop sent "
          f"{press.stop_latency_ms:.2f} ms after that frame (t_stop), peak norm "
          f"{press.peak_level:.4f}"
          + (f", peak force {peak_n:.2f} N" if peak_n is not None else ""))
    topk = ", ".join(f"{t['label']} ({t['distance']:.3f})" for t in ep.get("topk", []))
    print(f"   touch: top-3 {topk}")
    print(f"   sentence: \"{ep.get('description')}\"")
    model = (ep.get("vlm") or {}).get("model") or ""
    source = STANDIN_TAG if model == STANDIN_MODEL else f"VLM {model}"
    if ep.get("label"):
        print(f"   label ({source}): {ep['label']}  "
              f"({'right' if ep['label'] == name else 'wrong'})")
    else:  # (camera_error says why in error)
        print(f"   {source}: {ep.get('status')}"
              + (f": {ep['error']}" if ep.get("error") else ""))


def run_demo(config: str = "configs/sim.toml", objects: tuple[str, ...] = CUBE + FOOD) -> int:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.setdefault("VTZERO_LOG_LEVEL", "WARNING")
    standin = not env.get("VTZERO_VLM_URL", "").strip()
    with tempfile.TemporaryDirectory(prefix="vtzero-demo-") as tmp:
        vlm = None
        try:
            if standin:
                print("no VLM endpoint configured ($VTZERO_VLM_URL): starting the simulated "
                      "VLM ...", flush=True)
                vlm, url = _start_standin(Path(tmp), env)
                env["VTZERO_VLM_URL"], env["VTZERO_VLM_MODEL"] = url, STANDIN_MODEL
            else:
                print(f"VLM: {env['VTZERO_VLM_URL']} ({env.get('VTZERO_VLM_MODEL', '')})",
                      flush=True)
            print("starting the emulated robot and the daemon ...", flush=True)
            with sim_stack(config, objects[0], env) as stack:
                _recognise_all(stack, objects, standin, env)
        finally:
            if vlm is not None:
                stop(vlm, "simulated VLM")
    return 0


def _recognise_all(stack: Stack, objects: tuple[str, ...], standin: bool,
                   env: dict[str, str]) -> None:
    right = answered = 0
    shown_prompt = False
    for name in objects:
        dataset = "cube" if name in names("cube") else "foodreplica"
        stack.place(name)
        ep = http_json("POST", f"{stack.api}/v1/recognize",
                       {"candidates": names(dataset), "wait": True,
                        "timeout_s": RECOGNIZE_TIMEOUT_S}, timeout=RECOGNIZE_TIMEOUT_S + 5)
        peak = stack.world().get("peak_force_n")
        if "http_status" in ep:
            print(f"\n== {name}: HTTP {ep['http_status']}: {ep.get('error')}")
            continue
        _print_episode(name, ep, peak)
        if ep.get("label"):
            answered += 1
            right += ep["label"] == name
        if ep.get("status") == "not_configured" and not shown_prompt:
            prompt = (ep.get("vlm") or {}).get("prompt")
            print("\n   The prompt it would send (with the photo):\n")
            print("   " + str(prompt).replace("\n", "\n   "))
            shown_prompt = True
    if shown_prompt:
        print("\n" + VLM_HELP)
    if answered:
        who = STANDIN_TAG if standin else env.get("VTZERO_VLM_MODEL", "the VLM")
        print(f"\n{who}: {right} of {answered} labels right")
    if standin:
        print("\n" + STANDIN_NOTE + "\n" + VLM_HELP.split("\n", 2)[2])
