from pathlib import Path

import pytest

from edge.core.config import Config, apply_environment, config_from_dict, load_config
from edge.core.errors import ConfigError, EdgeError

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", ["sim.toml", "robot.toml"])
def test_example_configs_load(name):
    cfg = load_config(ROOT / "configs" / name)
    assert isinstance(cfg, Config)
    assert cfg.mode == name.removesuffix(".toml")
    assert cfg.sensor.channels == 96
    assert cfg.press.x_th == pytest.approx(0.004)


def test_defaults_are_the_paper_press():
    cfg = config_from_dict({})
    assert cfg.press.x_th == 0.004 and cfg.press.dt_stopping_s == 0.2
    assert cfg.bus.gripper_id == 15 and cfg.bus.joint_ids == (11, 12, 13, 14)


@pytest.mark.parametrize(
    ("raw", "needle"),
    [
        ({"press": {"x_th": "high"}}, "press.x_th = 'high': must be a number"),
        ({"press": {"x_th": 2.0}}, "press.x_th = 2.0: must be in (0, 1)"),
        ({"press": {"xth": 0.1}}, "unknown key 'press.xth'"),
        ({"mode": "real"}, "mode = 'real': must be one of 'sim', 'robot'"),
        ({"bus": {"joint_ids": [11, 12, 13, 15]}}, "must be distinct"),
        ({"bus": {"watchdog_ms": 30}}, "bus.watchdog_ms = 30"),
        ({"bus": {"gripper_id": True}}, "bus.gripper_id = True: must be an integer"),
        ({"sensor": "ws://x"}, "sensor must be a table"),
        ({"sensor": {"url": "http://x"}}, "sensor.url = 'http://x'"),
        ({"press": {"x_th": float("nan")}}, "must be finite"),
        ({"runtime": {"store_max_mb": -1}}, "runtime.store_max_mb = -1.0: must be >= 0"),
        ({"runtime": {"keep_free_mb": "lots"}}, "runtime.keep_free_mb = 'lots': must be a"),
    ],
)
def test_bad_values_name_the_field(raw, needle):
    with pytest.raises(ConfigError) as err:
        config_from_dict(raw)
    assert needle in str(err.value)
    assert isinstance(err.value, EdgeError) and isinstance(err.value, ValueError)


def test_bad_files_are_refused_clearly(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[press\nx_th = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("[press]\nx_th = -1\n")
    with pytest.raises(ConfigError, match=r"wrong\.toml: press\.x_th = -1"):
        load_config(wrong)


def test_config_is_frozen():
    cfg = config_from_dict({})
    with pytest.raises(AttributeError):
        cfg.press.x_th = 0.1  # type: ignore[misc]


ENVIRONMENT = ("VTZERO_STATE_DIR", "VTZERO_VLM_URL", "VTZERO_VLM_MODEL", "VTZERO_API_TOKEN")


def test_the_loader_applies_the_environment_once(tmp_path, monkeypatch):
    for name in ENVIRONMENT:
        monkeypatch.delenv(name, raising=False)
    path = tmp_path / "c.toml"
    path.write_text('[runtime]\nstate_dir = "here"\n[vlm]\nbase_url = "http://a:1/v1"\n'
                    'model = "m"\n')
    plain = load_config(path)
    assert (plain.runtime.state_dir, plain.vlm.base_url, plain.api.token) == (
        "here", "http://a:1/v1", "")
    monkeypatch.setenv("VTZERO_STATE_DIR", "/var/lib/vtzero")
    monkeypatch.setenv("VTZERO_VLM_URL", " http://b:2/v1/ ")
    monkeypatch.setenv("VTZERO_VLM_MODEL", "other")
    monkeypatch.setenv("VTZERO_API_TOKEN", "t" * 20)
    cfg = load_config(path)
    assert cfg.runtime.state_dir == "/var/lib/vtzero"
    assert (cfg.vlm.base_url, cfg.vlm.model) == ("http://b:2/v1", "other")
    assert cfg.api.token == "t" * 20
    # Built from a table, a configuration is what the table says.
    assert config_from_dict({}).runtime.state_dir == "state"


def test_a_token_file_wins_over_the_environment(tmp_path):
    cfg = apply_environment(config_from_dict({"api": {"token_file": str(tmp_path / "t")}}),
                            {"VTZERO_API_TOKEN": "t" * 20})
    assert cfg.api.token == "" and cfg.api.token_file == str(tmp_path / "t")
    given = config_from_dict({"api": {"token": "f" * 20}})
    assert apply_environment(given, {"VTZERO_API_TOKEN": "t" * 20}).api.token == "f" * 20


def test_a_bad_override_names_the_variable():
    with pytest.raises(ConfigError, match=r"\$VTZERO_VLM_URL.*must name the model"):
        apply_environment(config_from_dict({}), {"VTZERO_VLM_URL": "http://b:2/v1"})
    with pytest.raises(ConfigError, match=r"\$VTZERO_VLM_URL.*base_url = 'ftp://b/v1'"):
        apply_environment(config_from_dict({}), {"VTZERO_VLM_URL": "ftp://b/v1",
                                                 "VTZERO_VLM_MODEL": "m"})
