"""Config loading: unknown keys are errors, missing keys take defaults, values are type-checked."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest

from services.system_config import SystemConfig, load_system_config
from shared.config import ConfigError, describe, from_dict, load_yaml, param, parse_override, to_dict


@dataclasses.dataclass
class Inner:
    rate_hz: float = param(10.0, "a rate", "Hz")
    names: list[str] = param(["a"], "some names")


@dataclasses.dataclass
class Outer:
    count: int = param(3, "a count")
    mode: str = param("peer", "a mode")
    flag: bool = param(False, "a flag")
    inner: Inner = param(Inner(), "nested section")
    budget_ms: float | None = param(None, "optional budget", "ms")


def test_missing_keys_take_defaults_and_nested_sections_are_built():
    cfg = from_dict(Outer, {"inner": {"rate_hz": 20}})
    assert cfg.count == 3 and cfg.inner.rate_hz == 20.0 and isinstance(cfg.inner.rate_hz, float)
    assert cfg.inner.names == ["a"]


def test_mutable_defaults_are_not_shared():
    a, b = Outer(), Outer()
    a.inner.names.append("x")
    assert b.inner.names == ["a"]


@pytest.mark.parametrize("data, fragment", [
    ({"cuont": 1}, "unknown key(s) ['cuont']"),
    ({"inner": {"rate": 1}}, "inner: unknown key(s) ['rate']"),
    ({"count": "three"}, "count: expected an integer"),
    ({"count": True}, "count: expected an integer"),
    ({"flag": "yes"}, "flag: expected true or false"),
    ({"inner": {"names": "a"}}, "inner.names: expected a list"),
    ({"inner": 5}, "inner: expected a mapping"),
])
def test_bad_values_name_the_key(data, fragment):
    with pytest.raises(ConfigError) as exc:
        from_dict(Outer, data)
    assert fragment in str(exc.value)


def test_optional_field_accepts_none_and_numbers():
    assert from_dict(Outer, {"budget_ms": None}).budget_ms is None
    assert from_dict(Outer, {"budget_ms": 5}).budget_ms == 5.0


def test_yaml_file_round_trip_and_errors(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("count: 7\ninner:\n  rate_hz: 2.5\n")
    cfg = load_yaml(Outer, path)
    assert cfg.count == 7 and cfg.inner.rate_hz == 2.5
    assert from_dict(Outer, to_dict(cfg)) == cfg
    with pytest.raises(ConfigError, match="not found"):
        load_yaml(Outer, tmp_path / "missing.yaml")
    path.write_text("count: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_yaml(Outer, path)


def test_overrides():
    assert parse_override("a.b=3") == {"a": {"b": 3}}
    cfg = load_system_config(None, ["transport.namespace=sigmaslam/r2", "transport.shared_memory=false"])
    assert cfg.transport.namespace == "sigmaslam/r2" and cfg.transport.shared_memory is False
    with pytest.raises(ConfigError):
        parse_override("novalue")


def test_describe_documents_every_field_with_unit():
    text = describe(Outer)
    assert "rate_hz: 10.0  # a rate [Hz]" in text
    assert "budget_ms: null  # optional budget [ms]" in text
    for f in dataclasses.fields(SystemConfig):
        assert f.metadata.get("doc"), f"SystemConfig.{f.name} has no docstring"


def test_cli_rejects_unknown_key_with_exit_code_2():
    proc = subprocess.run([sys.executable, "-m", "services.app.cli", "config", "--set", "transport.bogus=1"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "unknown key(s) ['bogus']" in proc.stderr
