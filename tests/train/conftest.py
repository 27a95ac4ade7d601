"""Shared tiny fixtures: a 2-press-per-class simulated set, recorded once per session."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from edge.lab.record import record_dataset

PRESSES = 2
SEED = 0


@pytest.fixture(scope="session")
def work(tmp_path_factory) -> Path:
    """A release work directory whose recordings `vt-train release` reuses."""
    root = tmp_path_factory.mktemp("work")
    rec = root / "recordings"
    record_dataset("reference", PRESSES, rec / "reference", seed=SEED, workers=2)
    record_dataset("foodreplica", PRESSES, rec / "foodreplica", seed=SEED, workers=2)
    record_dataset("cube", PRESSES, rec / "cube", seed=SEED, workers=2)
    return root


@pytest.fixture(scope="session")
def reference_dir(work) -> Path:
    return work / "recordings" / "reference"


@pytest.fixture(scope="session")
def cube_dir(work) -> Path:
    return work / "recordings" / "cube"


@pytest.fixture(scope="session")
def data(reference_dir):
    from train.learn.data import training_data

    return training_data(reference_dir)


@pytest.fixture(scope="session")
def trained(data):
    from train.learn.trainer import Progress, TrainConfig, train

    return train(data, TrainConfig(max_epochs=8, patience=100), None, Progress(enabled=False))


@pytest.fixture(scope="session")
def released(work, tmp_path_factory) -> Path:
    """A tiny release (3 epochs): a complete, loadable model directory."""
    from train.learn.trainer import Progress
    from train.ship.release import ReleaseConfig, release

    out = tmp_path_factory.mktemp("models")
    release(ReleaseConfig(out=out, work=work / "run_a", recordings=work / "recordings",
                          seed=SEED, presses=PRESSES,
                          unseen_presses=PRESSES, max_epochs=3, workers=2),
            Progress(enabled=False))
    return out


@pytest.fixture
def model_copy(released, tmp_path) -> Path:
    """A private copy of the tiny release, for tests that change or damage it."""
    return Path(shutil.copytree(released, tmp_path / "model"))
