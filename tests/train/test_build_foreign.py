"""``vt-train build`` from another sensor's sequences (``*.seq.npz``, no ``dataset.json``): the
model's window at the data's rate, its channels, the database and evaluation made the same
way; the robot's runtime refuses it by its rate and channels, ``vt-train eval`` reads it; and
the choice of embedding leaves the shipped network only on a lead beyond the noise."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from edge.core.errors import ModelError, RecordingError
from edge.core.model import load_model
from train.cli import main
from train.learn import sequences
from train.learn.trainer import Progress
from train.ship.build import BuildConfig, build, read_dataset

RATE_HZ = 100.0
CHANNELS = 12
# Classes that differ only in their mean level. By name the last (wood) validates; its level
# sits between the others', so no ordering of levels finds it by its end of the range.
LEVELS = {"cork": 0.0, "felt": 2.0, "plastic": 3.0, "wood": 1.0}

pytestmark = pytest.mark.usefixtures("logging_as_found")


def level_set(directory: Path, presses: int, swing: float, levels=LEVELS,
              rate_hz: float = RATE_HZ, seconds: float = 1.1) -> Path:
    """Each press: its class's level on every channel, plus a 4 Hz swing of ``swing`` at a
    random phase per channel (whole cycles over the 1 s window: its mean there is 0) and a
    little white noise."""
    for ci, (label, level) in enumerate(levels.items()):
        for i in range(presses):
            rng = np.random.default_rng([ci, i])
            t = np.arange(round(seconds * rate_hz))[:, None] / rate_hz
            phase = rng.uniform(0, 2 * np.pi, CHANNELS)
            x = level + swing * np.sin(2 * np.pi * 4.0 * t + phase) \
                + 0.05 * rng.standard_normal((len(t), CHANNELS))
            sequences.save(directory / label / f"{label}_{i:02d}.seq.npz", x, rate_hz, label)
    return directory


def chosen(data: Path, out: Path, epochs: int = 2) -> dict:
    t0 = time.perf_counter()
    manifest = build(BuildConfig(data=data, out=out, max_epochs=epochs, seeds=1),
                     Progress(enabled=False))
    choice = manifest["metrics"]["choice"]
    print(f"build {time.perf_counter() - t0:.1f} s;",
          {n: f["loo_1nn_val_classes"]["mean"] for n, f in choice["figures"].items()},
          f"winner {choice['winner']}, lead {choice['lead']:.3f}, "
          f"floor {choice['noise_floor']:.3f}")
    return manifest


def test_a_build_from_sequences_records_their_rate_and_channels_and_the_robot_refuses_it(
        tmp_path, capsys):
    # Levels far apart, no swing: every candidate finds each class (a tie, or a lead of at
    # most one press of five, inside the noise): the shipped network stays.
    data = level_set(tmp_path / "biotac", presses=5, swing=0.0)
    out = tmp_path / "model"
    manifest = chosen(data, out)
    window = manifest["encoder"]["window"]
    assert window["rate_hz"] == RATE_HZ and window["subsample"] == 4
    assert window["sigma_samples"] == pytest.approx(2.4)  # 3 samples at 125 Hz, in time
    assert manifest["encoder"]["input_shape"] == ["batch", 25, CHANNELS]
    assert manifest["sequences"] == {"rate_hz": RATE_HZ, "channels": CHANNELS,
                                     "format": ".seq.npz"}
    assert manifest["sensor_layout"] is None and manifest["class_x_th"] == {}
    assert manifest["class_rate_hz"] == dict.fromkeys(LEVELS, RATE_HZ)
    assert manifest["origin"]["kind"] == "robot" and "sequences" in manifest["origin"]["recorder"]
    split = manifest["training"]["dataset"]
    assert split["train_classes"] == ["cork", "felt", "plastic"] and split["val_classes"] == [
        "wood"]
    # The database: every press at each of the window's 4 offsets.
    assert manifest["database"]["offsets"] == [0, 1, 2, 3]
    assert manifest["database"]["references"] == 4 * 5 * 4
    choice = manifest["metrics"]["choice"]
    assert choice["winner"] == "shipped" and choice["lead"] <= choice["noise_floor"]
    # No test classes: no consistency measured, said as such.
    assert all(f["top3_consistency"] is None for f in choice["figures"].values())
    md = (out / "eval" / "eval.md").read_text()
    section = md[md.index("## The embedding deployed"):]
    assert "| shipped (deployed) |" in section and "nan" not in section
    if choice["lead"] > 0:
        assert "within the noise: kept the shipped network" in section

    # The robot's runtime refuses it, naming the rate and the channels.
    with pytest.raises(ModelError, match=r"another sensor's sequences, 100 Hz x 12 channels"
                       r".*125 Hz"):
        load_model(out)
    # An evaluation reads it and encodes the data's own windows.
    model = load_model(out, any_sensor=True)
    z, _ = model.encode(np.zeros((25, CHANNELS), np.float32))
    assert z.shape == (manifest["encoder"]["embedding_dim"],)
    unseen = level_set(tmp_path / "unseen", presses=3, swing=0.0,
                       levels={"rubber": 0.5, "sponge": 2.5})
    capsys.readouterr()
    assert main(["eval", "--model", str(out), "--reference", str(data),
                 "--unseen", str(unseen), "--out", str(tmp_path / "eval")]) == 0
    assert "LOO" in (tmp_path / "eval" / "eval.md").read_text()


def test_the_choice_leaves_the_network_for_the_channel_means_on_a_clear_lead(tmp_path):
    # The level is all that tells the classes apart, under a swing 300 times the levels'
    # spacing that the channel means cancel: the means find every class, the networks not.
    out = tmp_path / "model"
    manifest = chosen(level_set(tmp_path / "levels", presses=10, swing=300.0), out, epochs=1)
    choice = manifest["metrics"]["choice"]
    figures = {n: f["loo_1nn_val_classes"]["mean"] for n, f in choice["figures"].items()}
    assert figures["mean"] == 1.0 and figures["shipped"] <= 0.6
    assert choice["winner"] == "mean" and choice["lead"] > choice["noise_floor"]
    assert choice["validation_presses"] == 10
    assert manifest["encoder"]["kind"] == "mean"
    md = (out / "eval" / "eval.md").read_text()
    assert f"`mean` replaced `shipped`, {choice['margin']:.3f} above it" in md
    assert "beyond the noise" in md


def test_sequences_at_two_rates_or_beside_press_recordings_are_refused(tmp_path):
    data = level_set(tmp_path / "two", presses=2, swing=0.0, levels={"cork": 0.0})
    level_set(data, presses=2, swing=0.0, levels={"felt": 1.0}, rate_hz=120.0)
    with pytest.raises(RecordingError, match=r"100 Hz x 12 channels \(class cork\); "
                       r"120 Hz x 12 channels \(class felt\)"):
        read_dataset(data)
    (data / "felt" / "felt_00.press.npz").write_bytes(b"")
    with pytest.raises(RecordingError, match="both the robot's press recordings and"):
        read_dataset(data)
