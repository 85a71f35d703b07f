"""The value rules of the schema: `Bounds` declared beside each number (`num`, `positive`),
checked by `check_values`, listed by `bounds_table` (the docs print it, the tests walk it), and
`require` for the cross-field checks that single values cannot express."""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import Any

from marlmerge.config.codec import type_hints


@dataclass(frozen=True)
class Bounds:
    """The values a number of the schema may take: `low`..`high` (None: unbounded), each end
    closed unless `low_open` / `high_open`; `ordered`: the field is a (low, high) range."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    ordered: bool = False

    def holds(self, v: float) -> bool:
        if self.low is not None and (v <= self.low if self.low_open else v < self.low):
            return False
        return self.high is None or (v < self.high if self.high_open else v <= self.high)

    def text(self) -> str:
        """The rule in words: `in (0, 1]`, `>= 0`, `<= 600`, ..."""
        lo, hi = self.low, self.high
        if lo is not None and hi is not None:
            left, right = "(" if self.low_open else "[", ")" if self.high_open else "]"
            return f"in {left}{lo:g}, {hi:g}{right}"
        if lo is not None:
            return f"{'>' if self.low_open else '>='} {lo:g}"
        if hi is not None:
            return f"{'<' if self.high_open else '<='} {hi:g}"
        return "finite"


def num(
    default: Any,
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
    high_open: bool = False,
    ordered: bool = False,
) -> Any:
    """A schema field with its default and the `Bounds` of its values (checked by
    `check_values`, listed by `bounds_table`)."""
    bounds = Bounds(low, high, low_open, high_open, ordered)
    return field(default=default, metadata={"bounds": bounds})


def positive(default: Any, high: float | None = None, **kw: Any) -> Any:
    """A field > 0 (and <= `high`)."""
    return num(default, 0.0, high, low_open=True, **kw)


def field_bounds(cls: type, name: str) -> Bounds | None:
    """The bounds of field `name` of dataclass `cls` (declared here or on a base class whose
    field a subclass gives another default)."""
    for klass in cls.__mro__:
        f = getattr(klass, "__dataclass_fields__", {}).get(name)
        if f is not None and "bounds" in f.metadata:
            return f.metadata["bounds"]
    return None


def bounds_table(cls: type, prefix: str = "") -> list[tuple[str, Any, str]]:
    """(dotted key, default, allowed values) of every number of dataclass `cls`, nested tables
    included: the table the docs print and the tests walk."""
    rows: list[tuple[str, Any, str]] = []
    hints = type_hints(cls)
    for f in dataclasses.fields(cls):
        key = prefix + f.name
        if dataclasses.is_dataclass(hints[f.name]):
            rows += bounds_table(hints[f.name], key + ".")
            continue
        bounds = field_bounds(cls, f.name)
        if bounds is not None:
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            rows.append((key, default, bounds.text()))
    return rows


def bounds_markdown(*classes: type) -> str:
    """The bounds of every number of the schemas `classes` as one Markdown table per schema
    (`docs/reliability.md` prints it; a test checks the page against it)."""
    lines: list[str] = []
    for cls in classes:
        lines += [f"**{cls.__name__}**", "", "| key | default | allowed |", "|---|---|---|"]
        for key, default, rule in bounds_table(cls):
            shown = list(default) if isinstance(default, tuple) else default
            lines.append(f"| `{key}` | {shown} | {rule} |")
        lines.append("")
    return "\n".join(lines)


def check_values(cfg: Any, prefix: str = "") -> None:
    """Every number in the (nested) dataclass `cfg` is finite and lies in the `Bounds` declared
    beside its field (`num`; a pair's bounds apply to both ends, and a range pair needs
    low <= high). Raises `ValueError` naming the full key and the value."""
    for f in dataclasses.fields(cfg):
        key, value = prefix + f.name, getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            check_values(value, key + ".")
            continue
        items = value if isinstance(value, tuple) else (value,)
        numbers = [v for v in items if isinstance(v, int | float) and not isinstance(v, bool)]
        if not numbers:
            continue
        if not all(math.isfinite(v) for v in numbers):
            raise ValueError(f"{key} must be finite, got {value!r}")
        bounds = field_bounds(type(cfg), f.name)
        if bounds is None:
            continue
        if not all(bounds.holds(v) for v in numbers):
            raise ValueError(f"{key} must be {bounds.text()}, got {value!r}")
        if bounds.ordered and len(numbers) == 2 and numbers[0] > numbers[1]:
            raise ValueError(f"{key} must be a range (low, high) with low <= high, got {value!r}")


def require(checks: list[tuple[bool, str]]) -> None:
    """Raise `ValueError` with the message of the first check that fails."""
    for ok, msg in checks:
        if not ok:
            raise ValueError(msg)


def check_count(name: str, value: Any) -> int:
    """`value` as an int if it is a whole number >= 1 (a Python or NumPy integer, not a bool),
    else a `ValueError` naming `name` and the value: sizes such as worlds, envs and agents."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)
