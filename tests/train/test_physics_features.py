"""The press's physics features (train/learn/physics.py): ordered as the physics says on
presses made here with known stiffness, relaxation and spread; hostile input refused; the
candidates through vt-train transfer and the evaluation's embedders."""

import json

import numpy as np
import pytest

from edge.core import preprocess
from edge.core.errors import PreprocessError
from train.eval import evaluate
from train.eval.transfer import TransferConfig, run
from train.learn import physics

from .synthetic import write_set

STOP, HOLD_END = physics.steps_of()
CHANNELS = 12


def press(stiffness: float = 1.0, relaxation: float = 0.0, taxels: int = CHANNELS,
          onset: int = 4) -> np.ndarray:
    """One window (25 steps, 12 channels): the load rises at ``stiffness`` units per step from
    ``onset`` steps before the stop, falls by the share ``relaxation`` over the hold, then the
    gripper opens; ``taxels`` channels carry it (the rest stay at rest)."""
    steps = preprocess.DEFAULT_WINDOW.n_steps
    n = np.zeros(steps)
    rise = np.arange(1, onset + 2) * stiffness
    n[STOP - onset:STOP + 1] = rise
    top = rise[-1]
    hold = np.linspace(top, top * (1 - relaxation), HOLD_END - STOP + 1)
    n[STOP:HOLD_END + 1] = hold
    x = np.zeros((steps, CHANNELS))
    x[:, :taxels] = n[:, None] / np.sqrt(taxels)
    return x


def feature(windows, name):
    return physics.features(np.stack(windows))[:, physics.FEATURES.index(name)]


def test_features_come_out_ordered_as_the_physics_says():
    stiff = feature([press(stiffness=k) for k in (0.5, 1.0, 2.0, 4.0)], "stiffness")
    print("stiffness", stiff)
    assert np.all(np.diff(stiff) > 0)
    assert stiff[1] == pytest.approx(1.0 * preprocess.DEFAULT_WINDOW.step_hz)  # per second
    peak = feature([press(stiffness=k) for k in (0.5, 1.0, 2.0)], "peak")
    assert np.all(np.diff(peak) > 0)
    relax = feature([press(relaxation=r) for r in (0.0, 0.1, 0.3, 0.6)], "relaxation")
    print("relaxation", relax)
    assert relax == pytest.approx([0.0, 0.1, 0.3, 0.6])
    spread = feature([press(taxels=t) for t in (12, 6, 3, 1)], "spread")
    print("spread", spread)
    assert spread[0] == pytest.approx(0.0) and np.all(np.diff(spread) > 0)
    # What the window starts at is not load: a sensor in raw counts gives the same figures.
    base = np.stack([press(stiffness=2.0, relaxation=0.3, taxels=4)])
    assert physics.features(base + 1000.0) == pytest.approx(physics.features(base))


def test_windows_too_short_for_the_hold_or_not_finite_are_refused():
    with pytest.raises(PreprocessError, match="more than 15 steps"):
        physics.features(np.ones((2, HOLD_END, 3)))
    bad = np.stack([press(), press()])
    bad[1, 3, 2] = np.inf
    with pytest.raises(PreprocessError, match=r"window 1 .*step 3, channel 2"):
        physics.features(bad)
    with pytest.raises(PreprocessError, match="window 1 never changes"):
        physics.features(np.stack([press(), np.zeros_like(press())]))


def test_the_side_by_side_embedding_weighs_each_block_alike():
    rng = np.random.default_rng(0)
    x = np.stack([press(stiffness=rng.uniform(0.5, 3), relaxation=rng.uniform(0, 0.5),
                        taxels=int(rng.integers(1, CHANNELS + 1))) for _ in range(40)])
    x += rng.normal(0, 0.01, x.shape)
    z, _ = evaluate.mean_physics_embedder(x)(x)
    means, phys = z[:, :CHANNELS], z[:, CHANNELS:]
    # Standardised features have a mean square of 1 each; each block then sums to 1.
    assert (means ** 2).sum(axis=1).mean() == pytest.approx(1.0, rel=1e-3)
    assert (phys ** 2).sum(axis=1).mean() == pytest.approx(1.0, rel=1e-3)
    z_phys, _ = evaluate.physics_embedder(x)(x)
    assert z_phys.shape == (40, len(physics.FEATURES))
    assert z_phys.mean(axis=0) == pytest.approx(np.zeros(4), abs=1e-5)


def test_the_physics_candidates_run_through_transfer(tmp_path):
    # Families differ in how fast the load builds (hard: 0.05 s, soft: 0.3 s), which the
    # physics features read as stiffness.
    write_set(tmp_path / "data", presses=4)
    partners = {"hard_a": ["hard_b"], "hard_b": ["hard_a"], "soft_a": ["soft_b"],
                "soft_b": ["soft_a"]}
    (tmp_path / "partners.json").write_text(json.dumps(partners))
    report = run(TransferConfig(tmp_path / "data", tmp_path / "partners.json",
                                tmp_path / "out", candidates=("mean", "physics",
                                                              "mean+physics"), seeds=2),
                 progress=False)
    assert list(report["candidates"]) == ["mean", "physics", "mean+physics"]
    for name, res in report["candidates"].items():
        print(name, {k: res[k]["mean"] for k in ("first", "top3", "loo_1nn")})
        assert [s["seed"] for s in res["seeds"]] == [0, 1]
        assert res["first"]["min"] == res["first"]["max"]  # no seed in a numpy feature
    physics_first = report["candidates"]["physics"]["first"]["mean"]
    assert physics_first > report["chance"]["first"] + 0.3
    assert any("neither depends on a seed" in line for line in report["differences"])
    md = (tmp_path / "out" / "transfer.md").read_text()
    assert "the press's physics (peak, stiffness, relaxation, spread)" in md


@pytest.mark.integration  # records the tiny sets and a tiny release (session fixtures)
def test_the_simulated_measurement_reports_every_variant_and_the_assumptions(work, released,
                                                                          tmp_path):
    from train.eval import physics_eval

    rec = work / "recordings"
    out = tmp_path / "physics"
    assert physics_eval.main(["--model", str(released), "--reference", str(rec / "reference"),
                              "--unseen", str(rec / "foodreplica"), str(rec / "cube"),
                              "--out", str(out)]) == 0
    report = json.loads((out / "physics.json").read_text())
    assert set(report["variants"]) == set(physics_eval.VARIANTS)
    for name, v in report["variants"].items():
        print(name, {k: v[k] for k, _ in physics_eval.FIGURES})
        assert all(0 <= v[k] <= 1 for k, _ in physics_eval.FIGURES)
        assert all(0 <= v["se"][k] < 0.5 for k, _ in physics_eval.FIGURES)
    a = report["assumptions"]
    print(a)
    # The emulated gripper closes at a constant speed: no slowing as the load builds.
    assert 1 < a["closing_speed_mm_s"]["median"] < 50
    assert 0.8 < a["second_half_over_first"]["median"] < 1.2
    # The harder the object pushes back, the more current the hold draws.
    assert a["spearman_with_hold_current"]["peak"] > 0.3
    md = (out / "physics.md").read_text()
    assert md.splitlines()[2].startswith("Command: `python -m train.eval.physics_eval")
    assert (out / "eval" / "eval.json").exists()
