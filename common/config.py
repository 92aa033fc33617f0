"""Configuration: typed dataclass schemas, filled from YAML plus ``key=value`` overrides.

* A schema is a (nested) ``@dataclass``; each field may carry ``metadata={"help": ...}``,
  which ``--help`` and :func:`describe` print.
* Sources are applied in order: schema defaults → optional preset dict → YAML file →
  ``key=value`` overrides (dotted keys for nested sections, values parsed as YAML:
  ``mapper.vox_size=0.3``, ``edge.depth_limit=inf``, ``names=[a,b]``).
* An unknown key is an error that names the key and the closest valid one.
* Values are type-checked against the field annotation (int → float is allowed).
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from pathlib import Path
from typing import Any, Callable, Iterable, TypeVar

import yaml

_T = TypeVar("_T")


class ConfigError(ValueError):
    """A configuration problem, with a message that says which key and why."""


def _field_names(schema: type) -> list[str]:
    return [f.name for f in dataclasses.fields(schema)]


def all_keys(schema: type, prefix: str = "") -> list[str]:
    """Every dotted key of a schema (sections and leaves)."""
    out = []
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        k = prefix + f.name
        out.append(k)
        t = hints[f.name]
        if dataclasses.is_dataclass(t):
            out.extend(all_keys(typing.cast(type, t), k + "."))
    return out


def _unknown(key: str, schema: type, prefix: str) -> ConfigError:
    valid = [prefix + n for n in _field_names(schema)]
    close = difflib.get_close_matches(prefix + key, valid + all_keys(schema, prefix), n=1, cutoff=0.5)
    hint = f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(valid)}"
    return ConfigError(f"unknown config key '{prefix}{key}'{hint}")


def _coerce(value: Any, t: Any, key: str) -> Any:
    """Check/convert ``value`` to annotation ``t``."""
    origin = typing.get_origin(t)
    if t is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        return _coerce_union(value, t, key)
    if origin in (list, tuple):
        return _coerce_sequence(value, t, origin, key)
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"config key '{key}': expected a mapping, got {value!r}")
        return dict(value)
    if origin is typing.Literal:
        if value not in typing.get_args(t):
            choices = ", ".join(map(repr, typing.get_args(t)))
            raise ConfigError(f"config key '{key}': {value!r} is not one of {choices}")
        return value
    for scalar, coerce in _SCALARS:
        if t is scalar:
            return coerce(value, key)
    if dataclasses.is_dataclass(t):
        raise ConfigError(f"config key '{key}' is a section; set its keys, e.g. '{key}.<name>=...'")
    return value


def _coerce_union(value: Any, t: Any, key: str) -> Any:
    """``value`` as the first member of the union ``t`` it fits (None for an optional)."""
    args = typing.get_args(t)
    if value is None and type(None) in args:
        return None
    errors = []
    for a in args:
        if a is type(None):
            continue
        try:
            return _coerce(value, a, key)
        except ConfigError as e:
            errors.append(str(e))
    raise ConfigError(f"config key '{key}': {value!r} does not match {t}")


def _coerce_sequence(value: Any, t: Any, origin: type, key: str) -> list | tuple:
    """``value`` as the list / tuple annotation ``t`` (``origin`` list or tuple), item by item."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
        raise ConfigError(f"config key '{key}': expected a list, got {value!r}")
    args = typing.get_args(t)
    if origin is tuple and args and args[-1] is not Ellipsis:
        if len(args) != len(value):
            raise ConfigError(f"config key '{key}': expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True)))
    a = args[0] if args else Any
    seq = [_coerce(v, a, f"{key}[{i}]") for i, v in enumerate(value)]
    return tuple(seq) if origin is tuple else seq


def _coerce_bool(value: Any, key: str) -> bool:
    if isinstance(value, bool):
        return value
    raise ConfigError(f"config key '{key}': expected true/false, got {value!r}")


def _coerce_int(value: Any, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"config key '{key}': expected an integer, got {value!r}")
    return value


def _coerce_float(value: Any, key: str) -> float:
    if isinstance(value, str):          # "inf", "nan", and "1e-4" (YAML 1.1 reads a float without a dot as text)
        try:
            return float(value.strip())
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"config key '{key}': expected a number, got {value!r}")
    return float(value)


def _coerce_str(value: Any, key: str) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"config key '{key}': expected a string, got {value!r}")
    return value


def _coerce_path(value: Any, key: str) -> Path:
    if not isinstance(value, (str, Path)):
        raise ConfigError(f"config key '{key}': expected a path, got {value!r}")
    return Path(value)


#: the plain scalar annotations and their coercions
_SCALARS: tuple[tuple[type, Callable[[Any, str], Any]], ...] = (
    (bool, _coerce_bool), (int, _coerce_int), (float, _coerce_float), (str, _coerce_str), (Path, _coerce_path),
)


def merge(cfg: _T, data: dict | None, prefix: str = "") -> _T:
    """Return a copy of dataclass instance ``cfg`` with the (nested) dict ``data`` applied."""
    if data is None:
        return cfg
    if not isinstance(data, dict):
        raise ConfigError(f"config section '{prefix.rstrip('.') or '<root>'}' must be a mapping, got {data!r}")
    schema = type(cfg)
    hints = typing.get_type_hints(schema)
    names = set(_field_names(schema))
    changes = {}
    for k, v in data.items():
        if not isinstance(k, str) or k not in names:
            raise _unknown(str(k), schema, prefix)
        t = hints[k]
        if dataclasses.is_dataclass(t):
            changes[k] = merge(getattr(cfg, k), v, prefix + k + ".")
        elif typing.get_origin(t) is dict and isinstance(getattr(cfg, k), dict):
            # a mapping section (e.g. ros.robots.<id>.<key>): each source adds to it
            changes[k] = _deep_update(getattr(cfg, k), _coerce(v, t, prefix + k))
        else:
            changes[k] = _coerce(v, t, prefix + k)
    return dataclasses.replace(typing.cast(Any, cfg), **changes)


def _deep_update(old: dict, new: dict) -> dict:
    """``old`` with ``new``'s entries; nested mappings are updated the same way (copies)."""
    out = dict(old)
    for k, v in new.items():
        out[k] = _deep_update(out[k], v) if isinstance(out.get(k), dict) and isinstance(v, dict) else v
    return out


def split_key_value(item: str, what: str = "override", form: str = "key=value") -> tuple[str, str]:
    """``"key=raw"`` → ``(key stripped, raw)``; a one-line :class:`ConfigError` naming ``what``
    without ``=`` or with an empty key."""
    if "=" not in item:
        raise ConfigError(f"{what} {item!r} is not of the form {form}")
    key, raw = item.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError(f"{what} {item!r} has an empty key")
    return key, raw


def parse_override(item: str) -> dict:
    """``"a.b=1.5"`` → ``{"a": {"b": 1.5}}`` (value parsed as YAML)."""
    key, raw = split_key_value(item)
    try:
        value = yaml.safe_load(raw) if raw.strip() != "" else ""
    except yaml.YAMLError:
        value = raw
    if isinstance(value, str) and value.strip().lower() in ("inf", "+inf", "-inf"):
        value = float(value)
    out: dict = {}
    cur = out
    parts = key.split(".")
    for p in parts[:-1]:
        cur = cur.setdefault(p, {})
    cur[parts[-1]] = value
    return out


def read_document(path: Path, loads: Callable[[str], Any], error: type[Exception], missing: str,
                  invalid: str) -> Any:
    """``loads(text of path)``; a missing file raises ``error(missing)``, a parse error
    ``error(f"{invalid}: {why}")`` (one line each)."""
    if not path.is_file():
        raise error(missing)
    try:
        return loads(path.read_text())
    except (ValueError, yaml.YAMLError) as e:
        raise error(f"{invalid}: {' '.join(str(e).split())}") from None


def load_yaml(path: str | Path) -> dict:
    p = Path(path)
    data = read_document(p, yaml.safe_load, ConfigError, f"config file not found: {p}",
                         f"config file {p} is not valid YAML")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {p} must hold a mapping at the top level")
    return data


def load_config(schema: type[_T], path: str | Path | None = None, overrides: Iterable[str] | None = (),
                base: dict | None = None) -> _T:
    """Build a ``schema`` instance: defaults → ``base`` → YAML ``path`` → ``overrides``."""
    cfg = schema()
    if base:
        cfg = merge(cfg, base)
    if path:
        cfg = merge(cfg, load_yaml(path))
    for item in overrides or ():
        cfg = merge(cfg, parse_override(item))
    return cfg


def to_dict(cfg: Any) -> dict:
    """Plain nested dict (YAML-safe: Paths become strings, tuples lists, inf stays float)."""
    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        return v
    return conv(cfg)


def describe(schema: type, prefix: str = "") -> str:
    """One line per key: ``key = default  -- help``; for ``--help`` epilogs."""
    lines = []
    inst = schema()
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        k = prefix + f.name
        t = hints[f.name]
        if dataclasses.is_dataclass(t):
            lines.append(f"[{k}]  {f.metadata.get('help', '')}".rstrip())
            lines.append(describe(typing.cast(type, t), k + "."))
            continue
        v = getattr(inst, f.name)
        if isinstance(v, float) and math.isinf(v):
            v = "inf" if v > 0 else "-inf"
        lines.append(f"  {k} = {v!r}  -- {f.metadata.get('help', '')}".rstrip(" -"))
    return "\n".join(lines)


def field_(default: Any, help: str, **kw: Any) -> Any:
    """Shorthand for a dataclass field with a help text (mutable defaults are copied)."""
    if isinstance(default, (list, dict, set)):
        def copy_() -> Any:
            return type(default)(default)
        return dataclasses.field(default_factory=copy_, metadata={"help": help}, **kw)
    if dataclasses.is_dataclass(default) and not isinstance(default, type):
        def fresh() -> Any:
            return dataclasses.replace(default)
        return dataclasses.field(default_factory=fresh, metadata={"help": help}, **kw)
    return dataclasses.field(default=default, metadata={"help": help}, **kw)


def section(schema: type, help: str = "") -> Any:
    """A nested config section field."""
    return dataclasses.field(default_factory=schema, metadata={"help": help})


def check_threads(threads: int, key: str) -> int:
    """``threads``, the value of a thread-count key (``key``; 0 = auto), as an int; a
    :class:`ConfigError` naming the key when it is negative."""
    if threads < 0:
        raise ConfigError(f"{key} must be >= 0 (0 = auto), got {threads}")
    return int(threads)
