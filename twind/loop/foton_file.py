"""Read and write LIGO CDS foton filter files (``C1SUS.txt``, ``H1SUSETMX.txt``, ...).

These are the plain-text files an RCG front-end model loads its IIR filter
coefficients from. The format below is the one the real-time loader
``fmReadCoeffFile()`` (advLigoRTS ``src/drv/fmReadCoeff.c``) accepts and the
one foton writes.

File layout
-----------
Lines whose first non-blank character is ``#`` are comments for the RCG
loader. foton keeps its own metadata in a few of them::

    # FILTERS FOR ONLINE SYSTEM
    #
    # Computer generated file: DO NOT EDIT
    #
    # MODULES ETMX_SUSPOS ETMX_SUSPIT ETMX_SUSYAW ETMX_SUSSIDE
    #
    # SAMPLING RATE 16384
    ################################################################################
    ### ETMX_SUSPOS                                                              ###
    ################################################################################
    # DESIGN   ETMX_SUSPOS 0 zpk([],[30],1,"n")
    ETMX_SUSPOS 0 21 1 0 0 LP30 0.00572... -0.98855... 0.0 1.0 0.0

- ``# MODULES`` lines list the filter modules (banks); the RCG code generator
  writes four names per line.
- ``# SAMPLING RATE`` gives the model rate in Hz. ``## SAMPLING MODULE rate``
  lines written by the RCG code generator are plain comments.
- ``# DESIGN MODULE INDEX text`` holds foton's design string of one stage. A
  long design ends in `` \\`` and continues on following ``#`` lines; the
  pieces are joined without a separator, as LIGO's pyDARM reader does.

Every other non-blank line belongs to a stage (one of the ten FM buttons).
A stage starts with a line of exactly 12 fields::

    MODULE INDEX TYPE SECTIONS RAMP TIMEOUT NAME GAIN A1 A2 B1 B2

followed by ``SECTIONS - 1`` continuation lines of exactly 4 numbers
``A1 A2 B1 B2``, one per further second-order section.

- INDEX is 0..9; FM1 is index 0.
- TYPE is ``10 * input + output`` switching (the RCG accepts 11..14, 21..24):

  - input 1 "always_on": the filter always sees its input;
  - input 2 "zero_history": the input is zeroed while the output is off, and
    the history is cleared when the stage switches off (type 22 also feeds the
    input while ramping on);
  - output 1 "immediate": switch on the next cycle;
  - output 2 "ramp": cross-fade over RAMP cycles (samples at the model rate);
  - output 3 "input_crossing": switch once ``|input - output| <= RAMP`` or
    after TIMEOUT cycles;
  - output 4 "zero_crossing": switch once the signal is within ``RAMP`` of
    zero or after TIMEOUT cycles.

  So RAMP is a sample count for output 2 but a tolerance for outputs 3 and 4;
  both RAMP and TIMEOUT are non-negative integers (source: ``fm10Gen.c``
  ``filterModule()``).
- SECTIONS is 1..10 (``MAX_SO_SECTIONS``); FIR stages with more sections
  live in ``.fir`` files, which this module does not handle.
- NAME is the button label, one token of at most 31 characters.

Biquad convention
-----------------
The RCG runs each section in direct form II (``fm10Gen.c`` ``iir_filter()``)::

    w[n] = x[n] - A1 w[n-1] - A2 w[n-2]
    y[n] = w[n] + B1 w[n-1] + B2 w[n-2]

with the input multiplied by GAIN first, so each section is::

    H(z) = (1 + B1 z^-1 + B2 z^-2) / (1 + A1 z^-1 + A2 z^-2)

The file stores ``A1 A2 B1 B2`` in that order with the denominator signs as
in the formula (foton's "online" order ``gain, a1, a2, b1, b2, ...`` in the
gds ``foton.py`` bindings). In scipy's ``sos`` layout a stage is
``[[G, G*B1, G*B2, 1, A1, A2], [1, B1', B2', 1, A1', A2'], ...]``, with the
overall gain folded into the first section. A gain-only stage is one section
``G 0 0 0 0``.

Errors and warnings
-------------------
The reader is stricter than the RCG loader where the loader would silently
ignore something that is most likely a corrupted file:

- :class:`~twind.errors.FotonError` (naming ``file:line`` and the problem):
  a line that is neither comment, stage line nor section line; a stage line
  without 12 fields or a section line without 4 (the RCG ignores extra
  tokens); a non-numeric or non-finite number; INDEX outside 0..9; TYPE
  outside 11..14/21..24; SECTIONS outside 1..10; negative RAMP or TIMEOUT;
  a NAME longer than 31 characters; fewer section lines than SECTIONS; a
  section line with no stage line before it; the same stage defined twice; a
  bad ``# DESIGN`` or ``# SAMPLING RATE`` line; two different sampling rates;
  a file that cannot be read or is not UTF-8.
- :class:`FotonFileWarning`: a stage or design of a module not listed in
  ``# MODULES`` (the RCG loader does not read ``# MODULES``; the module is
  kept); a file without any ``# MODULES`` line; a ``# DESIGN`` line for a
  stage that has no coefficients (ignored); a ``# SAMPLING module rate`` line
  that disagrees with ``# SAMPLING RATE``.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NoReturn

import numpy as np
from numpy.typing import NDArray

from twind.errors import FotonError, TwindWarning

__all__ = [
    "DEFAULT_SWITCHING",
    "FilterFile",
    "FilterStage",
    "FotonFileWarning",
    "INPUT_SWITCHING",
    "OUTPUT_SWITCHING",
    "read_filter_file",
    "write_filter_file",
]

N_STAGES = 10
"""Stages (FM buttons) per filter module."""

MAX_SECTIONS = 10
"""Second-order sections per IIR stage the RCG accepts (``MAX_SO_SECTIONS``)."""

MAX_NAME_LENGTH = 31
"""Longest stage NAME the RCG loader accepts."""

INPUT_SWITCHING: dict[int, str] = {1: "always_on", 2: "zero_history"}
"""Tens digit of TYPE -> input switching, named as in the gds foton.py bindings."""

OUTPUT_SWITCHING: dict[int, str] = {
    1: "immediate",
    2: "ramp",
    3: "input_crossing",
    4: "zero_crossing",
}
"""Units digit of TYPE -> output switching, named as in the gds foton.py bindings."""

DEFAULT_SWITCHING: dict[str, int] = {"type": 21, "ramp": 0, "timeout": 0}
"""Switching fields the writer uses when a stage leaves them out (foton's default)."""

_STAGE_FIELDS = "MODULE INDEX TYPE SECTIONS RAMP TIMEOUT NAME GAIN A1 A2 B1 B2"
_FLOAT_RE = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\Z")
_INT_RE = re.compile(r"[+-]?\d+\Z")
_MODULES_RE = re.compile(r"#\s*MODULES\b(.*)\Z")
_RATE_RE = re.compile(r"#\s*SAMPLING\s+RATE\b(.*)\Z")
_MODULE_RATE_RE = re.compile(r"#\s*SAMPLING\s+(\S+)\s+(\S+)\s*\Z")
_DESIGN_RE = re.compile(r"#\s*DESIGN\b(.*)\Z")


class FotonFileWarning(TwindWarning):
    """A filter file is readable but not quite what foton would write."""


@dataclass(frozen=True, eq=False)
class FilterStage:
    """One stage (FM button) of a filter module.

    Parameters
    ----------
    index : int
        Stage index 0..9; FM1 is index 0.
    name : str
        Button label (NAME field).
    sos : array_like, shape (n, 6)
        Second-order sections in scipy's layout ``[b0 b1 b2 a0 a1 a2]``, with
        the stage's overall gain folded into the first section. Stored as a
        private float copy.
    design : str or None
        The ``# DESIGN`` string, if the file has one.
    switching : dict
        Raw switching fields: ``type`` (TYPE, e.g. 21), ``ramp`` and
        ``timeout`` (integers; see the module docstring).
    """

    index: int
    name: str
    sos: NDArray[np.float64]
    design: str | None = None
    switching: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        try:
            sos = np.array(self.sos, dtype=float)
        except (TypeError, ValueError) as exc:
            msg = f"stage {self.name!r} (index {self.index}): sos is not a numeric (n, 6) array: {exc}"
            raise FotonError(msg) from exc
        if sos.ndim != 2 or sos.shape[0] < 1 or sos.shape[1] != 6:
            msg = f"stage {self.name!r} (index {self.index}): sos must have shape (n, 6) with n >= 1, got {sos.shape}"
            raise FotonError(msg)
        if not np.all(np.isfinite(sos)):
            msg = f"stage {self.name!r} (index {self.index}): sos has non-finite coefficients"
            raise FotonError(msg)
        # Copied so the caller's array cannot change the stage; left writeable because
        # scipy.signal.sosfilt refuses read-only coefficient arrays.
        object.__setattr__(self, "sos", sos)
        object.__setattr__(self, "switching", dict(self.switching))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, FilterStage):
            return NotImplemented
        return (
            self.index == other.index
            and self.name == other.name
            and self.design == other.design
            and self.switching == other.switching
            and self.sos.shape == other.sos.shape
            and bool(np.array_equal(self.sos, other.sos))
        )

    @property
    def input_switching(self) -> str:
        """Input switching name from the TYPE tens digit, e.g. ``"zero_history"``; "unknown" if invalid."""
        stype = self.switching.get("type", DEFAULT_SWITCHING["type"])
        return INPUT_SWITCHING.get(stype // 10, "unknown") if isinstance(stype, int) else "unknown"

    @property
    def output_switching(self) -> str:
        """Output switching name from the TYPE units digit, e.g. ``"ramp"``; "unknown" if invalid."""
        stype = self.switching.get("type", DEFAULT_SWITCHING["type"])
        return OUTPUT_SWITCHING.get(stype % 10, "unknown") if isinstance(stype, int) else "unknown"


@dataclass(frozen=True)
class FilterFile:
    """The contents of a foton filter file.

    Parameters
    ----------
    path : str
        File the contents were read from.
    rate_hz : float or None
        ``# SAMPLING RATE`` of the model, None if the file has none.
    modules : dict of str to list of FilterStage
        Module name -> its stages sorted by index. Every module named in
        ``# MODULES`` is present, possibly with an empty list; modules with
        stages but not listed follow in order of appearance.
    """

    path: str
    rate_hz: float | None
    modules: dict[str, list[FilterStage]]

    __hash__ = None  # type: ignore[assignment]  # holds dicts and arrays


# ----------------------------------------------------------------------------- reading


@dataclass
class _Pending:
    """A stage line whose section lines are still being read."""

    lineno: int
    module: str
    index: int
    name: str
    switching: dict[str, int]
    gain: float
    n_sections: int
    sections: list[tuple[float, float, float, float]]


@dataclass
class _State:
    """Everything collected while scanning a file."""

    path: str
    listed: list[str] = field(default_factory=list)
    rate: tuple[int, float] | None = None
    module_rates: list[tuple[int, str, float]] = field(default_factory=list)
    designs: dict[tuple[str, int], tuple[int, str]] = field(default_factory=dict)
    stages: dict[tuple[str, int], tuple[int, FilterStage]] = field(default_factory=dict)
    first_seen: dict[str, int] = field(default_factory=dict)
    pending: _Pending | None = None
    notes: list[str] = field(default_factory=list)


def read_filter_file(path: str | os.PathLike[str]) -> FilterFile:
    """Read a foton filter file.

    Parameters
    ----------
    path : str or path-like
        The filter file, e.g. ``/opt/rtcds/caltech/c1/chans/C1SUS.txt``.

    Returns
    -------
    FilterFile
        Sampling rate and, per module, the stages with their SOS
        coefficients, design strings and switching fields.

    Raises
    ------
    FotonError
        If the file cannot be read or a line is malformed; the message names
        ``file:line`` and the problem (see the module docstring for the list).

    Warns
    -----
    FotonFileWarning
        For oddities the RCG loader tolerates, e.g. a module missing from
        ``# MODULES``.
    """
    where = os.fspath(path)
    lines = _read_lines(where)
    state = _State(where)
    i = 0
    while i < len(lines):
        i = _parse_line(state, lines, i)
    if state.pending is not None:
        _fail_truncated(state, state.pending, "the file ends")
    result = _assemble(state)
    for note in state.notes:
        warnings.warn(note, FotonFileWarning, stacklevel=2)
    return result


def _fail(path: str, lineno: int, problem: str) -> NoReturn:
    msg = f"{path}:{lineno}: {problem}"
    raise FotonError(msg)


def _note(state: _State, lineno: int, problem: str) -> None:
    # Collected and emitted by read_filter_file so the warning points at its caller.
    state.notes.append(f"{state.path}:{lineno}: {problem}")


def _read_lines(path: str) -> list[str]:
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        msg = f"{path}: cannot read filter file: {exc.strerror or exc}"
        raise FotonError(msg) from exc
    lines = []
    # Decode per line so an encoding error can name its line.
    for lineno, chunk in enumerate(raw.splitlines(), start=1):
        try:
            lines.append(chunk.decode("utf-8"))
        except UnicodeDecodeError:
            _fail(path, lineno, "line is not valid UTF-8 text")
    return lines


def _parse_line(state: _State, lines: list[str], i: int) -> int:
    """Parse line ``i`` (0-based) and return the index of the next unread line."""
    text = lines[i].strip()
    if not text:
        return i + 1
    if text.startswith("#"):
        return _parse_comment(state, lines, i)
    tokens = text.split()
    if state.pending is not None:
        _parse_section_line(state, state.pending, i + 1, tokens)
    else:
        _parse_stage_line(state, i + 1, tokens)
    return i + 1


def _parse_comment(state: _State, lines: list[str], i: int) -> int:
    text = lines[i].strip()
    lineno = i + 1
    if m := _MODULES_RE.match(text):
        state.listed.extend(name for name in m.group(1).split() if name not in state.listed)
    elif m := _RATE_RE.match(text):
        _parse_rate(state, lineno, m.group(1))
    elif m := _MODULE_RATE_RE.match(text):
        rate = _number(state.path, lineno, m.group(2), f"sampling rate of {m.group(1)}")
        state.module_rates.append((lineno, m.group(1), rate))
    elif m := _DESIGN_RE.match(text):
        return _parse_design(state, lines, i, m.group(1))
    return i + 1


def _parse_rate(state: _State, lineno: int, rest: str) -> None:
    tokens = rest.split()
    if len(tokens) != 1:
        _fail(state.path, lineno, f"expected '# SAMPLING RATE <Hz>', got {len(tokens)} values after RATE")
    rate = _number(state.path, lineno, tokens[0], "SAMPLING RATE")
    if rate <= 0:
        _fail(state.path, lineno, f"SAMPLING RATE must be positive, got {tokens[0]}")
    if state.rate is not None and state.rate[1] != rate:
        _fail(
            state.path,
            lineno,
            f"SAMPLING RATE {tokens[0]} contradicts {state.rate[1]:g} on line {state.rate[0]}",
        )
    state.rate = (lineno, rate)


def _parse_design(state: _State, lines: list[str], i: int, rest: str) -> int:
    lineno = i + 1
    parts = rest.strip().split(None, 2)
    if len(parts) < 2:
        _fail(state.path, lineno, "expected '# DESIGN MODULE INDEX design-string'")
    module, index_text = parts[0], parts[1]
    index = _stage_index(state.path, lineno, index_text)
    text, nxt = _design_text(lines, i, parts[2] if len(parts) == 3 else "")
    key = (module, index)
    if key in state.designs:
        first = state.designs[key][0]
        _fail(state.path, lineno, f"second DESIGN for {_label(module, index)} (first on line {first})")
    state.designs[key] = (lineno, text)
    return nxt


def _design_text(lines: list[str], i: int, first: str) -> tuple[str, int]:
    """Join a design string continued with a trailing backslash onto ``#`` lines."""
    pieces = [first.strip()]
    j = i + 1
    while pieces[-1].endswith("\\"):
        pieces[-1] = pieces[-1][:-1].rstrip()
        if j >= len(lines) or not lines[j].lstrip().startswith("#"):
            break
        piece = lines[j].strip()[1:].strip()
        j += 1
        if not piece:
            break
        pieces.append(piece)
    return "".join(pieces), j


def _parse_stage_line(state: _State, lineno: int, tokens: list[str]) -> None:
    path = state.path
    if len(tokens) == 4 and all(_FLOAT_RE.match(t) for t in tokens):
        _fail(path, lineno, "section coefficient line without a stage line before it (more section lines than SECTIONS?)")
    if len(tokens) != 12:
        _fail(path, lineno, f"expected a stage line of 12 fields ({_STAGE_FIELDS}), got {len(tokens)}")
    module = tokens[0]
    index = _stage_index(path, lineno, tokens[1])
    key = (module, index)
    if key in state.stages:
        _fail(path, lineno, f"{_label(module, index)} is defined twice (first on line {state.stages[key][0]})")
    stype = _integer(path, lineno, tokens[2], "TYPE")
    if stype // 10 not in INPUT_SWITCHING or stype % 10 not in OUTPUT_SWITCHING:
        _fail(path, lineno, f"TYPE must be 11..14 or 21..24 (10*input + output switching), got {tokens[2]}")
    n_sections = _integer(path, lineno, tokens[3], "SECTIONS")
    if not 1 <= n_sections <= MAX_SECTIONS:
        _fail(path, lineno, f"SECTIONS must be 1..{MAX_SECTIONS} (FIR stages are not supported), got {tokens[3]}")
    ramp = _non_negative(path, lineno, tokens[4], "RAMP")
    timeout = _non_negative(path, lineno, tokens[5], "TIMEOUT")
    name = tokens[6]
    if len(name) > MAX_NAME_LENGTH:
        _fail(path, lineno, f"NAME {name!r} is longer than {MAX_NAME_LENGTH} characters")
    gain = _number(path, lineno, tokens[7], "GAIN")
    state.first_seen.setdefault(module, lineno)
    state.pending = _Pending(
        lineno=lineno,
        module=module,
        index=index,
        name=name,
        switching={"type": stype, "ramp": ramp, "timeout": timeout},
        gain=gain,
        n_sections=n_sections,
        sections=[_coefficients(path, lineno, tokens[8:])],
    )
    _complete_if_done(state)


def _parse_section_line(state: _State, pending: _Pending, lineno: int, tokens: list[str]) -> None:
    if len(tokens) == 12:
        _fail_truncated(state, pending, f"line {lineno} starts a new stage")
    if len(tokens) != 4:
        _fail(state.path, lineno, f"expected 4 coefficients per section line, got {len(tokens)}")
    pending.sections.append(_coefficients(state.path, lineno, tokens))
    _complete_if_done(state)


def _fail_truncated(state: _State, pending: _Pending, where: str) -> NoReturn:
    got = len(pending.sections) - 1
    _fail(
        state.path,
        pending.lineno,
        f"{_label(pending.module, pending.index)} declares SECTIONS={pending.n_sections} "
        f"but only {got} of {pending.n_sections - 1} section line(s) follow before {where}",
    )


def _complete_if_done(state: _State) -> None:
    pending = state.pending
    if pending is None or len(pending.sections) < pending.n_sections:
        return
    stage = FilterStage(
        index=pending.index,
        name=pending.name,
        sos=_online_to_sos(pending.gain, pending.sections),
        design=None,
        switching=pending.switching,
    )
    state.stages[(pending.module, pending.index)] = (pending.lineno, stage)
    state.pending = None


def _online_to_sos(gain: float, sections: list[tuple[float, float, float, float]]) -> NDArray[np.float64]:
    """Online ``gain, (a1 a2 b1 b2)...`` -> scipy sos with the gain in the first numerator."""
    sos = np.array([[1.0, b1, b2, 1.0, a1, a2] for a1, a2, b1, b2 in sections])
    sos[0, :3] *= gain
    return sos


def _coefficients(path: str, lineno: int, tokens: list[str]) -> tuple[float, float, float, float]:
    a1, a2, b1, b2 = (_number(path, lineno, t, n) for t, n in zip(tokens, ("A1", "A2", "B1", "B2")))
    return a1, a2, b1, b2


def _number(path: str, lineno: int, token: str, what: str) -> float:
    # A stricter grammar than float(): 'nan', 'inf' and '1_0' are not foton numbers.
    if not _FLOAT_RE.match(token):
        _fail(path, lineno, f"{what} must be a number, got {token!r}")
    value = float(token)
    if not math.isfinite(value):
        _fail(path, lineno, f"{what} overflows: {token!r}")
    return value


def _integer(path: str, lineno: int, token: str, what: str) -> int:
    if not _INT_RE.match(token):
        _fail(path, lineno, f"{what} must be an integer, got {token!r}")
    return int(token)


def _non_negative(path: str, lineno: int, token: str, what: str) -> int:
    value = _integer(path, lineno, token, what)
    if value < 0:
        _fail(path, lineno, f"{what} must not be negative, got {token}")
    return value


def _stage_index(path: str, lineno: int, token: str) -> int:
    index = _integer(path, lineno, token, "INDEX")
    if not 0 <= index < N_STAGES:
        _fail(path, lineno, f"INDEX must be 0..{N_STAGES - 1} (FM1..FM10), got {token}")
    return index


def _label(module: str, index: int) -> str:
    return f"{module} FM{index + 1} (index {index})"


def _assemble(state: _State) -> FilterFile:
    if not state.listed and state.first_seen:
        _note(state, min(state.first_seen.values()), "no '# MODULES' line; modules taken from the stage lines")
    else:
        for module, lineno in state.first_seen.items():
            if module not in state.listed:
                _note(state, lineno, f"module {module} has stages but is not listed in '# MODULES'")
    modules: dict[str, list[FilterStage]] = {name: [] for name in state.listed}
    for (module, _), (_, stage) in sorted(state.stages.items(), key=lambda kv: kv[0][1]):
        modules.setdefault(module, []).append(_with_design(state, module, stage))
    # setdefault above appends unlisted modules in index order; restore appearance order.
    modules = _order_modules(modules, state)
    _check_orphan_designs(state)
    rate = state.rate[1] if state.rate is not None else None
    _check_module_rates(state, rate)
    return FilterFile(path=state.path, rate_hz=rate, modules=modules)


def _order_modules(modules: dict[str, list[FilterStage]], state: _State) -> dict[str, list[FilterStage]]:
    unlisted = sorted((m for m in modules if m not in state.listed), key=lambda m: state.first_seen[m])
    return {m: modules[m] for m in [*state.listed, *unlisted]}


def _with_design(state: _State, module: str, stage: FilterStage) -> FilterStage:
    design = state.designs.get((module, stage.index))
    if design is None:
        return stage
    return FilterStage(stage.index, stage.name, stage.sos, design[1], stage.switching)


def _check_orphan_designs(state: _State) -> None:
    for (module, index), (lineno, _) in state.designs.items():
        if (module, index) not in state.stages:
            _note(state, lineno, f"DESIGN for {_label(module, index)} has no coefficient lines; ignored")


def _check_module_rates(state: _State, rate: float | None) -> None:
    for lineno, module, module_rate in state.module_rates:
        if rate is not None and module_rate != rate:
            _note(state, lineno, f"{module} samples at {module_rate:g} Hz, not at the file's {rate:g} Hz")


# ----------------------------------------------------------------------------- writing


def write_filter_file(
    path: str | os.PathLike[str],
    modules: Mapping[str, Sequence[FilterStage]],
    rate_hz: float,
) -> None:
    """Write a foton filter file that :func:`read_filter_file` reads back identically.

    Parameters
    ----------
    path : str or path-like
        File to (over)write.
    modules : mapping of str to sequence of FilterStage
        Module name -> stages; every module is listed in ``# MODULES``, also
        those without stages. Stages are written sorted by index.
    rate_hz : float
        Model sampling rate for ``# SAMPLING RATE``.

    Raises
    ------
    FotonError
        If a name, index, switching field, design string or SOS cannot be
        written in the format (e.g. a section with ``b0 == 0`` but a nonzero
        numerator, which foton's monic online sections cannot hold), or the
        file cannot be written. The message names the file and the stage.

    Notes
    -----
    Sections are normalised to foton's online form: each section's ``b0/a0``
    goes into the stage gain. For stages read from a file this reproduces the
    coefficients bit for bit; design strings are written on one line with
    surrounding whitespace stripped. Missing switching fields default to
    :data:`DEFAULT_SWITCHING`.
    """
    where = os.fspath(path)
    _check_rate(where, rate_hz)
    text = _format_file(where, modules, rate_hz)
    try:
        with open(where, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
    except OSError as exc:
        msg = f"{where}: cannot write filter file: {exc.strerror or exc}"
        raise FotonError(msg) from exc


def _check_rate(path: str, rate_hz: float) -> None:
    if not (isinstance(rate_hz, (int, float)) and math.isfinite(rate_hz) and rate_hz > 0):
        msg = f"{path}: sampling rate must be a positive number of Hz, got {rate_hz!r}"
        raise FotonError(msg)


def _format_file(path: str, modules: Mapping[str, Sequence[FilterStage]], rate_hz: float) -> str:
    names = list(modules)
    for name in names:
        _check_token(path, name, f"module name {name!r}", max_length=None)
    out = ["# FILTERS FOR ONLINE SYSTEM", "#", "# Computer generated file: DO NOT EDIT", "#"]
    # Four names per line, as the RCG code generator writes them.
    out += ["# MODULES " + " ".join(names[k : k + 4]) for k in range(0, len(names), 4)]
    out += ["#", f"# SAMPLING RATE {_format_rate(rate_hz)}", "#"]
    for name in names:
        out += _module_lines(path, name, modules[name])
    return "\n".join(out) + "\n"


def _format_rate(rate_hz: float) -> str:
    return str(int(rate_hz)) if float(rate_hz).is_integer() else repr(float(rate_hz))


def _module_lines(path: str, module: str, stages: Sequence[FilterStage]) -> list[str]:
    out = ["#" * 80, f"### {module:<72} ###", "#" * 80]
    seen: set[int] = set()
    for stage in sorted(stages, key=lambda s: s.index):
        if not (isinstance(stage.index, int) and 0 <= stage.index < N_STAGES):
            _fail_write(path, module, stage, f"index must be 0..{N_STAGES - 1}")
        if stage.index in seen:
            _fail_write(path, module, stage, "two stages with this index")
        seen.add(stage.index)
        out += _stage_lines(path, module, stage)
    return out


def _stage_lines(path: str, module: str, stage: FilterStage) -> list[str]:
    _check_token(path, stage.name, f"{_label(module, stage.index)}: name {stage.name!r}", MAX_NAME_LENGTH)
    stype, ramp, timeout = _switching_fields(path, module, stage)
    gain, sections = _sos_to_online(path, module, stage)
    out = []
    if stage.design is not None:
        out.append(f"# DESIGN   {module} {stage.index} {_design_line(path, module, stage)}".rstrip())
    a1, a2, b1, b2 = sections[0]
    out.append(
        f"{module} {stage.index} {stype} {len(sections)} {ramp} {timeout} {stage.name} "
        + " ".join(_fmt(v) for v in (gain, a1, a2, b1, b2))
    )
    out += ["    " + " ".join(_fmt(v) for v in sec) for sec in sections[1:]]
    return out


def _fmt(value: float) -> str:
    # repr is the shortest text that parses back to the same double.
    return repr(float(value))


def _design_line(path: str, module: str, stage: FilterStage) -> str:
    design = str(stage.design).strip()
    if "\n" in design or "\r" in design:
        _fail_write(path, module, stage, "design string must be a single line")
    if design.endswith("\\"):
        _fail_write(path, module, stage, "design string must not end with a backslash (it marks a continuation)")
    return design


def _switching_fields(path: str, module: str, stage: FilterStage) -> tuple[int, int, int]:
    unknown = set(stage.switching) - set(DEFAULT_SWITCHING)
    if unknown:
        _fail_write(path, module, stage, f"unknown switching field(s) {sorted(unknown)}; expected type, ramp, timeout")
    fields = {**DEFAULT_SWITCHING, **stage.switching}
    values = []
    for key in ("type", "ramp", "timeout"):
        value = fields[key]
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            _fail_write(path, module, stage, f"switching {key} must be a non-negative integer, got {value!r}")
        values.append(int(value))
    stype = values[0]
    if stype // 10 not in INPUT_SWITCHING or stype % 10 not in OUTPUT_SWITCHING:
        _fail_write(path, module, stage, f"switching type must be 11..14 or 21..24, got {stype}")
    return stype, values[1], values[2]


def _sos_to_online(
    path: str, module: str, stage: FilterStage
) -> tuple[float, list[tuple[float, float, float, float]]]:
    """Scipy sos -> online ``gain`` and monic ``(a1, a2, b1, b2)`` sections."""
    if stage.sos.shape[0] > MAX_SECTIONS:
        _fail_write(path, module, stage, f"{stage.sos.shape[0]} sections; the RCG takes at most {MAX_SECTIONS}")
    gain = 1.0
    sections = []
    for k, (b0, b1, b2, a0, a1, a2) in enumerate(stage.sos.tolist()):
        if a0 == 0.0:
            _fail_write(path, module, stage, f"section {k} has a0 == 0")
        if b0 == 0.0:
            if b1 != 0.0 or b2 != 0.0:
                _fail_write(path, module, stage, f"section {k} has b0 == 0; foton sections need a monic numerator")
            # A zero numerator is a zero gain; its b1, b2 are undefined and written as 0.
            gain = 0.0
            sections.append((a1 / a0, a2 / a0, 0.0, 0.0))
            continue
        gain *= b0 / a0
        sections.append((a1 / a0, a2 / a0, _exact_quotient(b1, b0), _exact_quotient(b2, b0)))
    return gain, sections


def _exact_quotient(x: float, d: float) -> float:
    """``x / d``, nudged by an ulp or two so that ``d * result == x`` when possible.

    The reader folds the gain in as ``gain * b1``; picking the quotient that
    multiplies back exactly makes write-then-read reproduce the sos bit for bit.
    """
    q = x / d
    if d * q == x:
        return q
    for direction in (math.inf, -math.inf):
        c = q
        for _ in range(4):
            c = math.nextafter(c, direction)
            if d * c == x:
                return c
    return q


def _check_token(path: str, token: str, what: str, max_length: int | None) -> None:
    # Names are single whitespace-free tokens; a leading '#' would make the line a comment.
    if not isinstance(token, str) or not token or any(ch.isspace() for ch in token) or token.startswith("#"):
        msg = f"{path}: {what} must be one non-empty token without whitespace, not starting with '#'"
        raise FotonError(msg)
    if max_length is not None and len(token) > max_length:
        msg = f"{path}: {what} is longer than {max_length} characters"
        raise FotonError(msg)


def _fail_write(path: str, module: str, stage: FilterStage, problem: str) -> NoReturn:
    msg = f"{path}: {_label(module, stage.index)} {stage.name!r}: {problem}"
    raise FotonError(msg)
