"""``vt-edge sim fusion`` on a tiny configuration: recorder presses of two unseen classes
through the daemon's analysis and fusion code, the report written whole."""

import json

import pytest

from edge.cli import main


# The recorder presses 12 times on the virtual robot: seconds, not the unit tier.
@pytest.mark.integration
def test_the_fusion_measurement_writes_its_report(tmp_path, capsys):
    code = main(["sim", "fusion", "--presses", "6", "--daemon", "0", "--classes", "macaron",
                 "konjac", "--out", str(tmp_path)])
    assert code == 0
    report = json.loads((tmp_path / "fusion.json").read_text())
    assert report["classes"] == ["macaron", "konjac"] and report["presses_per_class"] == 6
    # Every way of recognising has its figures: 6 recognitions of 1 press per class, 2 of 3.
    assert report["recognitions"]["1 press (offset 0, as today)"] == 12
    assert report["recognitions"]["3 presses, votes"] == 4
    for figures in report["consistency"].values():
        assert 0.0 <= figures["top3_overlap"] <= 1.0
    assert report["daemon_s"] == {}
    md = (tmp_path / "fusion.md").read_text()
    assert "Command: `vt-edge sim fusion" in md and "not a real" in md
    print(md)


def test_fewer_than_three_presses_are_refused_in_one_line(capsys):
    assert main(["sim", "fusion", "--presses", "2", "--daemon", "0"]) == 2
    assert "--presses must be at least 3" in capsys.readouterr().err
