"""Loading nested frozen config dataclasses from YAML files and ``key=value`` overrides.

Every component keeps its own frozen config dataclass beside it (``FieldConfig`` in ``field.py`` ...);
this module only knows how to fill such a tree from plain data, checking every key and type, so a typo in
a YAML file or a ``--set`` flag is a clear :class:`ConfigError` naming the dotted key, never silently ignored.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from .errors import ConfigError

__all__ = ["config_from_dict", "config_to_dict", "load_config", "parse_overrides", "apply_overrides",
           "merge_dicts", "read_config_file"]

T = TypeVar("T")


def _coerce(value: Any, tp: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(key, f"must be one of {list(typing.get_args(tp))}, got {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, key)
            except ConfigError as e:
                errors.append(e.problem)
        raise ConfigError(key, "; ".join(errors))
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(key, f"expected a list, got {value!r}")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(key, f"expected {len(args)} values, got {len(value)}")
            pairs = enumerate(zip(value, args, strict=True))
            return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in pairs)
        inner = args[0] if args else Any
        seq = [_coerce(v, inner, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(seq) if origin is tuple else seq
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(key, f"expected a mapping of {tp.__name__} fields, got {value!r}")
        return config_from_dict(tp, value, prefix=key + ".")
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(key, f"expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, f"expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str):  # YAML 1.1 reads "1e6" (no dot) as a string; accept it as a number
            try:
                value = float(value)
            except ValueError:
                raise ConfigError(key, f"expected a number, got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(key, f"expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(key, f"expected a string, got {value!r}")
        return value
    return value


def _unknown_key_message(key: str, value: Any, fields: dict[str, dataclasses.Field]) -> str:
    """What to say of an unknown key: the nearest valid one, or how to nest a dotted key, then the valid keys."""
    head, dot, rest = key.partition(".")
    if dot and head in fields:  # {"mapping.iters": 10}: the CLI's --set spelling in a mapping (HTTP, YAML)
        nested: Any = value
        for part in reversed(key.split(".")):
            nested = {part: nested}
        hint = (f"unknown key; dotted names are for --set overrides: in a mapping (YAML, JSON) nest them, "
                f"e.g. {json.dumps(nested, default=str)}")
    else:
        near = difflib.get_close_matches(key, list(fields), n=1, cutoff=0.6)
        hint = f"unknown key; did you mean {near[0]!r}?" if near else "unknown key"
    return f"{hint}; valid keys here: {sorted(fields)}"


def config_from_dict(cls: type[T], data: dict[str, Any], prefix: str = "") -> T:
    """Build dataclass ``cls`` from ``data``; missing keys keep their defaults, unknown keys raise."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(prefix + unknown[0], _unknown_key_message(unknown[0], data[unknown[0]], fields))
    kwargs = {name: _coerce(v, hints[name], prefix + name) for name, v in data.items()}
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as e:
        if isinstance(e, ConfigError):
            raise
        raise ConfigError(prefix.rstrip(".") or cls.__name__, str(e)) from e
    return obj


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict of a config dataclass (tuples become lists), suitable for YAML/JSON."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        return v

    return conv(cfg)


def parse_overrides(items: list[str] | tuple[str, ...]) -> dict[str, Any]:
    """Parse ``["mapping.iters=10", "field.use_color=false"]`` into a nested dict (values parsed as YAML)."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(item, "override must look like key=value (e.g. mapping.iters=20)")
        key, raw = item.split("=", 1)
        key = key.strip()
        if not key:
            raise ConfigError(item, "empty key in override")
        value = yaml.safe_load(raw) if raw.strip() else ""
        node = out
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(key, "conflicting overrides")
        node[parts[-1]] = value
    return out


def merge_dicts(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Nested merge of plain config dicts: ``over`` wins key by key, sub-mappings are merged (new dict)."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge_dicts(out[k], v)
        else:
            out[k] = v
    return out




def apply_overrides(cfg: T, overrides: dict[str, Any] | list[str]) -> T:
    """Return a new config with ``overrides`` (nested dict or ``key=value`` strings) applied."""
    if isinstance(overrides, (list, tuple)):
        overrides = parse_overrides(overrides)
    return config_from_dict(type(cfg), merge_dicts(config_to_dict(cfg), overrides))


def load_config(cls: type[T], path: str | Path | None = None, overrides: list[str] | None = None) -> T:
    """Load ``cls`` from a YAML file (optional) and apply ``key=value`` overrides.

    A YAML file may start with ``base: other.yaml`` (relative to itself) to inherit from another preset.
    """
    data: dict[str, Any] = {}
    if path is not None:
        data = _read_yaml_with_base(Path(path))
    cfg = config_from_dict(cls, data)
    if overrides:
        cfg = apply_overrides(cfg, list(overrides))
    return cfg


def read_config_file(path: str | Path) -> dict[str, Any]:
    """The plain dict of a YAML config file with its ``base:`` chain merged in (keys not yet checked)."""
    return _read_yaml_with_base(Path(path))


def _read_yaml_with_base(path: Path, depth: int = 0) -> dict[str, Any]:
    if depth > 8:
        raise ConfigError(str(path), "too many nested 'base:' references")
    if not path.is_file():
        raise ConfigError(str(path), "config file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(str(path), f"invalid YAML: {e}") from e
    if not isinstance(data, dict):
        raise ConfigError(str(path), "top level must be a mapping")
    base = data.pop("base", None)
    if base is not None:
        data = merge_dicts(_read_yaml_with_base((path.parent / base).resolve(), depth + 1), data)
    return data
