"""What every configuration file's reader shares: a TOML table walked key by key, values
converted with their units, and a damping filter module as written."""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twind.errors import ConfigError, TwindError
from twind.loop.filtermodule import N_STAGES, FilterModule, Stage
from twind.loop.foton import design_to_sos
from twind.units import parse_quantity


@dataclass(frozen=True)
class ModuleConfig:
    """Settings of one damping filter module as written in the file."""

    gain: float
    stages: tuple[Stage | None, ...]
    on: tuple[int, ...]
    ramp_s: float = 0.0
    limit: float = 0.0

    def build(self) -> FilterModule:
        """A fresh :class:`FilterModule` (mutable state for an engine)."""
        return FilterModule(list(self.stages), set(self.on), self.gain, ramp_s=self.ramp_s,
                            limit=self.limit)



class Reader:
    """Walks one TOML table, converting values and remembering the keys it used."""

    def __init__(self, source: str, table: dict[str, Any], prefix: str = "") -> None:
        self.source, self.table, self.prefix = source, table, prefix

    def key(self, name: str) -> str:
        """The dotted key of `name` in the file."""
        return f"{self.prefix}{name}"

    def fail(self, name: str, problem: str) -> ConfigError:
        """The error naming the file, key `name` and the `problem`."""
        return ConfigError(self.source, self.key(name), problem)

    def sub(self, name: str, required: bool = True) -> Reader:
        """The table `name` (an empty one if missing and not `required`)."""
        value = self.table.get(name, {} if not required else None)
        if value is None:
            raise self.fail(name, "missing table")
        if not isinstance(value, dict):
            raise self.fail(name, f"expected a table, got {value!r}")
        return Reader(self.source, value, self.key(name) + ".")

    def get(self, name: str, convert: Callable[[Any], Any], default: Any = ...) -> Any:
        """Value `name` through `convert`; `default` if missing (required if not given)."""
        if name not in self.table:
            if default is ...:
                raise self.fail(name, "missing parameter")
            return default
        try:
            return convert(self.table[name])
        except (ValueError, TypeError, TwindError) as err:
            raise self.fail(name, str(err)) from None

    def only(self, allowed: Sequence[str]) -> None:
        """Refuse any key but `allowed`."""
        for name in self.table:
            if name not in allowed:
                raise self.fail(name, f"unknown key; expected one of {', '.join(allowed)}")


def quantity(dimension: str) -> Callable[[Any], float]:
    """A converter of ``"number unit"`` of `dimension` to its SI value."""

    return lambda v: parse_quantity(v, dimension)


def positive_quantity(dimension: str) -> Callable[[Any], float]:
    """:func:`quantity`, refusing zero and negative values."""
    def convert(v: Any) -> float:
        value = quantity(dimension)(v)
        if not value > 0:
            msg = f"must be positive, got {v!r}"
            raise ValueError(msg)
        return value

    return convert


def non_negative_quantity(dimension: str) -> Callable[[Any], float]:
    """:func:`quantity`, refusing negative values."""
    def convert(v: Any) -> float:
        value = quantity(dimension)(v)
        if not value >= 0:
            msg = f"must not be negative, got {v!r}"
            raise ValueError(msg)
        return value

    return convert


def boolean(v: Any) -> bool:
    """`v` if it is a TOML boolean."""
    if not isinstance(v, bool):
        msg = f"expected true or false (no quotes), got {v!r}"
        raise ValueError(msg)
    return v


def positive(v: Any) -> float:
    """`v` if it is a positive plain number."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
        msg = f"expected a positive number, got {v!r}"
        raise ValueError(msg)
    return float(v)



def stage(rate_hz: float) -> Callable[[Any], Stage]:
    """A converter of ``["name", "foton design"]`` to a filter stage at `rate_hz`."""
    def convert(v: Any) -> Stage:
        if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, str) for x in v)):
            msg = f"expected [\"name\", \"foton design\"], got {v!r}"
            raise ValueError(msg)
        design_to_sos(v[1], rate_hz)  # a FotonError here names the design and its problem
        return Stage(v[0], v[1], rate_hz=rate_hz)

    return convert



def fm_numbers(v: Any) -> tuple[int, ...]:
    """`v` if it is a list of filter-module numbers 1..10."""
    if not isinstance(v, list) or not all(isinstance(x, int) and 1 <= x <= N_STAGES for x in v):
        msg = f"expected a list of FM numbers 1..{N_STAGES}, got {v!r}"
        raise ValueError(msg)
    return tuple(v)



def matrix(rows: int, columns: int) -> Callable[[Any], tuple[tuple[float, ...], ...]]:
    """A converter of a list of `rows` lists of `columns` finite plain numbers."""
    def convert(v: Any) -> tuple[tuple[float, ...], ...]:
        ok = (isinstance(v, list) and len(v) == rows
              and all(isinstance(r, list) and len(r) == columns for r in v)
              and all(isinstance(x, int | float) and not isinstance(x, bool)
                      and math.isfinite(x) for r in v for x in r))
        if not ok:
            msg = f"expected {rows} rows of {columns} finite numbers, got {v!r}"
            raise ValueError(msg)
        return tuple(tuple(float(x) for x in r) for r in v)

    return convert


def positive_int(v: Any) -> int:
    """`v` if it is a whole number of at least 1."""
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        msg = f"expected a whole number >= 1, got {v!r}"
        raise ValueError(msg)
    return v


def read_toml(path: str | Path) -> dict[str, Any]:
    """The TOML file `path`; a ConfigError when it is missing or not TOML."""
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(str(path), "-", "file not found") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(str(path), "-", f"not valid TOML: {err}") from None
