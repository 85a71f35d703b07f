"""The codec of every schema: nested dicts and TOML to frozen dataclasses and back, strictly
(an unknown key or a wrongly typed value raises `ValueError` naming its full path), and dotted
keys (`"traffic.flow_vph_per_lane"`) to read and set one value."""

from __future__ import annotations

import dataclasses
import functools
import sys
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib


T = TypeVar("T")


@functools.cache
def type_hints(cls: type) -> dict[str, Any]:
    """`typing.get_type_hints(cls)`, resolved once per class (it parses every annotation)."""
    return typing.get_type_hints(cls)


def set_dotted(data: dict[str, Any], dotted: str, value: Any, create: bool = False) -> None:
    """Set `data["a"]["b"] = value` for `dotted = "a.b"`; an unknown key raises (`create`: a
    missing key or table is added, for `from_dict` to judge)."""
    node = data
    *parents, leaf = dotted.split(".")
    for p in parents:
        if create and p not in node:
            node[p] = {}
        if not isinstance(node.get(p), dict):
            what = f": {p!r} is a value, not a table" if p in node else ""
            raise ValueError(f"unknown config key {dotted!r}{what}")
        node = node[p]
    if leaf not in node and not create:
        raise ValueError(f"unknown config key {dotted!r}")
    node[leaf] = value


def get_dotted(cfg: Any, dotted: str) -> Any:
    """`cfg.a.b` for `dotted = "a.b"`; an unknown key raises `ValueError`."""
    node = cfg
    for part in dotted.split("."):
        if not hasattr(node, part):
            raise ValueError(f"unknown config key {dotted!r}")
        node = getattr(node, part)
    return node


def to_dict(cfg: Any) -> dict[str, Any]:
    """The config as nested plain dicts (tuples become lists), ready for TOML or JSON."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        return v

    return conv(cfg)


def _coerce(value: Any, tp: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ValueError(f"config key {path!r} must be a table, got {value!r}")
        return from_dict(tp, value, _prefix=path + ".")
    if origin is tuple and typing.get_args(tp)[1:] == (Ellipsis,):  # tuple[X, ...]
        if not isinstance(value, list | tuple):
            raise ValueError(f"config key {path!r} must be a list, got {value!r}")
        item = typing.get_args(tp)[0]
        return tuple(_coerce(v, item, f"{path}[{i}]") for i, v in enumerate(value))
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list | tuple) or len(value) != len(args):
            raise ValueError(f"config key {path!r} must be a list of {len(args)}, got {value!r}")
        pairs = enumerate(zip(value, args, strict=True))
        return tuple(_coerce(v, a, f"{path}[{i}]") for i, (v, a) in pairs)
    if origin in (types.UnionType, typing.Union):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) != 1 or len(typing.get_args(tp)) != 2:
            raise TypeError(f"unsupported config type at {path!r}")
        return None if value is None else _coerce(value, args[0], path)  # X | None
    if tp is bool:
        if not isinstance(value, bool):
            raise ValueError(f"config key {path!r} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"config key {path!r} must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"config key {path!r} must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ValueError(f"config key {path!r} must be a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config type {tp!r} at {path!r}")


def from_dict(cls: type[T], data: dict[str, Any], _prefix: str = "") -> T:
    """Build `cls` from nested dicts. Unknown keys and wrongly typed values raise `ValueError`."""
    hints = type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(
            f"unknown config key {_prefix + unknown[0]!r} (valid keys in this table: "
            f"{', '.join(sorted(names))})"
        )
    kwargs = {k: _coerce(v, hints[k], _prefix + k) for k, v in data.items()}
    return cls(**kwargs)


def read_toml(path: Path) -> dict[str, Any]:
    """A TOML file's tables; a syntax error is a `ValueError` naming the file and the line."""
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path}: not valid TOML: {err}") from None
