"""The press physics, pressed by the robot's own press controller on the virtual robot,
reproduces the paper's press and plausible material behaviour."""

import numpy as np
import pytest

from edge.core import preprocess, recording
from edge.core.config import Config, load_config
from edge.core.errors import EdgeError
from edge.hw.arm import gripper_raw
from edge.lab.record import record_press
from edge.sim import catalogue, skin
from edge.sim.virtual import Transport
from edge.sim.world import gap_from_raw
from tests.support.daemon import ROOT

FRAME_S = 1 / 125


def press(name, seed=0, **kw):
    return record_press(name, np.random.default_rng(seed), **kw)


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


@pytest.mark.parametrize("open_width_m", [
    pytest.param(Config().press.open_width_m, id="shipped"),
    *(pytest.param(load_config(ROOT / "configs" / name).press.open_width_m, id=name)
      for name in ("sim.toml", "sim-4x6.toml")),
])
def test_every_object_is_free_of_the_open_fingers(open_width_m):
    # A piece wider than the open gripper would be squeezed before the press starts (its
    # tare taken on it) and still after the press "opened". (The tests open as sim.toml.)
    gap = gap_from_raw(gripper_raw(open_width_m))
    widest = max((catalogue.get(n) for n in catalogue.names()),
                 key=lambda o: o.width_m + 5 * o.width_sd_m)
    print(f"open {open_width_m} m, a {gap * 1e3:.1f} mm gap; widest "
          f"{widest.name} {widest.width_m * 1e3:.0f} +- {widest.width_sd_m * 1e3:.1f} mm")
    assert widest.width_m + 5 * widest.width_sd_m < gap


def test_lowering_the_arm_leaves_the_pads_far_under_x_th():
    # The press refuses to close where lowering the arm alone moves the pads by x_th (the
    # object already touches the fingers): never so for a piece that fits, the widest ones
    # included.
    levels = {name: press(name, seed=seed).outcome.lowering_level
              for seed, name in enumerate(("melon_pan", "cream_puff", "cotton_ball", "canele"))}
    x_th = load_config(ROOT / "configs" / "sim.toml").press.x_th
    print("lowering moved the pads by", {n: round(v, 5) for n, v in levels.items()},
          "x_th", x_th)
    assert all(0 < level < 0.25 * x_th for level in levels.values())


def test_unknown_object_is_named():
    with pytest.raises(KeyError, match="unknown object 'brick'"):
        catalogue.get("brick")


def test_gelatins_are_pressed_gentler_as_in_the_paper():
    gelatins = [c for c in catalogue.DATASETS["reference"] if c.name.startswith("gelatin")]
    assert gelatins and all(c.x_th == 0.003 for c in gelatins)
    rec = press("gelatin_hard").recording
    assert rec.threshold == 0.003
    assert press("wood_cube").recording.threshold == 0.004


def test_steel_crosses_within_samples_gelatin_takes_far_longer():
    steel = press("stainless_cube")
    gel = press("gelatin_soft")
    steel_ms = (steel.outcome.t_cross - steel.t_contact) * 1e3
    gel_ms = (gel.outcome.t_cross - gel.t_contact) * 1e3
    print(f"contact -> x_th: steel {steel_ms:.1f} ms, gelatin {gel_ms:.1f} ms")
    assert steel_ms <= 3 * FRAME_S * 1e3 + 2  # within a few samples of contact
    assert gel_ms > 20 * steel_ms


def _hold_ratio(pressed):
    rec = pressed.recording
    level = preprocess.norm(preprocess.recording_units(rec))
    hold = (rec.recv_time >= rec.t_stop + 0.02) & (rec.recv_time < rec.t_stop + 0.2)
    return float(level[hold][-1] / level[hold][0])


# How far below steel's each object's norm must end the hold. gelatin_soft is stopped at
# x_th 0.003, at about 0.2 N: its force relaxes by ~7 % over the hold, but at that force the
# pads' norm moves by ~1 % (0.992 against steel's 1.002). The 5 % it was held to passed only
# while the emulated world still saw the fingers short of their stop goal until the next
# state read (steel's hold then rose 5 %: 1.052).
HOLD_RELAXATION = {"boiled_kiri_mochi": 0.95, "gelatin_soft": 0.995, "otedama": 0.95}


@pytest.mark.parametrize("soft", list(HOLD_RELAXATION))
def test_hold_relaxes_viscoelastic_objects_not_steel(soft):
    steel = _hold_ratio(press("stainless_cube"))
    relaxed = _hold_ratio(press(soft))
    print(f"norm end/start of hold: steel {steel:.3f}, {soft} {relaxed:.3f}")
    # Steel holds; a viscoelastic object relaxes.
    assert steel > 0.97
    assert relaxed < HOLD_RELAXATION[soft] * steel


def test_slow_stop_overshoots_the_force():
    fast = press("stainless_cube", transport=Transport(stop_latency_p50_s=0.001,
                                                       stop_latency_p99_s=0.0011))
    slow = press("stainless_cube", transport=Transport(stop_latency_p50_s=0.020,
                                                       stop_latency_p99_s=0.022))
    print(f"overshoot: 1 ms {fast.overshoot_n:.2f} N, 20 ms {slow.overshoot_n:.2f} N")
    assert slow.overshoot_n > 2.5 * fast.overshoot_n
    assert slow.overshoot_n - fast.overshoot_n > 2.0  # newtons


def test_plausible_material_contrasts():
    def stiffness(name):
        # Norm per second of closing after contact, averaged over presses.
        rates = []
        for seed in range(3):
            r = press(name, seed)
            rates.append(1.0 / (r.outcome.t_cross - r.t_contact + FRAME_S))
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


def test_a_threshold_no_press_reaches_ends_in_a_clear_error():
    # A threshold no object can reach at the gripper's force cap: every try closes fully.
    with pytest.raises(EdgeError, match=r"cotton_ball: 3 presses gave no recording \(no_contact"):
        press("cotton_ball", x_th=0.9)


def test_a_dataset_is_byte_identical_for_a_seed_whatever_the_workers(tmp_path):
    from edge.lab.record import record_dataset

    record_dataset("cube", 2, tmp_path / "one", seed=3, workers=1)
    record_dataset("cube", 2, tmp_path / "two", seed=3, workers=2)
    one = sorted((tmp_path / "one").rglob("*.press.npz"))
    two = sorted((tmp_path / "two").rglob("*.press.npz"))
    assert len(one) == len(two) == 8
    for a, b in zip(one, two, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name


# The shipped model was trained on the recorder's presses of seed 0: a change to the
# emulated world that moves them (a random draw taken or skipped, a physics change) must be
# seen, and the release made again, not slip in. The Cube set's first press of every class.
CUBE_SEED0_SHA256 = "a72c1ae0c24607f676218e1bf8b3442901bb5827274d101e0cbab675c9eb30be"


def test_the_recorded_presses_of_a_seed_are_the_ones_the_release_was_trained_on(tmp_path):
    import hashlib

    from edge.lab.record import record_dataset

    record_dataset("cube", 1, tmp_path, seed=0, workers=1)
    digest = hashlib.sha256()
    for path in sorted(tmp_path.rglob(f"*{recording.SUFFIX}")):
        with np.load(path) as press:
            digest.update(press["frames"].tobytes())
            digest.update(press["tare"].tobytes())
    assert digest.hexdigest() == CUBE_SEED0_SHA256
