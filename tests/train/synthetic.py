"""Small labelled sequences made here (never a real data set): objects whose squeezes load
the channels with their own pattern; objects named alike (``soft_a``, ``soft_b``) share most
of it, so they feel alike."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from train.learn import sequences

OBJECTS = ("hard_a", "hard_b", "soft_a", "soft_b", "odd")


def pattern(obj: str, channels: int) -> tuple[np.ndarray, float]:
    """The object's load per channel and its time constant (s)."""
    family = obj.rsplit("_", 1)[0]
    base = np.random.default_rng(sum(map(ord, family))).uniform(0.2, 2.0, channels)
    own = np.random.default_rng(sum(map(ord, obj)) * 7).uniform(-0.15, 0.15, channels)
    tau = {"hard": 0.05, "soft": 0.3}.get(family, 0.15)
    return base * (1 + own), tau


def squeeze(obj: str, press: int, channels: int = 6, rate_hz: float = 100.0,
            seconds: float = 1.5) -> np.ndarray:
    load, tau = pattern(obj, channels)
    rng = np.random.default_rng([press, sum(map(ord, obj))])
    t = np.arange(round(seconds * rate_hz)) / rate_hz
    curve = 1 - np.exp(-t / tau)
    noise = rng.normal(0, 0.02, (len(t), channels))
    return (100 + 50 * curve[:, None] * load * rng.uniform(0.9, 1.1) + noise).astype(
        np.float32)


def write_set(directory: Path, objects=OBJECTS, presses: int = 4, channels: int = 6,
              rate_hz: float = 100.0) -> Path:
    for obj in objects:
        for i in range(presses):
            sequences.save(directory / obj / f"{obj}_{i:02d}.seq.npz",
                           squeeze(obj, i, channels, rate_hz), rate_hz, obj)
    return directory
