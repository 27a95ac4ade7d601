"""The stream's rate end to end on the training side: presses at 100 frames/s on both sides
(references and queries) against the shipped encoder, and ``vt-train build`` refusing a
dataset whose classes were pressed at rates more than 10 % apart, naming them."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import numpy as np
import pytest

from edge.core import preprocess, recording
from edge.core.errors import RecordingError
from edge.core.model import load_model
from edge.lab.record import record_press, sim_config
from tests.support.daemon import ROOT
from tests.support.lab_data import write_lab_dataset
from train.cli import main
from train.ship.build import read_dataset

CLASSES = ("otedama", "wood_cube", "sponge_cube", "kiwi_piece", "rubber_ball")
REFS, QUERIES = (0, 1, 2), (3, 4)


def _config(rate_hz: float):
    cfg = sim_config()
    return replace(cfg, sim=replace(cfg.sim, sensor_rate_hz=rate_hz))


def _pressed(rate_hz: float) -> dict[tuple[str, int], np.ndarray]:
    """Embeddings by the shipped encoder of presses of CLASSES at ``rate_hz`` (the daemon's
    press controller on the virtual-clock emulated robot)."""
    encoder = load_model(ROOT / "models").encoder
    cfg = _config(rate_hz)
    out = {}
    for label in CLASSES:
        for i in REFS + QUERIES:
            rec = record_press(label, 1000 + i, cfg=cfg).recording
            rate = preprocess.recording_rate(rec)
            assert rate.window_hz == pytest.approx(rate_hz, rel=0.02), rate
            x = preprocess.model_input(rec.recv_time, preprocess.recording_units(rec), rec.t_stop)
            assert x.shape == (25, rec.channels)
            out[label, i] = encoder(x[None])[0][0]
    return out


def _one_nn(refs: dict, queries: dict) -> float:
    hits = 0
    for label in CLASSES:
        for q in QUERIES:
            z = queries[label, q]
            best = min((float(np.linalg.norm(z - refs[c, r])), c)
                        for c in CLASSES for r in REFS)
            hits += best[1] == label
    return hits / (len(CLASSES) * len(QUERIES))


def test_100_hz_references_and_queries_recognise_as_125_hz_ones_do():
    # docs/method.md 'A stream that is not 125 Hz': one rate on both sides.
    at125, at100 = _pressed(125.0), _pressed(100.0)
    same125, same100 = _one_nn(at125, at125), _one_nn(at100, at100)
    print(f"1-NN over {len(CLASSES)} classes: 125/125 Hz {same125:.2f}, 100/100 Hz "
          f"{same100:.2f}, 125 references / 100 queries {_one_nn(at125, at100):.2f}")
    assert same100 >= same125 - 0.1 and same100 > 2 / len(CLASSES)


def test_build_refuses_classes_pressed_at_rates_apart_naming_them(tmp_path, caplog):
    data = write_lab_dataset(tmp_path / "mixed", {"otedama": ("train", 2, False),
                                                  "wood_cube": ("train", 2, False),
                                                  "sponge_cube": ("val", 2, False)})
    # sponge_cube pressed again with xela_server at 100 frames/s.
    for i in range(2):
        rec = record_press("sponge_cube", 50 + i, cfg=_config(100.0)).recording
        recording.save(rec, recording.press_path(data, "sponge_cube", i))
    with pytest.raises(RecordingError) as refused:
        read_dataset(data, progress=False)
    line = str(refused.value)
    print(line)
    assert "\n" not in line
    assert re.search(r"apart: (99|100)\.\d Hz: sponge_cube; 12\d\.\d(-12\d\.\d)? Hz: "
                     r"(otedama, wood_cube|wood_cube, otedama):", line)
    assert "xela_server's configuration" in line and "--mixed-rates" in line
    # Told: the build goes on, and says so.
    rates = read_dataset(data, progress=False, mixed_rates=True).rate_hz
    assert rates == pytest.approx({"otedama": 125, "wood_cube": 125, "sponge_cube": 100},
                                  abs=0.5)
    assert "--mixed-rates: classes pressed at stream rates more than 10 % apart" in caplog.text
    assert main(["build", "--data", str(data), "--out", str(tmp_path / "m"), "-q"]) == 2
    assert not (tmp_path / "m").exists()
    assert json.loads((data / "dataset.json").read_text())["classes"][2]["label"] == \
        "sponge_cube"
