"""Options several commands share, the argument types that check them, and how a result is
printed."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

from twind import strictjson

CONFIG_HELP = "twin config (TOML); default: the 40m file shipped with twind"
SEED_HELP = "seed of the twin's noise (default 0)"


def frequency(text: str) -> float:
    """A frequency argument (Hz): a finite number, zero or more."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        msg = f"not a frequency in Hz: {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return value


def checked(convert: Callable[[str], float], ok: Callable[[float], bool], wants: str,
            name: str) -> Callable[[str], float]:
    """An argument type: `convert` of the text, refused unless `ok`, the message saying
    it `wants` (argparse puts the option's name before it)."""
    def parse(text: str) -> float:
        try:
            value = convert(text)
        except ValueError:
            value = None
        if value is None or not ok(value):
            msg = f"must be {wants}, got {text!r}"
            raise argparse.ArgumentTypeError(msg)
        return value

    parse.__name__ = name
    return parse


positive = checked(float, lambda v: math.isfinite(v) and v > 0, "a positive number", "positive")
non_negative = checked(float, lambda v: math.isfinite(v) and v >= 0, "a number, zero or more",
                       "non_negative")
positive_int = checked(int, lambda v: v >= 1, "a whole number of at least 1", "positive_int")
count = checked(int, lambda v: v >= 0, "a whole number, zero or more", "count")
fraction = checked(float, lambda v: 0 <= v <= 1, "a number from 0 to 1", "fraction")


def overlap(text: str) -> float:
    """A Welch overlap: from 0 up to, not including, 1."""
    value = fraction(text)
    if value == 1:
        msg = "must be below 1 (segments that overlap wholly never advance)"
        raise argparse.ArgumentTypeError(msg)
    return value


FIGURES = (".png", ".pdf", ".svg")
"""The figure formats twind writes."""
TF_RESULTS = (".h5", ".hdf5", ".csv", ".mat", ".png")
"""What ``twind tf -o`` writes: the numbers, or a Bode matrix."""


def new_file(*suffixes: str) -> Callable[[str], str]:
    """An output argument: a file of one of `suffixes` that does not exist yet (twind never
    overwrites a result), checked before any work."""
    def output(text: str) -> str:
        path = Path(text)
        if path.suffix.lower() not in suffixes:
            msg = f"{text}: give a {', '.join(suffixes[:-1])} or {suffixes[-1]} file"
            raise argparse.ArgumentTypeError(msg)
        if path.exists():
            msg = f"{text} exists; twind does not overwrite results"
            raise argparse.ArgumentTypeError(msg)
        return text

    return output


def existing(text: str) -> str:
    """An input argument: a file that is there."""
    if not Path(text).exists():
        msg = f"no such input: {text}"
        raise argparse.ArgumentTypeError(msg)
    return text


def seed(text: str) -> int:
    """A seed argument: a non-negative integer."""
    value = int(text)
    if value < 0:
        msg = f"must be a non-negative integer, got {text}"
        raise argparse.ArgumentTypeError(msg)
    return value


def bus_arguments(p: argparse.ArgumentParser) -> None:
    """How a command reaches a running twin."""
    p.add_argument("--connect", action="append", help="Zenoh endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--ifo", help="the twin's interferometer prefix (default C1; inject: the "
                                 "channel's)")
    p.add_argument("--timeout", type=positive, default=5.0,
                   help="seconds to wait for the twin's reply (default 5)")
    p.add_argument("--zenoh-config", help="a Zenoh JSON5 configuration (TLS, access control)")
    p.add_argument("--wait", type=non_negative, default=0.0, metavar="S",
                   help="seconds to wait for a twin that is still starting to answer (0: ask "
                        "once)")


def exc_span(text: str) -> tuple[str, float, float]:
    """An ``--exc-times`` argument: ``DOF:START:END``, GPS seconds, START before END."""
    dof, _, span = text.partition(":")
    start, _, end = span.partition(":")
    try:
        a, b = float(start), float(end)
    except ValueError:
        a = b = math.nan
    if dof not in ("POS", "PIT", "YAW", "SIDE") or not (math.isfinite(a) and a < b < math.inf):
        msg = f"not DOF:START:END (e.g. POS:1400000000:1400000300): {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return dof, a, b


def input_arguments(p: argparse.ArgumentParser) -> None:
    """Measured transfer functions: diaggui XML files, MCAP sessions, or the data system's
    HDF5 files or GWF frames, and how to read them."""
    p.add_argument("inputs", nargs="+", type=existing, help="diaggui XML files (one per excited DOF), MCAP "
                   "sessions, or gwpy HDF5 files or GWF frames")
    p.add_argument("--bw", type=positive, default=0.01, help="time series: Welch resolution (Hz)")
    p.add_argument("--overlap", type=overlap, default=0.5, help="time series: Welch overlap")
    p.add_argument("--optic", help="time series: the optic, when several were excited")
    p.add_argument("--estimator", choices=["welch", "lpm"], default="welch",
                   help="time series: Welch (diaggui's) or Pintelon-Schoukens' local "
                        "polynomial method over each whole excitation (leakage removed; "
                        "--bw unused)")
    p.add_argument("--map", action="append", default=[], metavar="RECORDED=TWIN",
                   help="HDF5/GWF: a recorded channel-name prefix and the twin's, e.g. "
                        "C2:=C1: (repeatable; a final _DQ is dropped anyway)")
    p.add_argument("--exc-times", type=exc_span, action="append", default=[],
                   metavar="DOF:START:END",
                   help="time series: an excitation's GPS span, given by hand (an EXC "
                        "that never rests at zero; repeatable)")
    p.add_argument("--band", type=frequency, nargs=2, metavar=("LO", "HI"),
                   help="only the frequencies from LO to HI Hz")
    p.add_argument("--json", action="store_true", help="the numbers as JSON")


def show(result, as_json: bool) -> None:  # noqa: ANN001 - anything with to_json and lines
    """Print a result as its JSON object or as lines for a person."""
    if as_json:
        strictjson.dump(result.to_json(), sys.stdout)
        sys.stdout.write("\n")
    else:
        print("\n".join(result.lines()))


def shown(path: str | Path) -> str:
    """`path` as a person here would type it: relative to the working directory when it is
    under it (a figure's caption names its model so)."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except (ValueError, OSError):
        return str(path)
