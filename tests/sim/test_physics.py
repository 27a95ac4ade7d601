"""The press physics reproduces the paper's press and plausible material behaviour."""

from dataclasses import replace

import numpy as np
import pytest

from edge.core import preprocess, recording
from edge.sim import catalogue, skin
from edge.sim.press import PressParams, simulate_press

FRAME_S = 1 / 125


def press(name, seed=0, **kw):
    return simulate_press(name, np.random.default_rng(seed), replace(PressParams(), **kw))


def test_catalogue_has_the_papers_sets():
    ref = catalogue.DATASETS["reference"]
    assert len(ref) == 32
    assert sum(o.split == "train" for o in ref) == 27
    assert sum(o.split == "val" for o in ref) == 5
    names = {o.name for o in ref}
    assert {"wood_cube", "stainless_cube", "otedama", "kiwi_piece"} <= names
    assert any(n.startswith("gelatin") for n in names)
    food = catalogue.names("foodreplica")
    assert len(food) == 22
    for real in ("canele", "konjac", "chocolate", "ikura_sushi", "macaron"):
        assert real in food and f"resin_replica_{real}" in food
    assert set(catalogue.names("cube")) == {
        "raw_kabocha_squash", "boiled_kabocha_squash", "raw_kiri_mochi", "boiled_kiri_mochi"}
    assert all(o.description for o in ref), "reference classes need a description"
    assert len(set(catalogue.names())) == 32 + 22 + 4


def test_unknown_object_is_named():
    with pytest.raises(KeyError, match="unknown object 'brick'"):
        catalogue.get("brick")


def test_steel_crosses_within_samples_gelatin_takes_far_longer():
    steel = press("stainless_cube")
    gel = press("gelatin_soft")
    steel_ms = (steel.t_cross - steel.t_contact) * 1e3
    gel_ms = (gel.t_cross - gel.t_contact) * 1e3
    print(f"contact -> x_th: steel {steel_ms:.1f} ms, gelatin {gel_ms:.1f} ms")
    assert steel.contact and gel.contact
    assert steel_ms <= 3 * FRAME_S * 1e3 + 2  # within a few samples of contact
    assert gel_ms > 20 * steel_ms


def _hold_ratio(result):
    rec = result.recording
    level = preprocess.norm(preprocess.recording_units(rec))
    hold = (rec.recv_time >= result.t_stop + 0.02) & (rec.recv_time < result.t_stop + 0.2)
    return float(level[hold][-1] / level[hold][0])


@pytest.mark.parametrize("soft", ["boiled_kiri_mochi", "gelatin_soft", "otedama"])
def test_hold_relaxes_viscoelastic_objects_not_steel(soft):
    steel = _hold_ratio(press("stainless_cube"))
    relaxed = _hold_ratio(press(soft))
    print(f"norm end/start of hold: steel {steel:.3f}, {soft} {relaxed:.3f}")
    assert steel > 0.97
    assert relaxed < 0.95


def test_slow_reaction_overshoots_the_force():
    fast = press("stainless_cube", reaction_latency_s=0.001)
    slow = press("stainless_cube", reaction_latency_s=0.020)
    print(f"overshoot: 1 ms {fast.overshoot_n:.2f} N, 20 ms {slow.overshoot_n:.2f} N")
    assert slow.overshoot_n > 2.5 * fast.overshoot_n
    assert slow.overshoot_n - fast.overshoot_n > 2.0  # newtons


def test_plausible_material_contrasts():
    def stiffness(name):
        # Norm per second of closing after contact, averaged over presses.
        rates = []
        for seed in range(3):
            r = press(name, seed)
            rates.append(1.0 / (r.t_cross - r.t_contact + FRAME_S))
        return float(np.mean(rates))

    def peak(name):
        return np.mean([press(name, s).peak_force_n for s in range(3)])

    # A real canele is nearly as hard as its replica.
    assert peak("canele") / peak("resin_replica_canele") > 0.7
    # Raw and boiled kabocha are close under a gentle push.
    assert peak("boiled_kabocha_squash") / peak("raw_kabocha_squash") > 0.6
    # Boiled kiri mochi is much softer than raw.
    assert stiffness("raw_kiri_mochi") > 10 * stiffness("boiled_kiri_mochi")


def test_raw_counts_look_like_the_real_sensor():
    rec = press("wood_cube").recording
    assert rec.frames.dtype == np.uint16 and rec.frames.shape[1] == 96
    idle = rec.frames[:20].astype(float)
    # Idle levels and noise of the real XR1944 pads (tests/sim/test_pad_noise.py compares
    # them in detail with real recordings).
    level = idle.reshape(20, 32, 3).mean(axis=(0, 1))
    assert np.all(np.abs(level - np.array(skin.IDLE_LEVEL_COUNTS)) < 1500), level
    noise = idle.std(axis=0).mean()
    print(f"idle levels {level.round()} counts, noise {noise:.2f} counts")
    assert 1.0 < noise < 8.0
    assert np.all(np.diff(rec.seq) == 1)
    period = np.median(np.diff(rec.recv_time))
    assert period == pytest.approx(1 / 125, rel=0.05)


def test_press_is_deterministic_for_a_seed():
    a = recording.to_bytes(press("konjac", seed=7).recording)
    b = recording.to_bytes(press("konjac", seed=7).recording)
    c = recording.to_bytes(press("konjac", seed=8).recording)
    assert a == b
    assert a != c


def test_fully_closing_without_crossing_reports_no_contact():
    # A threshold no object can reach at the gripper's force cap.
    result = press("cotton_ball", x_th=0.9)
    assert not result.contact
    assert result.recording.extra["contact"] is False
