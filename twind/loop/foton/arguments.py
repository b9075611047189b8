"""What a foton function's arguments must be: the errors that name the design string
(:class:`_Failer`), the checks of each argument's kind, and of a sample rate."""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Union

import numpy as np

from twind.errors import FotonError
from twind.loop.foton.zpk import ComplexArray

MAX_ORDER = 20  # twind's limit for one design; the RCG runs at most 10 sections a stage

Arg = Union[float, complex, str, list[complex]]


class _Failer:
    """Builds FotonErrors that always name the design string; carries the sample rate the
    design is read at (None: the continuous design as written)."""

    def __init__(self, design: str, rate_hz: float | None = None) -> None:
        self.design = design
        self.rate_hz = rate_hz

    def __call__(self, msg: str) -> FotonError:
        return FotonError(f"{msg} in design {self.design!r}")


# ============================================================================================
# Argument checking
# ============================================================================================
def _arity(fname: str, args: Sequence[Arg], n_min: int, n_max: int, fail: _Failer) -> None:
    if not n_min <= len(args) <= n_max:
        want = str(n_min) if n_min == n_max else f"{n_min} to {n_max}"
        raise fail(f"{fname}() takes {want} arguments, got {len(args)}")


def _describe(arg: Arg) -> str:
    if isinstance(arg, str):
        return f"the string {arg!r}"
    if isinstance(arg, list):
        return "a vector"
    return f"the number {arg!r}"


def _real(fname: str, args: Sequence[Arg], k: int, what: str, fail: _Failer) -> float:
    arg = args[k]
    if isinstance(arg, (str, list)):
        raise fail(f"{fname}(): argument {k + 1} ({what}) must be a number, "
                   f"got {_describe(arg)}")
    if arg.imag != 0:
        raise fail(f"{fname}(): argument {k + 1} ({what}) must be real, got {arg!r}")
    return arg.real


def _positive(fname: str, args: Sequence[Arg], k: int, what: str, fail: _Failer) -> float:
    value = _real(fname, args, k, what, fail)
    if value <= 0:
        raise fail(f"{fname}(): argument {k + 1} ({what}) must be positive, got {value!r}")
    return value


def _vector_arg(fname: str, args: Sequence[Arg], k: int, what: str,
                fail: _Failer) -> ComplexArray:
    arg = args[k]
    if isinstance(arg, str):
        raise fail(f"{fname}(): argument {k + 1} ({what}) must be a vector like [1;2], "
                   f"got {_describe(arg)}")
    values = arg if isinstance(arg, list) else [arg]
    if len(values) > 2 * MAX_ORDER:
        raise fail(f"{fname}(): argument {k + 1} ({what}) has {len(values)} roots, "
                   f"more than {2 * MAX_ORDER}")
    return np.array(values, dtype=complex)


def _string(fname: str, args: Sequence[Arg], k: int, what: str, fail: _Failer) -> str:
    arg = args[k]
    if not isinstance(arg, str):
        raise fail(f"{fname}(): argument {k + 1} ({what}) must be a quoted string, "
                   f"got {_describe(arg)}")
    return arg


def _order(fname: str, args: Sequence[Arg], k: int, fail: _Failer) -> int:
    value = _real(fname, args, k, "order", fail)
    if value != int(value) or not 1 <= value <= MAX_ORDER:
        raise fail(f"{fname}(): order must be an integer from 1 to {MAX_ORDER}, got {value!r}")
    return int(value)


def _paired(roots: ComplexArray, fname: str, what: str, fail: _Failer) -> ComplexArray:
    """Match complex roots into exact conjugate pairs (foton filters have real coefficients)."""
    out = list(roots[roots.imag == 0])
    upper = [r for r in roots if r.imag > 0]
    lower = [r for r in roots if r.imag < 0]
    for r in upper:
        if not lower:
            raise fail(f"{fname}(): {what} {_fmt(r)} has no complex-conjugate partner")
        dist = [abs(r.conjugate() - q) for q in lower]
        j = int(np.argmin(dist))
        if dist[j] > 1e-6 * max(abs(r), 1e-300):
            raise fail(f"{fname}(): {what} {_fmt(r)} has no complex-conjugate partner")
        lower.pop(j)
        out.extend([r, r.conjugate()])
    if lower:
        raise fail(f"{fname}(): {what} {_fmt(lower[0])} has no complex-conjugate partner")
    return np.array(out, dtype=complex)


def _fmt(z: complex) -> str:
    return f"{z.real:g}{z.imag:+g}i" if z.imag else f"{z.real:g}"


def _check_rate(rate_hz: object) -> None:
    if not (isinstance(rate_hz, numbers.Real) and math.isfinite(rate_hz) and rate_hz > 0):
        msg = f"sample rate must be a positive number of Hz, got {rate_hz!r}"
        raise FotonError(msg)
