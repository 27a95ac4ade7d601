"""vt-train transfer on small sets made here: the figures, the chance beside them, the seed
spread, the reports, and the refusals of a partner file."""

import json

import pytest

from edge.core.errors import RecordingError
from train.cli import main
from train.eval import transfer
from train.eval.transfer import TransferConfig, chance, read_partners, run

from .synthetic import write_set

PARTNERS = {"hard_a": ["hard_b"], "hard_b": ["hard_a"], "soft_a": ["soft_b"],
            "soft_b": ["soft_a"]}


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    root = tmp_path_factory.mktemp("transfer")
    write_set(root / "data", presses=3)
    (root / "partners.json").write_text(json.dumps(PARTNERS))
    return root


@pytest.mark.integration  # trains 20 small models
def test_transfer_scores_every_candidate_against_partners_beside_chance(made):
    out = made / "out"
    report = run(TransferConfig(made / "data", made / "partners.json", out, seeds=2,
                                max_epochs=3, patience=3), progress=False)
    assert set(report["candidates"]) == {"shipped", "paper", "mean"}
    assert report["not_scored"] == ["odd"]
    assert report["chance"] == pytest.approx({"first": 0.25, "top3": 0.75, "loo_1nn": 0.25})
    mean = report["candidates"]["mean"]
    print("mean:", {k: mean[k]["mean"] for k in ("first", "top3", "loo_1nn")})
    # Objects of one family load the channels alike: the trivial feature finds the partner.
    assert mean["first"]["mean"] >= 0.9 and mean["top3"]["mean"] == 1.0
    assert mean["loo_1nn"]["mean"] > 0.5
    assert mean["first"]["min"] == mean["first"]["max"]  # no seed in a channel mean
    for name in ("shipped", "paper"):
        res = report["candidates"][name]
        assert [s["seed"] for s in res["seeds"]] == [0, 1]
        assert set(res["seeds"][0]["folds"]) == set(report["objects"])
        fold = res["seeds"][0]["folds"]["hard_a"]
        assert len(fold["first"]) == 3 and all(len(t) == 3 for t in fold["top3"])
        assert "hard_a" not in {n for t in fold["top3"] for n in t}  # never itself
        assert fold["epochs"] <= 3
        assert 0 <= res["first"]["min"] <= res["first"]["mean"] <= res["first"]["max"] <= 1
    assert len(report["differences"]) == 3 * 3  # three figures, three pairs
    assert all("seed" in line for line in report["differences"])
    md = (out / transfer.REPORT_MD).read_text()
    assert "| chance | 0.25 | 0.75 | 0.25 |" in md and "## Inside or beyond" in md
    assert json.loads((out / transfer.REPORT_JSON).read_text())["objects"]["odd"] == 3
    assert sorted(p.name for p in out.iterdir()) == ["transfer.json", "transfer.md"]


def test_the_robots_own_presses_go_through_the_same_command(reference_dir, tmp_path):
    from train.learn.data import load_presses

    classes = load_presses(reference_dir).classes
    partners = tmp_path / "p.json"
    partners.write_text(json.dumps({classes[0]: [classes[1]]}))
    report = run(TransferConfig(reference_dir, partners, tmp_path / "out",
                                candidates=("mean",), seeds=1), progress=False)
    assert report["window"] == {"offsets": 5, "steps": 25, "channels": 96}
    assert report["chance"]["first"] == pytest.approx(1 / (len(classes) - 1))


def test_chance_is_a_random_seen_object():
    objects = ["acrylic", "black_foam", "car_sponge", "flour_sack", "kitchen_sponge",
               "steel_vase"]
    partners = {"acrylic": ("steel_vase",), "steel_vase": ("acrylic",),
                "car_sponge": ("kitchen_sponge",), "kitchen_sponge": ("car_sponge",),
                "black_foam": ("car_sponge", "kitchen_sponge"),
                "flour_sack": ("car_sponge", "kitchen_sponge")}
    c = chance(objects, partners)
    # 5 seen objects: one partner is 1/5 first and 1 - C(4,3)/C(5,3) = 0.6 in the top 3.
    assert c["first"] == pytest.approx((4 * 0.2 + 2 * 0.4) / 6)
    assert c["top3"] == pytest.approx((4 * 0.6 + 2 * 0.9) / 6)
    assert c["loo_1nn"] == pytest.approx(0.2)


@pytest.mark.parametrize("content, message", [
    ('{"hard_a": ["steel"]}', r"steel not among the data's objects \(hard_a, hard_b"),
    ('{"glass": ["hard_a"]}', "glass not among"),
    ('{"hard_a": ["hard_a"]}', "hard_a named as its own partner"),
    ('{"hard_a": "hard_b"}', "maps each object to a list"),
    ('{"hard_a": []}', "no object has a partner"),
    ("hard_a: hard_b", "not JSON"),
])
def test_a_partner_file_with_unknown_names_is_refused(tmp_path, content, message):
    path = tmp_path / "partners.json"
    path.write_text(content)
    with pytest.raises(RecordingError, match=message):
        read_partners(path, ["hard_a", "hard_b", "soft_a"])


def test_the_command_refuses_clearly(made, tmp_path, caplog):
    bad = tmp_path / "p.json"
    bad.write_text('{"hard_a": ["glass"]}')
    assert main(["transfer", "--data", str(made / "data"), "--partners", str(bad),
                 "--out", str(tmp_path / "o"), "--candidates", "mean"]) == 2
    assert "glass not among the data's objects" in caplog.text
    assert main(["transfer", "--data", str(made / "data"), "--partners", str(bad),
                 "--out", str(tmp_path / "o"), "--candidates", "mean,best"]) == 2
    assert "unknown candidate best" in caplog.text
    assert not (tmp_path / "o").exists()


def test_one_seed_says_it_has_no_spread():
    """With one seed a network has no spread: no difference is called beyond it."""
    seed = {k: {"mean": 0.6, "min": 0.6, "max": 0.6} for k in ("first", "top3", "loo_1nn")}
    base = {k: {"mean": 0.5, "min": 0.5, "max": 0.5} for k in ("first", "top3", "loo_1nn")}
    lines = transfer.differences({"shipped": seed, "mean": base}, seeds=1)
    assert [line for line in lines if line.startswith("sensible first")] == [
        "sensible first neighbour: shipped 0.60 against mean 0.50: one seed, so no spread to "
        "judge the difference of 0.10 by (--seeds)."]
