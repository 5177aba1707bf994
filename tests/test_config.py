"""Config loading: unknown keys are errors, missing keys take defaults, values are type-checked, enumerations
(``Literal``) are checked against their allowed values, and what the loader returns is frozen."""

from __future__ import annotations

import dataclasses
from pathlib import Path
import subprocess
import sys
import typing
from typing import Literal, Optional

import pytest

from services.app.supervisor import ServiceSpec
from services.app.system_config import SystemConfig, load_system_config
from shared.config import (ConfigError, allowed_values, describe, from_dict, load_yaml, override, param,
                           parse_override, to_dict)


@dataclasses.dataclass(frozen=True)
class Inner:
    rate_hz: float = param(10.0, "a rate", "Hz")
    names: tuple[str, ...] = param(("a",), "some names")
    kinds: tuple[Literal["x", "y"], ...] = param(("x",), "enumerations in a list")


@dataclasses.dataclass(frozen=True)
class Outer:
    count: int = param(3, "a count")
    mode: str = param("peer", "a mode")
    flag: bool = param(False, "a flag")
    inner: Inner = param(Inner(), "nested section")
    budget_ms: float | None = param(None, "optional budget", "ms")
    shape: Literal["box", "ball"] = param("box", "an enumeration")
    level: Optional[Literal[1, 2]] = param(None, "an optional enumeration")
    items: tuple[Inner, ...] = param((), "a list of sections")


def test_missing_keys_take_defaults_and_nested_sections_are_built():
    cfg = from_dict(Outer, {"inner": {"rate_hz": 20}})
    assert cfg.count == 3 and cfg.inner.rate_hz == 20.0 and isinstance(cfg.inner.rate_hz, float)
    assert cfg.inner.names == ("a",)


@pytest.mark.parametrize("data, fragment", [
    ({"cuont": 1}, "unknown key(s) ['cuont']"),
    ({"inner": {"rate": 1}}, "inner: unknown key(s) ['rate']"),
    ({"count": "three"}, "count: expected an integer"),
    ({"count": True}, "count: expected an integer"),
    ({"flag": "yes"}, "flag: expected true or false"),
    ({"inner": {"names": "a"}}, "inner.names: expected a list"),
    ({"inner": 5}, "inner: expected a mapping"),
    ({"shape": "cube"}, "shape: 'cube' is not one of the allowed values ['box', 'ball']"),
    ({"shape": None}, "shape: None is not one of the allowed values"),
    ({"level": 3}, "level: 3 is not one of the allowed values [1, 2] (or null)"),
    ({"level": True}, "level: True is not one of the allowed values [1, 2]"),  # bool is an int, but not 1
    ({"inner": {"kinds": ["x", "z"]}}, "inner.kinds[1]: 'z' is not one of the allowed values ['x', 'y']"),
    ({"items": [{}, {"kinds": ["w"]}]}, "items[1].kinds[0]: 'w' is not one of the allowed values ['x', 'y']"),
])
def test_bad_values_name_the_key(data, fragment):
    with pytest.raises(ConfigError) as exc:
        from_dict(Outer, data)
    assert fragment in str(exc.value)


def test_optional_field_accepts_none_and_numbers():
    assert from_dict(Outer, {"budget_ms": None}).budget_ms is None
    assert from_dict(Outer, {"budget_ms": 5}).budget_ms == 5.0


def test_enumerations_accept_their_values_in_optionals_lists_and_nested_sections():
    cfg = from_dict(Outer, {"shape": "ball", "level": 2, "inner": {"kinds": ["y", "x"]}, "items": [{"kinds": ["y"]}]})
    assert cfg.shape == "ball" and cfg.level == 2 and cfg.inner.kinds == ("y", "x") and cfg.items[0].kinds == ("y",)
    assert from_dict(Outer, {"level": None}).level is None
    assert allowed_values(typing.get_type_hints(Outer)["level"]) == (1, 2)
    assert allowed_values(typing.get_type_hints(Inner)["kinds"]) == ("x", "y")
    assert allowed_values(int) is None


def test_loader_refuses_config_classes_that_are_not_frozen():
    @dataclasses.dataclass
    class Loose:
        x: int = param(1, "x")

    with pytest.raises(TypeError, match="frozen"):
        from_dict(Loose, {})


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


def test_extends_merges_the_file_on_top_of_the_one_it_names(tmp_path):
    (tmp_path / "base.yaml").write_text("count: 7\nmode: router\ninner:\n  rate_hz: 2.5\n  names: [b]\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "c.yaml").write_text("extends: ../base.yaml\ninner:\n  rate_hz: 4.0\n")
    cfg = load_yaml(Outer, tmp_path / "sub" / "c.yaml", {"count": 9})  # relative to the file, overrides on top
    assert (cfg.count, cfg.mode, cfg.inner.rate_hz, cfg.inner.names) == (9, "router", 4.0, ("b",))
    (tmp_path / "base.yaml").write_text("extends: sub/c.yaml\n")
    with pytest.raises(ConfigError, match="circle"):
        load_yaml(Outer, tmp_path / "sub" / "c.yaml")
    (tmp_path / "c2.yaml").write_text("extends: nowhere.yaml\n")
    with pytest.raises(ConfigError, match="not found.*extended by"):
        load_yaml(Outer, tmp_path / "c2.yaml")


def test_every_shipped_config_gets_the_stereo_network_that_holds_on_real_photographs():
    """No shipped config gives a user the network trained on rendered rooms only (stereo.pt): the default is the
    SGBM-guided one, and the real-camera config is the demo's pipeline."""
    from services.depth.weights import DEFAULT_STEREO, WEIGHTS_DIR, weights_path

    assert DEFAULT_STEREO == "stereo_refine.pt" and (WEIGHTS_DIR / DEFAULT_STEREO).is_file()
    demo, real = load_system_config("configs/demo.yaml"), load_system_config("configs/real.yaml")
    for path in sorted(p for p in Path("configs").rglob("*.yaml") if p.name != "budgets.yaml"):  # budgets: bench limits
        cfg = load_system_config(str(path))
        assert weights_path(cfg.depth.stereo_weights, DEFAULT_STEREO) == WEIGHTS_DIR / "stereo_refine.pt", path
    assert real == demo


def test_the_small_computer_config_is_the_demo_cheaper_and_without_the_viewer():
    demo, small = load_system_config("configs/demo.yaml"), load_system_config("configs/small.yaml")
    assert [s.argv[0] for s in small.supervisor.services] == ["frontend", "backend", "depth", "mapping"]
    assert not small.loop.enabled and not small.frontend.orb_descriptors  # the descriptors serve loop closure only
    assert small.depth.rate_hz < demo.depth.rate_hz and small.mapping.mesh_period_s > demo.mapping.mesh_period_s
    assert small.frontend.max_features_per_camera < demo.frontend.max_features_per_camera
    assert small.backend.window_keyframes < demo.backend.window_keyframes
    # everything else is the demo's: the depth network, the map, the rig
    assert small.depth.stereo_weights == demo.depth.stereo_weights and small.mapping.sensor == demo.mapping.sensor
    assert small.rig == demo.rig and small.o2p == demo.o2p


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


# ----------------------------------------------------------------------------- enumerations of the system config

def _config_classes(cls: type, path: tuple = ()) -> list[tuple[tuple, type]]:
    """(path, class) of ``cls`` and every config dataclass inside it, sections and list items ("[]") alike."""
    out = [(path, cls)]
    for f in dataclasses.fields(cls):
        tp = typing.get_type_hints(cls)[f.name]
        if dataclasses.is_dataclass(tp):
            out += _config_classes(tp, (*path, f.name))
        elif typing.get_origin(tp) in (list, tuple):
            items = [a for a in typing.get_args(tp) if a is not Ellipsis]
            if len(items) == 1 and dataclasses.is_dataclass(items[0]):
                out += _config_classes(items[0], (*path, f.name, "[]"))
    return out


def _data_at(path: tuple, value) -> dict:
    """Plain data setting ``value`` at ``path``; a list item ("[]") gets the fields a service spec needs."""
    node = value
    for i in range(len(path) - 1, -1, -1):
        if path[i] == "[]":
            node = [{"name": "x", "argv": ["x"], **node}]
        else:
            node = {path[i]: node}
    return node


def _value_at(cfg, path: tuple):
    for part in path:
        cfg = cfg[0] if part == "[]" else getattr(cfg, part)
    return cfg


def _dotted(path: tuple) -> str:
    return ".".join(path).replace(".[]", "[0]")


def _enum_fields() -> list[tuple[tuple, tuple]]:
    """(path of the field, allowed values) of every Literal field of every config dataclass in SystemConfig."""
    out = []
    for path, cls in _config_classes(SystemConfig):
        for f in dataclasses.fields(cls):
            values = allowed_values(typing.get_type_hints(cls)[f.name])
            if values is not None:
                out.append(((*path, f.name), values))
    return out


def test_every_config_class_is_frozen_and_round_trips():
    for path, cls in _config_classes(SystemConfig):
        assert cls.__dataclass_params__.frozen, f"{cls.__name__} ({_dotted(path) or 'root'}) is not frozen"
    assert from_dict(SystemConfig, to_dict(SystemConfig())) == SystemConfig()


def test_every_enumeration_rejects_a_value_outside_its_set_and_accepts_its_own():
    fields = _enum_fields()
    names = {_dotted(p) for p, _ in fields}
    assert {"mapping.pose_source", "mapping.sensor.sigma_model", "depth.method", "transport.mode", "player.mode",
            "supervisor.services[0].restart"} <= names, names
    assert len(fields) >= 13
    for path, values in fields:
        key = _dotted(path)
        with pytest.raises(ConfigError) as exc:
            from_dict(SystemConfig, _data_at(path, "not-a-value"))
        msg = str(exc.value)
        assert key in msg and "'not-a-value'" in msg and all(repr(v) in msg for v in values), msg
        for v in values:
            assert _value_at(from_dict(SystemConfig, _data_at(path, v)), path) == v
        assert _value_at(from_dict(SystemConfig, _data_at(path[:-1], {})), path) in values, f"{key}: default"


@pytest.mark.parametrize("override_text, fragment", [
    ("mapping.pose_source=gt", "mapping.pose_source: 'gt' is not one of the allowed values ['estimator', 'frame']"),
    ("mapping.sensor.sigma_model=foo",
     "mapping.sensor.sigma_model: 'foo' is not one of the allowed values ['input', 'linear', 'quadratic']"),
])
def test_set_with_a_bad_enumeration_is_refused(override_text, fragment):
    with pytest.raises(ConfigError) as exc:
        load_system_config(None, [override_text])
    assert fragment in str(exc.value)


def test_cli_refuses_a_bad_enumeration_with_exit_code_2():
    proc = subprocess.run([sys.executable, "-m", "services.app.cli", "config", "--set", "mapping.pose_source=gt"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stdout == ""
    assert "mapping.pose_source: 'gt' is not one of the allowed values ['estimator', 'frame']" in proc.stderr


def test_yaml_with_a_bad_enumeration_names_the_file_and_the_key(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("mapping:\n  sensor:\n    sigma_model: foo\n")
    with pytest.raises(ConfigError) as exc:
        load_system_config(path)
    msg = str(exc.value)
    assert str(path) in msg and "mapping.sensor.sigma_model: 'foo'" in msg and "'quadratic'" in msg


def test_defaults_list_the_allowed_values_of_every_enumeration():
    text = describe(SystemConfig)
    assert "pose_source: estimator  # " in text and "(allowed: estimator, frame)" in text
    for path, values in _enum_fields():
        line = next(l for l in text.splitlines() if l.strip().startswith(f"{path[-1]}:") and "(allowed:" in l
                    and all(str(v) in l.split("(allowed:")[1] for v in values))
        assert line


# ----------------------------------------------------------------------------- frozen after loading

def test_a_loaded_config_cannot_be_mutated():
    cfg = load_system_config(None, ["supervisor.services=[{name: a, argv: [frontend]}]"])
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.rig.calibration = "/somewhere"
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.mapping.sensor.sigma_model = "linear"
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.supervisor.services[0].restart = "never"
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.mapping = None
    with pytest.raises(AttributeError):  # lists are tuples
        cfg.transport.connect.append("tcp/10.0.0.1:7447")
    with pytest.raises(TypeError):
        cfg.supervisor.services[0] = ServiceSpec(name="b", argv=("backend",))


def test_override_gives_a_checked_changed_copy():
    cfg = load_system_config(None, ["transport.namespace=sigmaslam/r2"])
    new = override(cfg, {"rig.calibration": "/data/V1_01", "supervisor.start_router": False,
                         "supervisor.services": [ServiceSpec(name="a", argv=["frontend"], restart="never")]})
    assert new.rig.calibration == "/data/V1_01" and not new.supervisor.start_router
    assert new.supervisor.services == (ServiceSpec(name="a", argv=("frontend",), restart="never"),)
    assert new.transport.namespace == "sigmaslam/r2" and new.mapping == cfg.mapping
    assert cfg.rig.calibration == "" and cfg.supervisor.services == () and cfg.supervisor.start_router
    with pytest.raises(ConfigError, match="mapping.pose_source: 'gt' is not one of the allowed values"):
        override(cfg, {"mapping.pose_source": "gt"})
    with pytest.raises(ConfigError, match=r"supervisor.services\[0\].restart: 'sometimes'"):
        override(cfg, {"supervisor.services": [ServiceSpec(name="a", argv=["frontend"], restart="sometimes")]})
    with pytest.raises(ConfigError, match="unknown key"):
        override(cfg, {"rig.calib": "/x"})


def test_the_run_player_waits_for_the_heartbeats_its_services_send(tmp_path):
    """`sigmaslam run` starts the player with --wait-for naming each service's node (its heartbeat), whatever the
    service is called in the config: a service named 'fe' runs the frontend node, the recorder's node is 'recorder'."""
    from services.app.run_pipeline import pipeline_services

    cfg = load_system_config(None, ["supervisor.services=[{name: fe, argv: [frontend]}, {name: be, argv: [backend]}]"])
    services = pipeline_services(cfg, "DATA", tmp_path, rate=1.0, record=True, player_args=[])
    assert [s.name for s in services] == ["fe", "be", "recorder", "player"]
    player = services[-1].argv
    assert player[player.index("--wait-for") + 1] == "frontend,backend,recorder"
    plain = pipeline_services(load_system_config(None, []), "DATA", tmp_path, rate=0.0, record=False,
                              player_args=[])
    argv = plain[-1].argv
    assert argv[argv.index("--wait-for") + 1] == "frontend,backend" and "--lockstep" in argv
