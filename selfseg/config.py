"""Typed configs: dataclasses loaded from YAML or dicts, with unknown keys rejected.

Every stage and method declares its settings as a (possibly nested) dataclass. ``load_config``
builds one from defaults, an optional YAML file and ``key.sub=value`` overrides (values are
parsed as YAML scalars), checking types and refusing keys the dataclass does not declare.
``config_hash`` is the short hash of the resolved config, recorded with every output.
"""
from __future__ import annotations

import dataclasses
import difflib
import os
import re
import types
import typing
from pathlib import Path
from typing import Any, Iterable, TypeVar

import yaml

from selfseg.fileio import hash_json

T = TypeVar("T")
_FLOAT_LITERAL = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")  # exponent forms YAML 1.1 leaves as strings


class ConfigError(ValueError):
    """A config key or value is invalid; the message names the key (and file, if any)."""


def _suggest(key: str, choices: Iterable[str]) -> str:
    close = difflib.get_close_matches(key, list(choices), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _coerce(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping for {tp.__name__}, got {value!r}")
        return from_dict(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"{where}: invalid value {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: {value!r} is not one of {list(args)}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        inner = args[0] if args else Any
        out = [_coerce(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        kt, vt = args or (Any, Any)
        return {_coerce(k, kt, where): _coerce(v, vt, f"{where}.{k}") for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str) and _FLOAT_LITERAL.fullmatch(value.strip()):
            return float(value)  # YAML 1.1 reads 1e-6 (no dot) as a string
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{where}: expected a string, got {value!r}")
    if tp is Path:
        if isinstance(value, (str, os.PathLike)):
            return Path(value)
        raise ConfigError(f"{where}: expected a path, got {value!r}")
    return value


def from_dict(cls: type[T], data: dict, where: str = "") -> T:
    """Build dataclass ``cls`` from a mapping; missing keys keep their defaults, unknown keys raise."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where or cls.__name__}: expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    kwargs = {}
    for key, value in data.items():
        path = f"{where}.{key}" if where else str(key)
        if key not in fields:
            raise ConfigError(f"unknown config key {path!r}{_suggest(str(key), fields)}; "
                              f"{cls.__name__} has: {', '.join(fields)}")
        kwargs[key] = _coerce(value, hints[key], path)
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where or cls.__name__}: {e}") from None
    return obj


def to_dict(cfg: Any) -> dict:
    """Plain-JSON dict of a config dataclass (paths as strings, tuples as lists)."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {str(k): conv(x) for k, x in v.items()}
        if isinstance(v, Path):
            return str(v)
        return v

    return conv(cfg)


def config_hash(cfg: Any) -> str:
    """Short, stable hash of a resolved config."""
    return hash_json(to_dict(cfg) if dataclasses.is_dataclass(cfg) else cfg)


def parse_overrides(overrides: Iterable[str]) -> dict:
    """['a.b=3', 'c=[1, 2]'] → {'a': {'b': 3}, 'c': [1, 2]} (values parsed as YAML)."""
    out: dict = {}
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like key=value or key.sub=value")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as e:
            raise ConfigError(f"override {item!r}: value is not valid YAML ({e})") from None
        node = out
        parts = key.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {item!r} conflicts with an earlier override")
        node[parts[-1]] = value
    return out


def _merge(base: dict, extra: dict) -> dict:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


# Top-level YAML sections about how a command runs, not what it computes (e.g. ``executor:``, see
# :mod:`selfseg.executor`): never part of a config, so they change no hash; read them with :func:`load_section`.
RUN_SECTIONS = ("executor",)


def _read_yaml(p: Path) -> dict:
    """The mapping in YAML file ``p``; ConfigError naming the file if it is missing or not a mapping."""
    try:
        loaded = yaml.safe_load(p.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: not valid YAML ({e})") from None
    if not isinstance(loaded, dict):
        raise ConfigError(f"{p}: a config file must hold a mapping")
    return loaded


def load_config(cls: type[T], path: str | os.PathLike | None = None, overrides: Iterable[str] = (),
                base: dict | None = None) -> T:
    """Defaults of ``cls`` ← ``base`` ← YAML file ``path`` (less its :data:`RUN_SECTIONS`) ← ``key=value``
    overrides, type-checked."""
    data = to_dict(cls())
    if base:
        data = _merge(data, base)
    if path is not None:
        p = Path(path)
        loaded = {k: v for k, v in _read_yaml(p).items() if k not in RUN_SECTIONS}
        try:
            from_dict(cls, _merge(data, loaded))  # validate the file alone, to name it in errors
        except ConfigError as e:
            raise ConfigError(f"{p}: {e}") from None
        data = _merge(data, loaded)
    data = _merge(data, parse_overrides(overrides))
    return from_dict(cls, data)


def load_section(cls: type[T], path: str | os.PathLike | None, section: str) -> T:
    """The run section ``section`` (one of :data:`RUN_SECTIONS`) of YAML file ``path`` as ``cls``: defaults
    for keys it leaves out, ConfigError naming the file for unknown keys or bad values."""
    if path is None:
        return cls()
    p = Path(path)
    try:
        return from_dict(cls, _read_yaml(p).get(section) or {}, section)
    except ConfigError as e:
        raise ConfigError(f"{p}: {e}") from None
