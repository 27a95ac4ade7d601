"""The robot's presses embed where the dataset's do: a reduced `vt-edge sim consistency`
(the full one, 8 objects, writes models/eval/consistency.md)."""

import pytest

from edge.tools.consistency import run_consistency
from tests.support.daemon import ROOT


@pytest.mark.slow
def test_daemon_presses_sit_with_the_dataset_presses_of_their_object(tmp_path):
    report = run_consistency(("raw_kiri_mochi", "boiled_kiri_mochi", "raw_kabocha_squash"),
                             daemon_presses=3, dataset_presses=10, models=ROOT / "models",
                             config=ROOT / "configs" / "sim.toml", out=tmp_path)
    print(report.markdown("test"))
    # Generous bounds for 3 presses per object (the full report's ratios for these three:
    # 0.39-1.51): a second copy of the press protocol put the daemon's presses 3-4 times the
    # dataset's spread away.
    assert report.median_ratio <= 2.5
    assert report.reid_daemon >= report.loo_dataset - 0.34
    assert (tmp_path / "consistency.md").exists() and (tmp_path / "consistency.json").exists()
