"""A model directory whose database has features (each reference's per-channel mean over its
model input): the shipped encoder, a database built by ``vt-train db build`` from presses of
a few of its classes made by the dataset recorder."""

from __future__ import annotations

import shutil
from pathlib import Path

from tests.support.daemon import ROOT
from tests.support.lab_data import write_lab_dataset

# Known classes of the shipped model, and presses of each in the built database.
FEATURED_CLASSES = ("wood_cube", "sponge_cube", "apple_piece", "marshmallow", "glass_marble",
                    "yokan")
FEATURED_PRESSES = 4


def featured_model(out: Path) -> Path:
    """``out/model``: the shipped model with a database of :data:`FEATURED_CLASSES`, built
    with features."""
    from train.ship.database import build_into

    model = Path(shutil.copytree(ROOT / "models", out / "model"))
    recordings = write_lab_dataset(out / "recordings", {
        label: ("train", FEATURED_PRESSES, False) for label in FEATURED_CLASSES}, seed=7)
    build_into(model, recordings)
    return model
