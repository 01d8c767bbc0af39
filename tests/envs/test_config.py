"""Typed configs (envs/config.py): boolean keys take booleans only."""

from dataclasses import dataclass, field

import pytest

from envs.config import ConfigError, load_config


@dataclass
class _Inner:
    enabled: bool = False
    gain: float = 1.0


@dataclass
class _Outer:
    flag: bool = True
    inner: _Inner = field(default_factory=_Inner)


@pytest.mark.parametrize("value", ["3", "1", "0", "2.5", "'true'", "maybe"])
def test_a_boolean_key_refuses_numbers_and_strings_by_name(value):
    # OmegaConf alone reads any integer as a boolean (3 -> true); the loader names the key instead.
    with pytest.raises(ConfigError, match=r"config key 'inner\.enabled' \(from overrides\): must be true or false"):
        load_config(_Outer, overrides=[f"inner.enabled={value}"])


def test_booleans_from_yaml_files_overrides_and_mappings_pass(tmp_path):
    assert load_config(_Outer, overrides=["inner.enabled=true", "flag=false"]) == _Outer(False, _Inner(True))
    assert load_config(_Outer, overrides=["inner.enabled=yes"]).inner.enabled is True  # YAML's own boolean words
    assert load_config(_Outer, overrides={"inner.enabled": True, "inner.gain": 2}).inner == _Inner(True, 2.0)
    path = tmp_path / "c.yaml"
    path.write_text("flag: false\ninner:\n  enabled: true\n")
    assert load_config(_Outer, files=[path]) == _Outer(False, _Inner(True))
    path.write_text("inner:\n  enabled: 1\n")
    with pytest.raises(
        ConfigError, match=rf"config key 'inner\.enabled' \(from {path}\): must be true or false, got 1"
    ):
        load_config(_Outer, files=[path])
    with pytest.raises(ConfigError, match=r"config key 'flag' \(from overrides\): must be true or false, got 2"):
        load_config(_Outer, overrides={"flag": 2})
