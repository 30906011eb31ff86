"""Generic helpers for typed config dataclasses: to/from plain dicts and YAML, dotted overrides
(`--set fine.iterations=5000`), and a stable hash. Knows nothing about NeHaD's knobs."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import stat
import typing
from pathlib import Path
from typing import Any

import yaml

from nehad.runtime.yamlfile import MalformedYAML, load_yaml_text


class ConfigError(ValueError):
    """A config file or override names an unknown key or holds a value of the wrong type."""


def to_dict(cfg) -> dict:
    """Nested plain dict (tuples become lists) of a config dataclass."""
    def conv(v):
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        return v
    return conv(cfg)


def _is_union(origin) -> bool:
    """Whether a type's origin is a Union (``Optional[X]``, ``X | None``)."""
    return origin is typing.Union or (origin is not None
                                      and str(origin) == "<class 'types.UnionType'>")


def _coerce_union(value: Any, args: tuple, where: str):
    """`value` as the first member type of the union that accepts it (None when allowed)."""
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


def _coerce_sequence(value: Any, origin, args: tuple, where: str):
    """`value` (a list, or a comma-separated string) as a tuple or list of its element types."""
    if isinstance(value, str):
        value = [v for v in value.replace("(", "").replace(")", "").replace("[", "")
                 .replace("]", "").split(",") if v.strip() != ""]
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{where}: expected a list, got {value!r}")
    if origin is tuple and args and args[-1] is not Ellipsis:
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    inner = args[0] if args else Any
    out = [_coerce(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
    return tuple(out) if origin is tuple else out


def _coerce_bool(value: Any, where: str) -> bool:
    """A bool, or a string such as true/yes/on/1 or false/no/off/0."""
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.lower() in ("true", "yes", "on", "1", "false", "no", "off", "0"):
        return value.lower() in ("true", "yes", "on", "1")
    raise ConfigError(f"{where}: expected true/false, got {value!r}")


def _coerce_int(value: Any, where: str) -> int:
    """An int, or a number or string holding a whole number (not a bool)."""
    if isinstance(value, bool):
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    if isinstance(value, int):
        return value
    try:
        f = float(value)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{where}: expected an integer, got {value!r}") from None
    if not math.isfinite(f) or not f.is_integer():
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    return int(f)


def _coerce_float(value: Any, where: str) -> float:
    """A finite float from a number or a string (not a bool)."""
    if isinstance(value, bool):
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    try:
        f = float(value)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{where}: expected a number, got {value!r}") from None
    if not math.isfinite(f):
        # nan/inf pass every range check (comparisons with nan are false) and train to NaN
        raise ConfigError(f"{where}: expected a finite number, got {value!r}")
    return f


def _coerce(value: Any, tp, where: str):
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if _is_union(origin):
        return _coerce_union(value, args, where)
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: expected one of {list(args)}, got {value!r}")
        return value
    if origin in (tuple, list):
        return _coerce_sequence(value, origin, args, where)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return from_dict(tp, value, where)
    if tp is bool:
        return _coerce_bool(value, where)
    if tp is int:
        return _coerce_int(value, where)
    if tp is float:
        return _coerce_float(value, where)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def from_dict(cls, data: dict, where: str = ""):
    """Build config dataclass `cls` from a (partial) nested dict; unknown keys are errors."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for key in data:
        if key not in names:
            raise ConfigError(f"{where + '.' if where else ''}{key}: unknown config key "
                              f"(known: {', '.join(sorted(names))})")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name in data:
            kwargs[f.name] = _coerce(data[f.name], hints[f.name], f"{where + '.' if where else ''}{f.name}")
    return cls(**kwargs)


def merge(cfg, data: dict, where: str = ""):
    """A copy of `cfg` with the (partial) nested dict `data` applied on top."""
    hints = typing.get_type_hints(type(cfg))
    names = {f.name for f in dataclasses.fields(cfg)}
    changes = {}
    for key, value in data.items():
        path = f"{where + '.' if where else ''}{key}"
        if key not in names:
            raise ConfigError(f"{path}: unknown config key (known: {', '.join(sorted(names))})")
        current = getattr(cfg, key)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            changes[key] = merge(current, value, path)
        else:
            changes[key] = _coerce(value, hints[key], path)
    return dataclasses.replace(cfg, **changes)


def parse_override(text: str) -> dict:
    """'a.b.c=value' -> {'a': {'b': {'c': value}}}; the value is parsed as YAML (numbers, lists,
    booleans), then coerced to the field's type by `merge`."""
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected KEY=VALUE, e.g. fine.iterations=5000")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError(f"override {text!r}: empty key")
    try:
        value = load_yaml_text(raw) if raw.strip() else ""
    except MalformedYAML:  # kept as text: the type check names it
        value = raw
    out: dict = {}
    node = out
    parts = key.split(".")
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value
    return out


#: Largest text file (a config, a run's metrics log) read whole
MAX_TEXT_BYTES = 256 << 20


def read_text(path, kind: str = "config file", expected: str = "a YAML config",
              error=None) -> str:
    """The text of a file a user or a run folder gives (a config, a run's metrics.jsonl); a
    missing, unreadable, binary or non-UTF-8 file raises `error` (ConfigError) naming it: the
    same words for every such file (issues 15, 26)."""
    error = error or ConfigError
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise error(f"{path}: no such {kind}") from None
    except OSError as e:
        raise error(f"{path}: cannot read ({e.strerror or e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise error(f"{path}: is a folder, not a {kind}")
    if not stat.S_ISREG(st.st_mode):
        # a FIFO blocks until someone writes to it, /dev/zero never ends (issue 26)
        raise error(f"{path}: not a regular file (a device, FIFO or socket); expected {expected}")
    if st.st_size > MAX_TEXT_BYTES:
        raise error(f"{path}: {st.st_size} bytes, too large for {expected} (at most "
                    f"{MAX_TEXT_BYTES >> 20} MB)")
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise error(f"{path}: no such {kind}") from None
    except IsADirectoryError:
        raise error(f"{path}: is a folder, not a {kind}") from None
    except OSError as e:
        raise error(f"{path}: cannot read ({e.strerror or e})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not a UTF-8 text file (byte {e.start}: {raw[e.start]:#04x}); "
                    f"expected {expected}") from None
    if "\x00" in text:
        raise error(f"{path}: a binary file (holds NUL bytes); expected {expected}")
    return text


def load_yaml(path) -> dict:
    """The mapping in a YAML config file; a missing, binary, non-UTF-8 or malformed file raises
    ConfigError naming it (issue 15: no traceback for any file a user can pass)."""
    path = Path(path)
    text = read_text(path)
    try:
        data = load_yaml_text(text)
    except MalformedYAML as e:
        raise ConfigError(f"{path}: {e}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return data


def dump_yaml(cfg) -> str:
    return yaml.safe_dump(to_dict(cfg), sort_keys=False)


def config_hash(cfg) -> str:
    """Stable short hash of a config's values."""
    text = json.dumps(to_dict(cfg), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def diff(a: dict, b: dict, where: str = "") -> list[str]:
    """Human-readable differences between two nested dicts."""
    out = []
    for key in sorted(set(a) | set(b)):
        path = f"{where + '.' if where else ''}{key}"
        if key not in a or key not in b:
            out.append(f"{path}: {a.get(key, '<absent>')!r} -> {b.get(key, '<absent>')!r}")
        elif isinstance(a[key], dict) and isinstance(b[key], dict):
            out.extend(diff(a[key], b[key], path))
        elif a[key] != b[key]:
            out.append(f"{path}: {a[key]!r} -> {b[key]!r}")
    return out
