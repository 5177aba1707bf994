"""Config dataclasses loaded from YAML.

Every component declares one frozen dataclass whose fields are made with :func:`param`, which records a
docstring and a unit for the field. :func:`from_dict` is the one loader that builds an instance from plain
data: unknown keys are errors (with the dotted path), missing keys take the defaults, values are checked
against the field's type, enumerations (``typing.Literal[...]``, also inside ``Optional``, lists and tuples)
against their allowed values, and nested sections are built the same way. Config classes must be frozen
dataclasses (``@dataclasses.dataclass(frozen=True)``, lists as ``tuple[X, ...]``), so a loaded config
cannot be changed by accident; :func:`override` gives a changed copy, checked by the loader again.
:func:`to_dict` gives the resolved config back as plain data (written into recordings and output folders).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    """A config file or value that cannot be used; the message names the offending key."""


def param(default: Any, doc: str, unit: str | None = None, **kwargs: Any) -> Any:
    """A config field with a default, a one-line docstring and a unit (``None`` for unitless).

    Mutable defaults (list, dict, dataclass instances) are copied per instance.
    """
    meta = {"doc": doc, "unit": unit}
    if isinstance(default, (list, dict)) or dataclasses.is_dataclass(default):
        proto = default
        return dataclasses.field(default_factory=lambda: _copy(proto), metadata=meta, **kwargs)
    return dataclasses.field(default=default, metadata=meta, **kwargs)


def _copy(value: Any) -> Any:
    import copy

    return copy.deepcopy(value)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp)


def _coerce(value: Any, tp: Any, path: str) -> Any:
    """Check ``value`` against the annotation ``tp`` and convert where lossless (int -> float, list -> tuple)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        if len(options) == 1:  # Optional[X]: X's own error is the clearest
            try:
                return _coerce(value, options[0], path)
            except ConfigError as exc:
                raise ConfigError(f"{exc} (or null)") from None
        for option in options:
            try:
                return _coerce(value, option, path)
            except ConfigError:
                pass
        raise ConfigError(f"{path}: {value!r} matches none of {[_type_name(a) for a in args]}")
    if origin is typing.Literal:
        # bool is an int and 1 == 1.0: the type must match too
        if not any(value == a and type(value) is type(a) for a in args):
            raise ConfigError(f"{path}: {value!r} is not one of the allowed values {list(args)}")
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):  # built in code: checked like data
            value = to_dict(value)
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a mapping for {tp.__name__}, got {type(value).__name__}")
        return from_dict(tp, value, path)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected a list, got {type(value).__name__}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{path}: expected {len(args)} items, got {len(value)}")
            return tuple(_coerce(v, a, f"{path}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        item_tp = args[0] if args else Any
        items = [_coerce(v, item_tp, f"{path}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a mapping, got {type(value).__name__}")
        key_tp, val_tp = args if args else (Any, Any)
        return {_coerce(k, key_tp, f"{path}.{k}"): _coerce(v, val_tp, f"{path}.{k}") for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {value!r}")
        return value
    if isinstance(tp, type) and not isinstance(value, tp):
        raise ConfigError(f"{path}: expected {tp.__name__}, got {type(value).__name__}")
    return value


def from_dict(cls: type[T], data: dict[str, Any] | None, path: str = "") -> T:
    """Build config dataclass ``cls`` from ``data``; unknown keys and bad values raise :class:`ConfigError`.

    ``cls`` must be a frozen dataclass (TypeError otherwise): what the loader returns cannot be mutated.
    """
    if not dataclasses.is_dataclass(cls) or not cls.__dataclass_params__.frozen:  # type: ignore[attr-defined]
        raise TypeError(f"{getattr(cls, '__name__', cls)}: config classes must be frozen dataclasses "
                        "(@dataclasses.dataclass(frozen=True)) so that loaded configs cannot be changed")
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{path or cls.__name__}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        where = path or cls.__name__
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known keys: {sorted(fields)}")
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(value, hints[name], f"{path}.{name}" if path else name)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{path or cls.__name__}: {exc}") from exc


def read_yaml(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The mapping of a YAML config file. A top-level ``extends: OTHER.yaml`` (relative to the file) starts from
    that file's mapping, and this file's keys are merged on top."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}" + (f" (extended by {_seen[-1]})" if _seen else ""))
    if path.resolve() in _seen:
        raise ConfigError(f"{path}: 'extends' goes round in a circle ({' -> '.join(map(str, _seen))})")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file is a mapping of sections, not {type(data).__name__}")
    base = data.pop("extends", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError(f"{path}: 'extends' names one YAML file, got {base!r}")
    return merge(read_yaml(path.parent / base, (*_seen, path.resolve())), data)


def load_yaml(cls: type[T], path: str | Path, overrides: dict[str, Any] | None = None) -> T:
    """Load ``cls`` from a YAML file (:func:`read_yaml`: ``extends`` included); ``overrides`` (nested mapping) is
    merged on top."""
    path = Path(path)
    data = read_yaml(path)
    if overrides:
        data = merge(data, overrides)
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    """Recursive merge of mappings; values of ``top`` win."""
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


def _nest(key: str, value: Any) -> dict[str, Any]:
    """``("a.b.c", 3)`` -> ``{"a": {"b": {"c": 3}}}``."""
    parts = key.strip().split(".")
    out: dict[str, Any] = {parts[-1]: value}
    for part in reversed(parts[:-1]):
        out = {part: out}
    return out


def parse_override(text: str) -> dict[str, Any]:
    """``"a.b.c=3"`` -> ``{"a": {"b": {"c": 3}}}`` (the value is parsed as YAML)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} is not of the form key.path=value")
    key, raw = text.split("=", 1)
    return _nest(key, yaml.safe_load(raw))


def override(cfg: T, changes: dict[str, Any]) -> T:
    """A copy of the config ``cfg`` with ``changes`` applied, built and checked by the loader.

    ``changes`` maps dotted keys to values given as plain data or config dataclasses, e.g.
    ``override(cfg, {"rig.calibration": "/data/V1_01", "supervisor.services": [ServiceSpec(...)]})``;
    a bad key or value raises :class:`ConfigError` as it would in a file.
    """
    extra: dict[str, Any] = {}
    for key, value in changes.items():
        extra = merge(extra, _nest(key, to_dict(value)))
    return from_dict(type(cfg), merge(to_dict(cfg), extra))


def to_dict(cfg: Any) -> Any:
    """Plain data (dicts, lists, scalars) of a config dataclass, e.g. for YAML or MCAP metadata."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: to_dict(v) for k, v in cfg.items()}
    return cfg


def to_yaml(cfg: Any) -> str:
    return yaml.safe_dump(to_dict(cfg), sort_keys=False)


def allowed_values(tp: Any) -> tuple | None:
    """The values allowed by a ``Literal`` annotation, also inside ``Optional``, lists and tuples; else None."""
    if typing.get_origin(tp) is typing.Literal:
        return typing.get_args(tp)
    for arg in typing.get_args(tp):
        if arg is not type(None) and arg is not Ellipsis and (values := allowed_values(arg)) is not None:
            return values
    return None


def _item_dataclass(tp: Any) -> type | None:
    """``X`` for ``list[X]`` / ``tuple[X, ...]`` of a config dataclass X."""
    if typing.get_origin(tp) in (list, tuple):
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        if len(args) == 1 and dataclasses.is_dataclass(args[0]):
            return args[0]
    return None


def describe(cls: type, indent: int = 0) -> str:
    """Documentation of a config dataclass: one line per field with default, docstring, unit and, for
    enumerations, the allowed values; nested sections (and the items of lists of sections) indented."""
    lines = []
    pad = "  " * indent
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        doc = f.metadata.get("doc", "")
        unit = f.metadata.get("unit")
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            lines.append(f"{pad}{f.name}:  # {doc}")
            lines.append(describe(tp, indent + 1))
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            default = to_dict(f.default_factory())  # type: ignore[misc]
        else:
            default = "<required>"
        unit_txt = f" [{unit}]" if unit else ""
        values = allowed_values(tp)
        allowed_txt = f" (allowed: {', '.join(map(str, values))})" if values is not None else ""
        default_txt = yaml.safe_dump(to_dict(default), default_flow_style=True).strip().removesuffix('...').strip()
        lines.append(f"{pad}{f.name}: {default_txt}  # {doc}{unit_txt}{allowed_txt}")
        if (item := _item_dataclass(tp)) is not None:
            lines.append(f"{pad}  # each item of {f.name}:")
            lines.append(describe(item, indent + 2))
    return "\n".join(lines)
