"""Helpers for the VLM tests: images and a fast client configuration."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from edge.vlm.client import VLMConfig

MODEL = "fake-vlm"
CANDIDATES = ["raw_kiri_mochi", "boiled_kiri_mochi", "raw_kabocha_squash",
              "boiled_kabocha_squash"]
DESCRIPTION = "wood cube, stainless steel cube"


def image_bytes(width: int = 320, height: int = 240, fmt: str = "JPEG", *,
                noise: bool = False, mode: str = "RGB", seed: int = 0) -> bytes:
    if noise:
        rng = np.random.default_rng(seed)
        channels = {"RGB": 3, "RGBA": 4}[mode]
        arr = rng.integers(0, 256, (height, width, channels), dtype=np.uint8)
        img = Image.fromarray(arr, mode)
    else:
        img = Image.new(mode, (width, height), (200, 120, 40, 255)[: len(mode)])
    buf = io.BytesIO()
    img.save(buf, fmt)
    return buf.getvalue()


def vlm_config(base_url: str, **overrides) -> VLMConfig:
    """Real settings, scaled so a test's retries take milliseconds."""
    values = dict(base_url=base_url, model=MODEL, connect_timeout_s=1.0, total_timeout_s=5.0,
                  max_retries=3, backoff_base_s=0.01, backoff_cap_s=0.05,
                  retry_after_cap_s=5.0)
    values.update(overrides)
    return VLMConfig(**values)
