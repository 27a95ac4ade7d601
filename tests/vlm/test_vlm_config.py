"""VLMConfig: defaults, loading through edge.core.config.from_dict, errors naming the field."""

import pytest

from edge.core.config import from_dict
from edge.core.errors import ConfigError
from edge.vlm.client import VLMConfig


def test_defaults_mean_no_vlm_and_are_valid():
    cfg = VLMConfig()
    cfg.validate("vlm")
    assert not cfg.configured and cfg.mode == "vision_tactile" and cfg.seed == 0
    assert cfg.api_key_env == "VTZERO_VLM_API_KEY"
    assert cfg.structured_output == "json_schema"


def test_loads_from_a_toml_table(tmp_path):
    cfg = from_dict(VLMConfig, {
        "base_url": "http://localhost:11434/v1", "model": "qwen2.5vl:7b",
        "mode": "vision_only", "api_key_file": str(tmp_path / "key"), "seed": 7,
        "total_timeout_s": 30, "max_retries": 2,
    }, "vlm")
    assert cfg.configured and cfg.mode == "vision_only" and cfg.total_timeout_s == 30.0
    assert cfg.api_key_file == tmp_path / "key"


@pytest.mark.parametrize(
    ("raw", "needle"),
    [
        ({"base_url": "localhost:11434"}, "vlm.base_url = 'localhost:11434'"),
        ({"base_url": "ftp://x/v1", "model": "m"}, "http:// or https://"),
        ({"base_url": "http://user:pw@x/v1", "model": "m"}, "must not hold credentials"),
        ({"base_url": "http://x/v1"}, "vlm.model = ''"),
        ({"mode": "smell"}, "vlm.mode = 'smell'"),
        ({"structured_output": "xml"}, "vlm.structured_output = 'xml'"),
        ({"structured_output": "json"}, "'json_schema', 'json_object', 'none'"),
        ({"seed": -1}, "vlm.seed = -1"),
        ({"connect_timeout_s": 0}, "vlm.connect_timeout_s = 0"),
        ({"connect_timeout_s": 10.0, "total_timeout_s": 5.0}, "vlm.total_timeout_s = 5.0"),
        ({"max_retries": 11}, "vlm.max_retries = 11"),
        ({"backoff_base_s": 2.0, "backoff_cap_s": 1.0}, "vlm.backoff_cap_s = 1.0"),
        ({"max_image_side_px": 10}, "vlm.max_image_side_px = 10"),
        ({"max_image_bytes": 100}, "vlm.max_image_bytes = 100"),
        ({"max_response_bytes": 10}, "vlm.max_response_bytes = 10"),
        ({"api_key_env": "MY-KEY"}, "vlm.api_key_env = 'MY-KEY'"),
        ({"api_key": "sk-123"}, "unknown key 'vlm.api_key'"),
    ],
)
def test_bad_values_name_the_field(raw, needle):
    with pytest.raises(ConfigError) as err:
        from_dict(VLMConfig, raw, "vlm")
    assert needle in str(err.value)
    assert "pw" not in str(err.value)
