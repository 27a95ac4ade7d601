"""What the bench's phases share: their settings (a full run and a quick one), the paths and
the objects and controllers they compare."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SIM_CONFIG = ROOT / "configs" / "sim.toml"
MODELS = ROOT / "models"
CUBE = ["raw_kiri_mochi", "boiled_kiri_mochi", "raw_kabocha_squash", "boiled_kabocha_squash"]
OBJECTS = ("stainless_cube", "gelatin_soft")
CONTROLLERS = ("per_frame", "tick125", "loop100")
CONTROLLER_TEXT = {
    "per_frame": "threshold checked on every arriving frame (production)",
    "tick125": "threshold checked on a 125 Hz tick (the sampler's rate)",
    "loop100": "threshold checked by a 100 Hz control loop (ROS 2 style)",
}
HELPER_START_S = 30.0


@dataclass(frozen=True)
class Settings:
    quick: bool
    load_min_s: float  # the loaded phase lasts at least this long (sampler figure)
    presses: int  # loaded presses per controller (alternating the two objects)
    quiet_presses: int  # presses with no extra load (the overhead figure)
    rt_presses: int  # production presses under the load with real-time scheduling on
    rt_min_s: float  # ... over at least this long (its sampler figure)
    move_time_s: float  # arm moves between poses (time-based profile)
    vlm_latency_s: float  # the fake VLM's answer delay
    load_vlm_clients: int  # concurrent askers sending the large still
    image_px: tuple[int, int]
    encode_load_s: float  # encoder work per worker-thread call in the load
    encode_duty: float  # fraction of the time the encoder thread works (1: back to back)
    poll_hz: float
    label_presses: int  # presses of the label phase (arm moves as on the real arm)
    label_warmup: bool  # one press more before them, not counted: it loads the encoder
    daemon_runs: int
    rss_samples: int
    encode_n: int
    retrieval_queries: int
    brute_queries_1m: int
    retrieval_refs: int
    retrieval_classes: int


FULL = Settings(quick=False, load_min_s=60.0, presses=30, quiet_presses=8, rt_presses=20,
                rt_min_s=60.0, move_time_s=0.2,
                vlm_latency_s=1.0, load_vlm_clients=2, image_px=(3000, 2000),
                encode_load_s=0.02, encode_duty=1.0, poll_hz=20.0, label_presses=10,
                label_warmup=True, daemon_runs=3, rss_samples=6,
                encode_n=2000, retrieval_queries=200, brute_queries_1m=20,
                retrieval_refs=1_000_000, retrieval_classes=1000)
QUICK = replace(FULL, quick=True, load_min_s=5.0, presses=3, quiet_presses=2, rt_presses=2,
                rt_min_s=3.0, label_presses=3, daemon_runs=1,
                rss_samples=3, encode_n=300, retrieval_queries=50, brute_queries_1m=5)
