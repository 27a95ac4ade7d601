import subprocess
import sys

from edge.core import recording
from edge.core.recording import DATASET_INDEX
from edge.daemon.episode import Episode, Status
from edge.daemon.store import new_id


def run(*args, **kw):
    return subprocess.run([sys.executable, "-m", "edge", *args], capture_output=True,
                          text=True, timeout=120, **kw)


def test_sim_record_writes_a_loadable_deterministic_dataset(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    out = run("sim", "record", "--dataset", "cube", "--presses", "2", "--out", str(a), "-q")
    assert out.returncode == 0, out.stderr
    assert "wrote 8 presses of 4 classes" in out.stdout
    run("sim", "record", "--dataset", "cube", "--presses", "2", "--out", str(b), "-q",
        "--workers", "1")
    files = recording.find(a)
    assert len(files) == 8 and (a / DATASET_INDEX).exists()
    for f in files:
        rec = recording.load(f)
        assert rec.label == f.parent.name
        assert (b / f.relative_to(a)).read_bytes() == f.read_bytes()


def test_sim_press_prints_a_press_summary():
    out = run("sim", "press", "boiled_kiri_mochi", "stainless_cube")
    assert out.returncode == 0, out.stderr
    assert "boiled_kiri_mochi" in out.stdout and "X 25x96" in out.stdout


def test_bad_arguments_exit_nonzero():
    out = run("sim", "record", "--dataset", "bricks", "--out", "x")
    assert out.returncode == 2 and "invalid choice" in out.stderr


def test_episodes_list_show_export(tmp_path):
    from edge.daemon.store import EpisodeStore

    store = EpisodeStore(tmp_path / "episodes")
    eid = store.create(Episode(new_id(), Status.DONE, label="macaron", description="soft"), {})
    env = {**__import__("os").environ, "VTZERO_STATE_DIR": str(tmp_path)}
    out = run("episodes", "--config", "configs/sim.toml", "list", env=env)
    assert out.returncode == 0 and eid in out.stdout and "macaron" in out.stdout
    out = run("episodes", "--config", "configs/sim.toml", "show", eid, env=env)
    assert '"label": "macaron"' in out.stdout
    out = run("episodes", "--config", "configs/sim.toml", "export", eid, "--out",
              str(tmp_path), env=env)
    assert out.returncode == 0 and (tmp_path / f"{eid}.tar.gz").exists()
    out = run("episodes", "--config", "configs/sim.toml", "show", "nope", env=env)
    assert out.returncode == 2 and "no episode" in out.stderr


def test_a_file_the_command_cannot_write_is_one_line_not_a_traceback(tmp_path, monkeypatch,
                                                                      caplog):
    from edge.cli import main
    from edge.daemon import udev

    def refused(*_args, **_kw):
        raise PermissionError(13, "Permission denied", "/etc/udev/rules.d/60-vtzero.rules")

    monkeypatch.setattr(udev, "install", refused)
    assert main(["install-udev", "--install"]) == 2
    assert "Permission denied" in caplog.text and "sudo" in caplog.text
    assert "Traceback" not in caplog.text
