import subprocess
import sys

from edge.core import recording
from edge.core.recording import DATASET_INDEX
from edge.runtime.domain import Episode, Status
from edge.runtime.store import new_id


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
    from edge.runtime.store import EpisodeStore

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
    from edge.deploy import udev

    def refused(*_args, **_kw):
        raise PermissionError(13, "Permission denied", "/etc/udev/rules.d/60-vtzero.rules")

    monkeypatch.setattr(udev, "install", refused)
    assert main(["install-udev", "--install"]) == 2
    assert "Permission denied" in caplog.text and "sudo" in caplog.text
    assert "Traceback" not in caplog.text


def test_config_before_or_after_the_subcommand_and_the_retry_line(tmp_path):
    from edge.cli import build_parser, main

    env = {**__import__("os").environ, "VTZERO_STATE_DIR": str(tmp_path)}
    for argv in (["--config", "configs/sim.toml", "episodes", "list"],
                 ["episodes", "--config", "configs/sim.toml", "list"],
                 ["episodes", "list", "--config", "configs/sim.toml"]):
        out = run(*argv, env=env)
        assert out.returncode == 0, (argv, out.stderr)
    parser = build_parser()
    for argv in (["episodes", "retry", "--all-failed", "--config", "robot.toml"],
                 ["--config", "robot.toml", "episodes", "retry", "--all-failed"]):
        args = parser.parse_args(argv)
        assert args.all_failed and args.id is None and args.config == "robot.toml"
    # Where a command needs one, it is asked for by name; where it takes none, it is refused.
    out = run("doctor")
    assert out.returncode == 2 and "vt-edge doctor" in out.stderr and "--config" in out.stderr
    out = run("--config", "configs/sim.toml", "bench")
    assert out.returncode == 2 and "vt-edge bench takes no --config" in out.stderr
    assert main(["--config", "configs/sim.toml", "models", "install", "models", "--to",
                 str(tmp_path / "m")]) == 2
    assert not (tmp_path / "m").exists()


def test_episodes_list_shows_why_an_episode_failed(tmp_path):
    from edge.runtime.store import EpisodeStore

    store = EpisodeStore(tmp_path / "episodes")
    why = ("HTTP 400 from http://vlm.lab:8000/v1: model 'qwen' does not support images; "
           "send a text-only question or pick a vision model")
    store.create(Episode(new_id(), Status.VLM_ERROR, last_error=why), {})
    env = {**__import__("os").environ, "VTZERO_STATE_DIR": str(tmp_path)}
    out = run("episodes", "list", "--config", "configs/sim.toml", env=env)
    print(out.stdout)
    assert out.returncode == 0 and "vlm_error" in out.stdout
    assert "HTTP 400 from http://vlm.lab:8000/v1: model 'qwen' does..." in out.stdout


def test_sim_serve_writes_absolute_paths_and_sim_place_puts_an_object_on_the_table(tmp_path):
    import json
    import os
    import time
    import urllib.request
    from pathlib import Path

    from edge.core.config import load_config

    root = Path(__file__).resolve().parents[1]
    written = tmp_path / "run.toml"
    serve = subprocess.Popen([sys.executable, "-m", "edge", "sim", "serve", "--config",
                              str(root / "configs/sim.toml"), "--write-config", str(written)],
                             cwd=root, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                             text=True)
    try:
        deadline = time.monotonic() + 60
        while not written.exists():
            assert serve.poll() is None and time.monotonic() < deadline
            time.sleep(0.1)
        elsewhere = tmp_path / "elsewhere"
        elsewhere.mkdir()
        os.chdir(elsewhere)
        try:
            cfg = load_config(written)
        finally:
            os.chdir(root)
        assert cfg.runtime.models_dir == str(root / "models")
        assert (Path(cfg.runtime.models_dir) / "manifest.json").is_file()
        assert cfg.runtime.state_dir == str(root / "state")
        out = run("sim", "place", "wood_cube", "--config", str(written), cwd=elsewhere)
        assert out.returncode == 0, out.stderr
        assert "wood_cube is on the emulated table" in out.stdout
        control = cfg.camera.url.removesuffix("/camera.jpg")
        with urllib.request.urlopen(f"{control}/object", timeout=5) as reply:
            assert json.load(reply)["object"] == "wood_cube"
        out = run("sim", "place", "no_such_thing", "--url", control)
        assert out.returncode == 2 and "unknown object 'no_such_thing'" in out.stderr
    finally:
        serve.terminate()
        serve.wait(timeout=30)
