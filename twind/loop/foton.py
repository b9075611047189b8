"""Foton filter *design strings*: parse them into continuous zpk, discretize them for the CDS.

A foton design string is what a commissioner types into foton (and what a filter file keeps
on its ``# DESIGN`` lines), e.g. ``zpk([0],[30],6.283185307179586,"n")`` or
``zpk([1],[10],1,"n")gain(3)``.  Factors written one after the other (optionally joined by
``*``) multiply.  Whitespace, newlines, backslash line continuations and ``%`` comments
(which IIRrational writes inside ``zpk`` vectors) are ignored.

Conventions
-----------
As LIGO's own foton reads them (``python-foton`` 4.1.5, the CDS DTT project's bindings,
``foton.FilterDesign(design, rate)``), measured function by function and held against it
by ``tests/test_foton_ligo.py`` over generated designs.  Each function is its own filter;
they multiply.  ``plane`` is ``"s"`` (rad/s, as written; the default), ``"f"`` (Hz, same
sign: ``s = 2 pi r``) or ``"n"`` (Hz, stable roots written positive: ``s = -2 pi r``, each
root divided by its magnitude, ``s/(2 pi)`` at the origin, so ``gain`` is the DC gain).

* ``zpk(zeros, poles, gain[, plane])``; complex roots ``a+i*b;a-i*b`` (also ``a+b*i``,
  ``bi``, ``i*-b``) in conjugate pairs; ``;`` or ``,`` between elements.
* ``pole(f[, gain[, plane]])`` = ``gain/(s + w)``, ``zero`` its inverse;
  ``pole2(f, Q[, gain[, plane]])`` = ``gain/(s^2 + (w/|Q|) s + w^2)`` (a double real pole
  at ``-w`` for ``|Q| <= 1/2``), ``zero2`` its inverse; ``w`` is ``f`` in "s", ``2 pi f``
  otherwise, "n" normalises.
* ``rpoly(num, den, gain)``: ``gain num(s)/den(s)``, coefficients highest power first.
* ``gain(g[, "scalar"|"dB"])``.
* ``notch(f, Q[, depth])``: zeros and poles at ``f``; foton's ``Q`` is ``f`` over *half*
  the width between the -3 dB points, so the poles' quality is ``sqrt(1 - 2 r^2) Q (4Q^2 -
  1)/(8Q^2 - 1)``, ``r`` the depth as a ratio (0 for depth 0, an infinitely deep notch;
  otherwise deeper than 3.01 dB), and the zeros' damping ``r`` times the poles'.
  ``resgain(f, Q[, height])`` is the inverse of the notch of depth ``height`` (30 dB by
  default).  Both need complex roots (quality above 1/2).
* ``comb(f, Q[, amplitude[, N]])``: a resgain (amplitude > 0) or notch (< 0; 0: infinitely
  deep) at ``f`` and its harmonics up to the N-th, all below Nyquist for N = 0.
* ``butter(type, order, f1[, f2])``, ``cheby1(type, order, ripple, f1[, f2])``,
  ``cheby2(type, order, attenuation, f1[, f2])``, ``ellip(type, order, ripple,
  attenuation, f1[, f2])``, type ``"LowPass"``, ``"HighPass"``, ``"BandPass"`` or
  ``"BandStop"`` (any case), band edges in either order: digital designs, the analog
  prototype at the prewarped edges then the bilinear transform (``scipy.signal`` with
  ``fs``).
* z-plane designs: ``sos(gain, [b1;b2;a1;a2;...][, "s"|"o"])`` (sections ``(1 + b1/z +
  b2/z^2)/(1 + a1/z + a2/z^2)``; "o" orders each a1, a2, b1, b2), ``biquad(b0, b1, b2, a1,
  a2)``, ``direct([b0;b1;...], [a1;a2;...])`` (denominator ``1 - a1/z - ...``) and
  ``zroots(zeros, poles[, gain])`` (``gain prod(z - zeros)/prod(z - poles)``); a numerator
  shorter than the denominator counts its missing zeros at z = -1.
* A function with more zeros than poles gets foton's poles at twice the sample rate: a
  Butterworth pair for two missing, ``-2fs/(s + 2fs)`` for one, which turns the sign of the
  response (``zero(5)`` has DC gain -5).
* Poles in the right half plane (or outside the unit circle, or at or above Nyquist) are
  refused, as foton refuses them.

Discretization
--------------
Every s-plane root is prewarped radially, ``|r| -> 2 fs tan(|r| / 2 fs)`` (a root above
Nyquist folds through infinity), then ``s -> 2 fs (z-1)/(z+1)``, each factor normalised at
DC; missing zeros go to z = -1.  The digital designs (IIR, z-plane, foton's extra poles)
depend on the sample rate: :func:`parse_design` with ``rate_hz`` returns the continuous
filter whose discretization is exactly foton's (roots unwarped, the inverse of the
prewarp), which is what the model's continuous responses use.

What the bilinear transform cannot keep is the high-frequency asymptote: each pole in excess
of the zeros makes the discrete response differ by ``tan(x)/x - 1 ~ x^2/3``, ``x = pi f/fs``
(1.2e-4 at 100 Hz for 16384 Hz); the nominal FM2 (8 poles) is therefore 1e-3 off at 100 Hz,
as any bilinear CDS implementation of it is.
"""

from __future__ import annotations

import math
import numbers
import os
import re
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Union

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import signal

from twind.errors import FotonError
from twind.loop import FOTON_READERS, FOTON_VARIABLE

__all__ = [
    "NOMINAL_FM1",
    "NOMINAL_FM2",
    "NOMINAL_FM3",
    "ZPK",
    "design_to_sos",
    "implementation",
    "n_plane_design",
    "parse_design",
    "zpk_to_sos",
]

TWO_PI = 2.0 * math.pi
MAX_ORDER = 20  # twind's limit for one design; the RCG runs at most 10 sections a stage

# --- nominal damping controller (sos_etmx_nominal.json "controller"), foton "n" plane ------
# FM1: an "n"-plane zero at the origin is s/(2 pi) (unity at 1 Hz); the gain 2 pi makes it s.
NOMINAL_FM1 = 'zpk([0],[30.000330908653446],6.283185307179586,"n")'
# FM2 "Cheby": pole pairs (f, Q) written f/(2Q) +- i*f*sqrt(1 - 1/(4Q^2)) in Hz, DC gain 1.
NOMINAL_FM2 = (
    "zpk([],"
    "[2.784757795351504+i*3.1942103905747907;2.784757795351504-i*3.1942103905747907;"
    "3.5585347603474+i*4.1428457169986554;3.5585347603474-i*4.1428457169986554;"
    "2.038584192971233+i*8.726745077486314;2.038584192971233-i*8.726745077486314;"
    "0.7461736023194235+i*11.92095546818733;0.7461736023194235-i*11.92095546818733]"
    ',1,"n")'
)
# FM3 "BounceRoll": notch zeros on the imaginary axis and their pole pairs, DC gain 1.
NOMINAL_FM3 = (
    "zpk([0+i*15.849353127564198;0-i*15.849353127564198;"
    "0+i*15.985447321046138;0-i*15.985447321046138;"
    "0+i*16.19983737166611;0-i*16.19983737166611;"
    "0+i*16.338941081813793;0-i*16.338941081813793;"
    "0+i*23.140320589850464;0-i*23.140320589850464;"
    "0+i*23.26601400048155;0-i*23.26601400048155;"
    "0+i*23.4787668327507;0-i*23.4787668327507;"
    "0+i*23.60629860829092;0-i*23.60629860829092],"
    "[0.5211835443328433+i*15.408608752182579;0.5211835443328433-i*15.408608752182579;"
    "0.058251837358148116+i*15.601957325436517;0.058251837358148116-i*15.601957325436517;"
    "0.06196994001969834+i*16.597791687192313;0.06196994001969834-i*16.597791687192313;"
    "0.5678095655664466+i*16.787090745525184;0.5678095655664466-i*16.787090745525184;"
    "0.36960722373365074+i*22.87824676135586;0.36960722373365074-i*22.87824676135586;"
    "0.0389075111666054+i*23.001902251253206;0.0389075111666054-i*23.001902251253206;"
    "0.04017003191967269+i*23.748286093426035;0.04017003191967269-i*23.748286093426035;"
    "0.38563718208449665+i*23.870482240972727;0.38563718208449665-i*23.870482240972727]"
    ',1,"n")'
)

ComplexArray = NDArray[np.complex128]
Arg = Union[float, complex, str, list[complex]]


# ============================================================================================
# Continuous zero-pole-gain
# ============================================================================================
@dataclass(frozen=True, eq=False)
class ZPK:
    """Continuous transfer function ``k * prod(s - z) / prod(s - p)``, s in rad/s.

    Attributes
    ----------
    zeros : ndarray of complex
        s-plane zeros in rad/s (left-half-plane roots have a negative real part).
    poles : ndarray of complex
        s-plane poles in rad/s.
    gain : float
        The overall factor ``k``.
    """

    zeros: ComplexArray
    poles: ComplexArray
    gain: float

    def __post_init__(self) -> None:
        # Read-only copies keep a frozen ZPK really immutable.
        for name in ("zeros", "poles"):
            roots = np.array(getattr(self, name), dtype=complex).ravel()
            roots.setflags(write=False)
            object.__setattr__(self, name, roots)
        object.__setattr__(self, "gain", float(self.gain))

    def response(self, f_hz: ArrayLike) -> ComplexArray:
        """Complex frequency response.

        Parameters
        ----------
        f_hz : array_like
            Frequencies in Hz.

        Returns
        -------
        ndarray of complex
            ``H(2 pi i f)``, same shape as `f_hz`.
        """
        f = np.asarray(f_hz, dtype=float)
        s = (2j * math.pi * f).ravel()[:, None]
        if self.zeros.size + self.poles.size <= 40:
            num = np.prod(s - self.zeros[None, :], axis=1)
            den = np.prod(s - self.poles[None, :], axis=1)
            return (self.gain * num / den).reshape(f.shape)
        with np.errstate(divide="ignore", invalid="ignore"):  # a comb's hundreds of roots
            log_h = (np.sum(np.log(s - self.zeros[None, :]), axis=1)
                     - np.sum(np.log(s - self.poles[None, :]), axis=1))
        return (self.gain * np.exp(log_h)).reshape(f.shape)

    def __mul__(self, other: ZPK) -> ZPK:
        """Cascade (product) of two transfer functions.

        Parameters
        ----------
        other : ZPK

        Returns
        -------
        ZPK
        """
        if not isinstance(other, ZPK):
            return NotImplemented
        return ZPK(np.concatenate([self.zeros, other.zeros]),
                   np.concatenate([self.poles, other.poles]),
                   self.gain * other.gain)

    def is_finite(self) -> bool:
        """Whether every root and the gain are finite numbers.

        Returns
        -------
        bool
        """
        return bool(np.all(np.isfinite(self.zeros)) and np.all(np.isfinite(self.poles))
                    and math.isfinite(self.gain))

    @staticmethod
    def unity() -> ZPK:
        """The transfer function 1.

        Returns
        -------
        ZPK
        """
        return ZPK(np.empty(0, complex), np.empty(0, complex), 1.0)

    def __repr__(self) -> str:
        return f"ZPK(zeros={self.zeros!r}, poles={self.poles!r}, gain={self.gain!r})"


# ============================================================================================
# Tokenizer
# ============================================================================================
@dataclass(frozen=True)
class _Token:
    kind: str  # "num", "name", "str", or the punctuation character itself
    text: str
    pos: int


_TOKEN_RE = re.compile(
    r"""(?P<ws>\s+|\\)
      | (?P<comment>%[^\n]*)
      | (?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)
      | (?P<name>[A-Za-z_][A-Za-z0-9_]*)
      | (?P<str>"[^"\n]*"|'[^'\n]*')
      | (?P<punct>[()\[\],;*+\-])
    """,
    re.VERBOSE | re.ASCII,
)


class _Failer:
    """Builds FotonErrors that always name the design string; carries the sample rate the
    design is read at (None: the continuous design as written)."""

    def __init__(self, design: str, rate_hz: float | None = None) -> None:
        self.design = design
        self.rate_hz = rate_hz

    def __call__(self, msg: str) -> FotonError:
        return FotonError(f"{msg} in design {self.design!r}")


def _tokenize(design: str, fail: _Failer) -> list[_Token]:
    tokens: list[_Token] = []
    pos = 0
    while pos < len(design):
        m = _TOKEN_RE.match(design, pos)
        if m is None:
            ch = design[pos]
            if ch in "\"'":
                raise fail(f"unterminated string starting at position {pos}")
            raise fail(f"unexpected character {ch!r} at position {pos}")
        kind = m.lastgroup or ""
        if kind == "punct":
            tokens.append(_Token(m.group(), m.group(), pos))
        elif kind in ("num", "name"):
            tokens.append(_Token(kind, m.group(), pos))
        elif kind == "str":
            tokens.append(_Token("str", m.group()[1:-1], pos))
        pos = m.end()
    return tokens


def _check_brackets(tokens: Sequence[_Token], fail: _Failer) -> None:
    """Report unbalanced brackets before parsing, with the position a user can look at."""
    stack: list[_Token] = []
    closer = {")": "(", "]": "["}
    for tok in tokens:
        if tok.kind in ("(", "["):
            stack.append(tok)
        elif tok.kind in closer:
            if not stack:
                raise fail(f"unbalanced parentheses: {tok.kind!r} at position {tok.pos} "
                           "has no opening partner")
            if stack[-1].kind != closer[tok.kind]:
                raise fail(f"unbalanced parentheses: {stack[-1].kind!r} at position "
                           f"{stack[-1].pos} is closed by {tok.kind!r} at position {tok.pos}")
            stack.pop()
    if stack:
        raise fail(f"unbalanced parentheses: {stack[-1].kind!r} at position "
                   f"{stack[-1].pos} is never closed")


# ============================================================================================
# Parser: design := { NAME '(' args ')' [ '*' ] }
# ============================================================================================
class _Parser:
    def __init__(self, design: str, rate_hz: float | None = None) -> None:
        self.fail = _Failer(design, rate_hz)
        self.tokens = _tokenize(design, self.fail)
        _check_brackets(self.tokens, self.fail)
        self.i = 0

    # -- token helpers -------------------------------------------------------------------
    def _peek(self, ahead: int = 0) -> _Token | None:
        j = self.i + ahead
        return self.tokens[j] if j < len(self.tokens) else None

    def _take(self, what: str = "more input") -> _Token:
        tok = self._peek()
        if tok is None:
            raise self.fail(f"expected {what}, but the string ends")
        self.i += 1
        return tok

    def _expect(self, kind: str, what: str) -> _Token:
        tok = self._take(what)
        if tok.kind != kind:
            raise self.fail(f"expected {what} at position {tok.pos}, got {tok.text!r}")
        return tok

    # -- grammar -------------------------------------------------------------------------
    def parse(self) -> ZPK:
        result = ZPK.unity()
        while self._peek() is not None:
            with np.errstate(all="ignore"):
                result = result * self._factor()
            if not result.is_finite():
                raise self.fail("the overall gain overflows")
            tok = self._peek()
            if tok is not None and tok.kind == "*":
                self.i += 1
                if self._peek() is None:
                    raise self.fail("design ends with '*'")
        return result

    def _factor(self) -> ZPK:
        name = self._expect("name", "a foton function name")
        self._expect("(", f"'(' after {name.text!r}")
        args = self._args()
        func = _FUNCTIONS.get(name.text)
        if func is None:
            raise self.fail(f"unknown foton function {name.text!r}")
        with np.errstate(all="ignore"):
            factor = func(name.text, args, self.fail)
        if not factor.is_finite():
            raise self.fail(f"{name.text}(): numbers out of range give a non-finite filter")
        rate = self.fail.rate_hz
        if rate is not None and np.any(np.abs(factor.poles) >= math.pi * rate):
            raise self.fail(f"{name.text}(): a pole is not below the Nyquist frequency "
                            f"{rate / 2:g} Hz")
        return factor

    def _args(self) -> list[Arg]:
        args: list[Arg] = []
        if self._peek_kind() == ")":
            self.i += 1
            return args
        while True:
            args.append(self._arg())
            tok = self._take("',' or ')'")
            if tok.kind == ")":
                return args
            if tok.kind != ",":
                raise self.fail(f"expected ',' or ')' at position {tok.pos}, got {tok.text!r}")

    def _peek_kind(self) -> str | None:
        tok = self._peek()
        return None if tok is None else tok.kind

    def _arg(self) -> Arg:
        kind = self._peek_kind()
        if kind == "str":
            return self._take().text
        if kind == "[":
            return self._vector()
        return self._number()

    def _vector(self) -> list[complex]:
        self._expect("[", "'['")
        values: list[complex] = []
        while True:
            kind = self._peek_kind()
            if kind == "]":
                self.i += 1
                return values
            if kind in (";", ","):
                self.i += 1  # empty or trailing separators are harmless
                continue
            values.append(self._number())

    def _number(self) -> complex:
        """A real or complex literal: terms joined by + and -, e.g. ``-1.5+i*2e3``."""
        total = 0j
        sign = self._sign(required=False)
        total += sign * self._term()
        while self._peek_kind() in ("+", "-"):
            sign = self._sign(required=True)
            total += sign * self._term()
        if not (math.isfinite(total.real) and math.isfinite(total.imag)):
            raise self.fail("number is not finite")
        return total

    def _sign(self, *, required: bool) -> float:
        sign = 1.0
        seen = False
        while self._peek_kind() in ("+", "-"):
            seen = True
            if self._take().kind == "-":
                sign = -sign
        if required and not seen:
            raise self.fail("expected '+' or '-'")
        return sign

    def _term(self) -> complex:
        tok = self._take("a number")
        if tok.kind == "num":
            value = float(tok.text)
            if self._is_imag_unit(self._peek()):
                self.i += 1
                return 1j * value
            if self._peek_kind() == "*" and self._is_imag_unit(self._peek(1)):
                self.i += 2
                return 1j * value
            return complex(value)
        if self._is_imag_unit(tok):
            if self._peek_kind() == "*":
                self.i += 1
                sign = self._sign(required=False)  # foton reads i*-3 as -3i
                num = self._expect("num", "a number after 'i*'")
                return 1j * sign * float(num.text)
            return 1j
        raise self.fail(f"expected a number at position {tok.pos}, got {tok.text!r}")

    @staticmethod
    def _is_imag_unit(tok: _Token | None) -> bool:
        return tok is not None and tok.kind == "name" and tok.text in ("i", "j")


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


# ============================================================================================
# Planes and foton's normalisations
# ============================================================================================
_PLANES = ("s", "f", "n")
_NONE = np.empty(0, complex)


def _abs_norm(roots: ComplexArray) -> float:
    """``prod |r|``, 2 pi for each root at the origin: what makes a root "normalised"."""
    nonzero = roots[roots != 0]
    return float(np.prod(np.abs(nonzero))) * TWO_PI ** (roots.size - nonzero.size)


def _normalised(zeros: ComplexArray, poles: ComplexArray, gain: float, plane: str) -> ZPK:
    """s-plane roots and a gain written in `plane`: in "n" each root is divided by its
    magnitude (``1 + s/|w|``, ``s/(2 pi)`` at the origin), so `gain` is the DC gain of
    stable roots."""
    if plane != "n":
        return ZPK(zeros, poles, gain)
    return ZPK(zeros, poles, gain * _abs_norm(poles) / _abs_norm(zeros))


def _zpk_from_plane(zeros: ComplexArray, poles: ComplexArray, gain: float,
                    plane: str) -> ZPK:
    """Convert roots and gain written in foton plane `plane` to an s-plane ZPK."""
    scale = {"s": 1.0, "f": TWO_PI, "n": -TWO_PI}[plane]
    return _normalised(scale * zeros, scale * poles, gain, plane)


def _dc_norm(roots: ComplexArray, origin: float = TWO_PI) -> float:
    """Product turning prod(s - r) into prod(1 - s/r), with s/origin for the roots at 0."""
    nonzero = roots[roots != 0]
    n_origin = roots.size - nonzero.size
    return float(np.real(np.prod(-nonzero))) * origin**n_origin


def _pair(w: float, q: float) -> ComplexArray:
    """Roots of ``s^2 + (w/|Q|) s + w^2``; foton puts a double real root at ``-w`` when
    ``|Q| <= 1/2``."""
    q = abs(q)
    if q <= 0.5:
        return np.array([complex(-w), complex(-w)])
    im = abs(w) * math.sqrt(1.0 - 1.0 / (4.0 * q * q))
    return np.array([complex(-w / (2 * q), im), complex(-w / (2 * q), -im)])


def _stable(fname: str, poles: ComplexArray, fail: _Failer) -> None:
    """foton takes poles in the left half plane or on the imaginary axis only."""
    bad = poles[poles.real > 0]
    if bad.size:
        raise fail(f"{fname}(): pole {_fmt(bad[0])} rad/s is in the right half plane "
                   "(foton takes stable poles only)")


def _with_foton_poles(unit: ZPK, fail: _Failer) -> ZPK:
    """Poles foton adds to a function with more zeros than poles, at twice the sample rate.

    foton packs a function's zeros and its poles two by two into second-order sections;
    a section with two zeros and no pole gets a Butterworth pair at ``|s| = 2 fs`` (Q
    1/sqrt(2)), a section one pole short a real pole at ``s = -2 fs`` written ``-2fs/(s +
    2fs)``: each such real pole turns the sign of the response.  Without a sample rate
    the design is kept as written.
    """
    n_z, n_p = unit.zeros.size, unit.poles.size
    if n_z <= n_p or fail.rate_hz is None:
        return unit
    c = 2.0 * fail.rate_hz
    added: list[complex] = []
    sign = 1.0
    for k in range(0, n_z, 2):
        short = min(2, n_z - k) - max(0, min(2, n_p - k))
        if short == 2:
            added += [c * complex(-1, 1) / math.sqrt(2), c * complex(-1, -1) / math.sqrt(2)]
        elif short == 1:
            added.append(complex(-c))
            sign = -sign
    return ZPK(unit.zeros, np.concatenate([unit.poles, added]),
               unit.gain * sign * c ** len(added))


def _unwarp(roots: ComplexArray, rate_hz: float) -> ComplexArray:
    """Undo :func:`_prewarp`: the continuous roots whose prewarped images are `roots`."""
    c = 2.0 * rate_hz
    out = np.array(roots, dtype=complex)
    mag = np.abs(out)
    nz = mag > 0
    out[nz] *= c * np.arctan(mag[nz] / c) / mag[nz]
    return out


def _unwarped(zeros: ComplexArray, poles: ComplexArray, gain: float, rate_hz: float) -> ZPK:
    """The continuous ZPK that :func:`zpk_to_sos` turns into the plain bilinear transform
    of ``gain prod(s - zeros)/prod(s - poles)``."""
    z_s, p_s = _unwarp(zeros, rate_hz), _unwarp(poles, rate_hz)
    k = (gain * _dc_norm(zeros, 1.0) / _dc_norm(poles, 1.0)
         * _dc_norm(p_s, 1.0) / _dc_norm(z_s, 1.0))
    return ZPK(z_s, p_s, k)


# ============================================================================================
# foton functions
# ============================================================================================
FotonFunction = Callable[[str, Sequence[Arg], _Failer], ZPK]


def _plane(fname: str, args: Sequence[Arg], k: int, fail: _Failer) -> str:
    """The optional plane argument at `k`, ``"s"`` when absent (foton's default)."""
    plane = _string(fname, args, k, "plane", fail) if len(args) > k else "s"
    if plane not in _PLANES:
        raise fail(f'{fname}(): plane must be one of "s", "f", "n", got "{plane}"')
    return plane


def _f_zpk(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    _arity(fname, args, 3, 4, fail)
    zeros = _paired(_vector_arg(fname, args, 0, "zeros", fail), fname, "zero", fail)
    poles = _paired(_vector_arg(fname, args, 1, "poles", fail), fname, "pole", fail)
    gain = _real(fname, args, 2, "gain", fail)
    unit = _zpk_from_plane(zeros, poles, gain, _plane(fname, args, 3, fail))
    _stable(fname, unit.poles, fail)
    return _with_foton_poles(unit, fail)


def _f_rpoly(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    _arity(fname, args, 3, 3, fail)
    polys = []
    for k, what in ((0, "numerator"), (1, "denominator")):
        coef = _vector_arg(fname, args, k, what, fail)
        if np.any(coef.imag != 0):
            raise fail(f"{fname}(): {what} coefficients must be real")
        coef = np.trim_zeros(coef.real, "f")
        if coef.size == 0:
            raise fail(f"{fname}(): {what} polynomial is zero")
        polys.append(coef)
    gain = _real(fname, args, 2, "gain", fail)
    num, den = polys
    with np.errstate(all="ignore"):
        zeros, poles = np.roots(num), np.roots(den)
    if not (np.all(np.isfinite(zeros)) and np.all(np.isfinite(poles))):
        raise fail(f"{fname}(): polynomial roots are not finite")
    _stable(fname, poles, fail)
    return _with_foton_poles(ZPK(zeros, poles, gain * num[0] / den[0]), fail)


def _f_gain(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    _arity(fname, args, 1, 2, fail)
    g = _real(fname, args, 0, "gain", fail)
    unit = _string(fname, args, 1, "format", fail).lower() if len(args) == 2 else "scalar"
    if unit == "db":
        g = 10.0 ** (g / 20.0)
        if not math.isfinite(g):
            raise fail(f"{fname}(): gain in dB is too large")
    elif unit != "scalar":
        raise fail(f'{fname}(): format must be "scalar" or "dB", got "{unit}"')
    return ZPK(_NONE, _NONE, g)


def _f_pole(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    """pole(f[, gain[, plane]]) = gain/(s + f), zero(...) = gain (s + f); f in rad/s in
    "s", in Hz in "f" and "n"."""
    _arity(fname, args, 1, 3, fail)
    f = _real(fname, args, 0, "frequency", fail)
    gain = _real(fname, args, 1, "gain", fail) if len(args) > 1 else 1.0
    plane = _plane(fname, args, 2, fail)
    root = np.array([complex(-f if plane == "s" else -TWO_PI * f)])
    if fname == "pole":
        _stable(fname, root, fail)
        return _normalised(_NONE, root, gain, plane)
    return _with_foton_poles(_normalised(root, _NONE, gain, plane), fail)


def _f_pole2(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    """pole2(f, Q[, gain[, plane]]) = gain/(s^2 + (w/Q) s + w^2), zero2 its inverse."""
    _arity(fname, args, 2, 4, fail)
    f = _real(fname, args, 0, "frequency", fail)
    q = _real(fname, args, 1, "Q", fail)
    gain = _real(fname, args, 2, "gain", fail) if len(args) > 2 else 1.0
    plane = _plane(fname, args, 3, fail)
    roots = _pair(f if plane == "s" else TWO_PI * f, q)
    if fname == "pole2":
        _stable(fname, roots, fail)
        return _normalised(_NONE, roots, gain, plane)
    return _with_foton_poles(_normalised(roots, _NONE, gain, plane), fail)


_SQRT2_DB = 20.0 * math.log10(math.sqrt(2.0))  # 3.01 dB: a notch must be deeper than this


def _f_notch(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    """notch(f, Q[, depth]) and resgain(f, Q[, height]) as foton designs them.

    foton's Q is ``f`` over *half* the width between the -3 dB points: the poles' Q is
    ``sqrt(1 - 2 r^2) Q (4Q^2 - 1)/(8Q^2 - 1)`` with ``r`` the notch's depth as a ratio
    (0 for depth 0, an infinitely deep notch); the zeros share the poles' frequency with
    ``r`` times their damping.  resgain is the inverse of the notch of depth ``height``
    (default 30 dB).
    """
    _arity(fname, args, 2, 3, fail)
    f = _positive(fname, args, 0, "frequency", fail)
    q = _positive(fname, args, 1, "Q", fail)
    what = "depth" if fname == "notch" else "height"
    level = _real(fname, args, 2, what, fail) if len(args) == 3 else (
        0.0 if fname == "notch" else 30.0)
    ratio = 0.0 if (fname == "notch" and level == 0) else 10.0 ** (-level / 20.0)
    if level < 0 or 1.0 - 2.0 * ratio**2 <= 0:
        zero = ", or 0 for an infinitely deep notch" if fname == "notch" else ""
        raise fail(f"{fname}(): {what} must exceed {_SQRT2_DB:.2f} dB{zero}, got {level!r}")
    width = (8 * q * q - 1) / (q * (4 * q * q - 1))  # -3 dB width over f
    q_low = math.sqrt(1.0 - 2.0 * ratio**2) / width
    if q <= 0.5 or q_low <= 0.5:
        raise fail(f"{fname}(): Q {q!r} is too small for a {what} of {level!r} dB (the "
                   "roots would be real)")
    if fail.rate_hz is not None and f >= fail.rate_hz / 2:
        raise fail(f"{fname}(): {f!r} Hz is not below the Nyquist frequency "
                   f"{fail.rate_hz / 2:g} Hz")
    w = TWO_PI * f
    low = _pair(w, q_low)
    high = _pair(w, math.inf) if ratio == 0 else _pair(w, q_low / ratio)
    return ZPK(high, low, 1.0) if fname == "notch" else ZPK(low, high, 1.0)


_BAND_TYPES = {"lowpass": "lowpass", "highpass": "highpass",
               "bandpass": "bandpass", "bandstop": "bandstop"}


def _band_edges(fname: str, args: Sequence[Arg], k: int, btype: str,
                fail: _Failer) -> list[float]:
    """The edges in Hz; foton takes a band's two edges in either order."""
    needs_two = btype in ("bandpass", "bandstop")
    if len(args) != k + 1 + needs_two:
        want = "f1 and f2" if needs_two else "only f1"
        raise fail(f"{fname}(): a {btype} design takes {want} after its other arguments, "
                   f"got {len(args)} arguments in all")
    edges = sorted(_positive(fname, args, k + j, f"f{j + 1}", fail)
                   for j in range(1 + needs_two))
    if needs_two and edges[0] == edges[1]:
        raise fail(f"{fname}(): f1 and f2 must differ, both are {edges[0]!r}")
    rate = fail.rate_hz
    if rate is not None and edges[-1] >= rate / 2:
        raise fail(f"{fname}(): {edges[-1]!r} Hz is not below the Nyquist frequency "
                   f"{rate / 2:g} Hz")
    return edges


def _f_iir(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    """butter, cheby1, cheby2, ellip: with a sample rate, the digital design foton makes
    (the analog prototype at the prewarped edges, then the bilinear transform, as
    ``scipy.signal`` does with ``fs``); without, the analog prototype."""
    n_spec = {"butter": 0, "cheby1": 1, "cheby2": 1, "ellip": 2}[fname]
    _arity(fname, args, 3 + n_spec, 4 + n_spec, fail)
    raw_type = _string(fname, args, 0, "type", fail)
    btype = _BAND_TYPES.get(raw_type.lower())
    if btype is None:
        raise fail(f'{fname}(): type must be one of "LowPass", "HighPass", "BandPass", '
                   f'"BandStop", got "{raw_type}"')
    order = _order(fname, args, 1, fail)
    spec = [_positive(fname, args, 2 + j, ("ripple" if fname != "cheby2" and j == 0
                                             else "attenuation") + " (dB)", fail)
            for j in range(n_spec)]
    edges = _band_edges(fname, args, 2 + n_spec, btype, fail)
    rate = fail.rate_hz
    wn = [TWO_PI * e if rate is None else 2 * rate * math.tan(math.pi * e / rate)
          for e in edges]
    design = {"butter": signal.butter, "cheby1": signal.cheby1,
              "cheby2": signal.cheby2, "ellip": signal.ellip}[fname]
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            z, p, k = design(order, *spec, wn if len(wn) == 2 else wn[0], btype=btype,
                             analog=True, output="zpk")
    except (ValueError, ArithmeticError) as exc:
        raise fail(f"{fname}(): cannot design this filter ({exc})") from None
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(p)) and np.isfinite(k)):
        raise fail(f"{fname}(): the design has non-finite roots or gain")
    if rate is None:
        return ZPK(z, p, float(np.real(k)))
    return _unwarped(z, p, float(np.real(k)), rate)


# -- z-plane designs --------------------------------------------------------------------
def _rate(fname: str, fail: _Failer) -> float:
    if fail.rate_hz is None:
        raise fail(f"{fname}() is a z-plane design: it needs the sample rate")
    return fail.rate_hz


def _from_z(fname: str, zeros: ComplexArray, poles: ComplexArray, gain: float,
            fail: _Failer) -> ZPK:
    """The continuous ZPK whose discretization is ``gain prod(z - zeros)/prod(z - poles)``.

    Each root maps back through the bilinear transform and is unwarped; a zero at z = -1 is
    what :func:`zpk_to_sos` puts there for a pole in excess, and counts as 2 at DC, as a
    zero missing against the poles does in foton's ``zroots``.
    """
    rate = _rate(fname, fail)
    if np.any(np.abs(poles) > 1.0 + 1e-12):
        raise fail(f"{fname}(): a z-plane pole is outside the unit circle")
    at_origin = min(int(np.sum(zeros == 0)), int(np.sum(poles == 0)))
    zeros = np.concatenate([zeros[zeros != 0], np.zeros(int(np.sum(zeros == 0)) - at_origin)])
    poles = np.concatenate([poles[poles != 0], np.zeros(int(np.sum(poles == 0)) - at_origin)])
    zeros = zeros[np.abs(zeros + 1.0) > 1e-6]
    c = 2.0 * rate
    k = (gain * np.prod((1.0 + zeros) / c) / np.prod((1.0 + poles) / c)
         * 2.0 ** (poles.size - zeros.size))
    unit = _unwarped(c * (zeros - 1) / (zeros + 1), c * (poles - 1) / (poles + 1),
                     float(np.real(k)), rate)
    return _with_foton_poles(unit, fail)


def _polynomial(fname: str, coef: NDArray[np.float64], what: str,
                fail: _Failer) -> tuple[ComplexArray, float]:
    """Roots and leading coefficient of a polynomial written highest power first; foton
    reads a shorter numerator's missing zeros as zeros at z = -1 (see :func:`_from_z`)."""
    if coef.size == 0 or coef[0] == 0:
        raise fail(f"{fname}(): the {what}'s first coefficient (b0) must not be 0")
    return np.roots(coef).astype(complex), float(coef[0])


def _f_sos(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    """sos(gain, [b1;b2;a1;a2;...][, "s"|"o"]): sections ``(1 + b1/z + b2/z^2)/(1 + a1/z +
    a2/z^2)``; the "o" (online) format orders each section a1, a2, b1, b2."""
    _arity(fname, args, 2, 3, fail)
    gain = _real(fname, args, 0, "gain", fail)
    coef = _vector_arg(fname, args, 1, "coefficients", fail).real
    form = _string(fname, args, 2, "format", fail) if len(args) == 3 else "s"
    if form not in ("s", "o"):
        raise fail(f'{fname}(): format must be "s" or "o", got "{form}"')
    if coef.size == 0 or coef.size % 4:
        raise fail(f"{fname}(): the number of coefficients must be a multiple of 4, "
                   f"got {coef.size}")
    rows = coef.reshape(-1, 4) if form == "s" else coef.reshape(-1, 4)[:, [2, 3, 0, 1]]
    zeros = np.concatenate([np.roots([1.0, b1, b2]) for b1, b2, _, _ in rows])
    poles = np.concatenate([np.roots([1.0, a1, a2]) for _, _, a1, a2 in rows])
    return _from_z(fname, zeros.astype(complex), poles.astype(complex), gain, fail)


def _f_biquad(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    """biquad(b0, b1, b2, a1, a2): ``(b0 + b1/z + b2/z^2)/(1 + a1/z + a2/z^2)``."""
    _arity(fname, args, 5, 5, fail)
    b0, b1, b2, a1, a2 = (_real(fname, args, k, what, fail)
                          for k, what in enumerate(("b0", "b1", "b2", "a1", "a2")))
    zeros, k = _polynomial(fname, np.array([b0, b1, b2]), "numerator", fail)
    poles, _ = _polynomial(fname, np.array([1.0, a1, a2]), "denominator", fail)
    return _from_z(fname, zeros, poles, k, fail)


def _f_direct(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    """direct([b0;b1;...], [a1;a2;...]): ``(b0 + b1/z + ...)/(1 - a1/z - a2/z^2 - ...)``."""
    _arity(fname, args, 2, 2, fail)
    b = _vector_arg(fname, args, 0, "numerator", fail).real
    a = _vector_arg(fname, args, 1, "denominator", fail).real
    zeros, k = _polynomial(fname, b, "numerator", fail)
    poles, _ = _polynomial(fname, np.concatenate([[1.0], -a]), "denominator", fail)
    return _from_z(fname, zeros, poles, k, fail)


def _f_zroots(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    """zroots(zeros, poles[, gain]): ``gain prod(z - zeros)/prod(z - poles)``."""
    _arity(fname, args, 2, 3, fail)
    zeros = _paired(_vector_arg(fname, args, 0, "zeros", fail), fname, "zero", fail)
    poles = _paired(_vector_arg(fname, args, 1, "poles", fail), fname, "pole", fail)
    gain = _real(fname, args, 2, "gain", fail) if len(args) == 3 else 1.0
    return _from_z(fname, zeros, poles, gain, fail)


def _f_comb(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    """comb(f, Q[, amplitude[, N]]): at f and its harmonics up to the N-th (all below the
    Nyquist frequency for N = 0), a resgain of `amplitude` dB when it is positive, a notch
    of its depth when negative, an infinitely deep notch when 0."""
    _arity(fname, args, 2, 4, fail)
    f = _positive(fname, args, 0, "frequency", fail)
    q = _positive(fname, args, 1, "Q", fail)
    amp = _real(fname, args, 2, "amplitude", fail) if len(args) > 2 else 0.0
    n = int(_real(fname, args, 3, "harmonics", fail)) if len(args) > 3 else 0
    if n <= 0:
        n = math.ceil(_rate(fname, fail) / 2 / f) - 1
    if n < 1:
        raise fail(f"{fname}(): {f!r} Hz is not below the Nyquist frequency")
    single = "resgain" if amp > 0 else "notch"
    out = ZPK.unity()
    for k in range(1, n + 1):
        out = out * _f_notch(single, [k * f, q, abs(amp)], fail)
    return out


_FUNCTIONS: dict[str, FotonFunction] = {
    "zpk": _f_zpk,
    "rpoly": _f_rpoly,
    "gain": _f_gain,
    "pole": _f_pole,
    "zero": _f_pole,
    "pole2": _f_pole2,
    "zero2": _f_pole2,
    "notch": _f_notch,
    "resgain": _f_notch,
    "butter": _f_iir,
    "cheby1": _f_iir,
    "cheby2": _f_iir,
    "ellip": _f_iir,
    "sos": _f_sos,
    "biquad": _f_biquad,
    "direct": _f_direct,
    "zroots": _f_zroots,
    "comb": _f_comb,
}


# ============================================================================================
# Public API
# ============================================================================================
def parse_design(design: str, rate_hz: float | None = None) -> ZPK:
    """Parse a whole foton design string into one continuous zpk.

    Parameters
    ----------
    design : str
        E.g. ``'zpk([1],[10],1,"n")gain(3)'``; factors multiply.  An empty string is unity.
    rate_hz : float, optional
        The sample rate the design runs at.  With it, the result is the continuous filter
        whose discretization (:func:`zpk_to_sos`) is the filter foton makes at that rate:
        its IIR designs are digital, and functions with more zeros than poles get poles
        at twice the rate.  Without it, the design as written in continuous time.

    Returns
    -------
    ZPK
        The product of all factors, s-plane roots in rad/s.

    Raises
    ------
    FotonError
        For anything foton would not accept; the message quotes `design`.
    """
    if not isinstance(design, str):
        msg = f"a foton design must be a string, got {type(design).__name__}"
        raise FotonError(msg)
    if rate_hz is not None:
        _check_rate(rate_hz)
        rate_hz = float(rate_hz)
    return _parsed(design, rate_hz)


@lru_cache(maxsize=4096)
def _parsed(design: str, rate_hz: float | None) -> ZPK:
    """A design parsed once (a ZPK is immutable): a fit evaluates the damping loop's filter
    responses thousands of times, and parsing was most of the fit's time."""
    return _Parser(design, rate_hz).parse()


def _check_rate(rate_hz: object) -> None:
    if not (isinstance(rate_hz, numbers.Real) and math.isfinite(rate_hz) and rate_hz > 0):
        msg = f"sample rate must be a positive number of Hz, got {rate_hz!r}"
        raise FotonError(msg)


def _prewarp(roots: ComplexArray, rate_hz: float) -> ComplexArray:
    """Move each root radially so its frequency survives the bilinear transform, as foton
    does: ``|r| -> 2 fs tan(|r| / 2 fs)``; a root above the Nyquist frequency folds."""
    out = roots.copy()
    mag = np.abs(roots)
    nz = mag > 0
    out[nz] *= 2.0 * rate_hz * np.tan(mag[nz] / (2.0 * rate_hz)) / mag[nz]
    return out


def _log_product(values: ComplexArray) -> tuple[float, float]:
    """``log |prod(values)|`` and the sign of the product (real: conjugates come in pairs),
    without the overflow of a product over a comb's hundreds of roots."""
    if values.size == 0:
        return 0.0, 1.0
    mag = np.abs(values)
    phase = np.prod(np.where(mag > 0, values / np.where(mag > 0, mag, 1.0), 1.0))
    return float(np.sum(np.log(mag))), float(np.sign(phase.real) or 1.0)


def _bilinear_factors(roots: ComplexArray, rate_hz: float) -> tuple[
        ComplexArray, tuple[float, float]]:
    """z-plane roots and the gain of prod(1 - s/r) (s for r = 0) under
    s -> 2fs(z-1)/(z+1), as :func:`_log_product` gives it.

    Each factor becomes ``g (z - zr)/(z + 1)``; the ``(z + 1)`` are left to the caller.
    """
    c = 2.0 * rate_hz
    warped = _prewarp(roots, rate_hz)
    origin = warped == 0
    nonzero = warped[~origin]
    if np.any(np.abs(c - nonzero) <= 1e-12 * c):
        msg = (f"a root maps to s = 2*fs = {c} rad/s, which the bilinear transform sends "
               "to infinity")
        raise FotonError(msg)
    zr = np.concatenate([(c + nonzero) / (c - nonzero), np.ones(int(origin.sum()))])
    log_gain, sign = _log_product(1.0 - c / nonzero)
    return zr.astype(complex), (log_gain + int(origin.sum()) * math.log(c), sign)


def zpk_to_sos(zpk: ZPK, rate_hz: float) -> NDArray[np.float64]:
    """Discretize a continuous zpk the way foton does (bilinear, per-root prewarp).

    Parameters
    ----------
    zpk : ZPK
        Continuous filter; right-half-plane roots are allowed (the result is then unstable).
    rate_hz : float
        Sample rate, e.g. 16384.

    Returns
    -------
    ndarray, shape (n_sections, 6)
        Second-order sections ``[b0 b1 b2 1 a1 a2]`` (scipy layout), overall gain folded in.

    Raises
    ------
    FotonError
        If the rate is not a positive number, the filter has more zeros than poles, or a
        root lands on the singularity of the bilinear map.
    """
    _check_rate(rate_hz)
    n_excess = zpk.zeros.size - zpk.poles.size
    if n_excess > 0:
        msg = (f"filter has {zpk.zeros.size} zeros but only {zpk.poles.size} poles; the "
               "bilinear transform would put poles at the Nyquist frequency")
        raise FotonError(msg)
    with np.errstate(all="ignore"):
        # k prod(s - r) = k prod(-r) prod(1 - s/r) s^m: the per-factor form keeps DC exact.
        (lz, sz), (lp, sp) = (_log_product(-r[r != 0]) for r in (zpk.zeros, zpk.poles))
        zd, (lgz, sgz) = _bilinear_factors(zpk.zeros, rate_hz)
        pd, (lgp, sgp) = _bilinear_factors(zpk.poles, rate_hz)
        # a root that prewarping folds past infinity keeps the sign of its factor at DC
        folded = sum(int(np.sum(np.abs(r) > math.pi * rate_hz)) for r in (zpk.zeros, zpk.poles))
        kd = (zpk.gain * sz * sp * sgz * sgp * (-1.0) ** folded
              * math.exp(lz - lp + lgz - lgp))
    if not (math.isfinite(kd) and np.all(np.isfinite(zd)) and np.all(np.isfinite(pd))):
        msg = "the discrete roots or gain are not finite numbers"
        raise FotonError(msg)
    # The (z+1) denominators of the zero factors cancel those of the pole factors;
    # what is left over becomes zeros at Nyquist.
    zd = np.concatenate([zd, -np.ones(-n_excess)])
    if zd.size == 0 and pd.size == 0:
        return np.array([[kd, 0.0, 0.0, 1.0, 0.0, 0.0]])
    try:
        sos = signal.zpk2sos(zd, pd, kd)
    except ValueError as exc:
        msg = f"cannot form second-order sections ({exc})"
        raise FotonError(msg) from None
    return np.asarray(sos, dtype=float)


def n_plane_design(zeros: ArrayLike, poles: ArrayLike, gain: float = 1.0) -> str:
    """A foton design ``zpk([...],[...],gain,"n")`` of continuous roots.

    Parameters
    ----------
    zeros, poles : array_like of complex
        s-plane roots in rad/s (complex ones in conjugate pairs); poles stable.
    gain : float
        The DC gain (of roots off the origin).

    Returns
    -------
    str
        Roots in Hz with foton's "n" sign (stable: positive real part), 10 digits.
    """
    def written(roots: ArrayLike) -> str:
        hz = -np.asarray(roots, dtype=complex) / TWO_PI
        hz = hz[np.argsort(np.abs(hz), kind="stable")]
        out = []
        for r in hz:
            if abs(r.imag) <= 1e-12 * abs(r):
                out.append(f"{r.real:.10g}")
            elif r.imag > 0:
                out += [f"{r.real:.10g}+i*{r.imag:.10g}", f"{r.real:.10g}-i*{r.imag:.10g}"]
        return ";".join(out)

    return f'zpk([{written(zeros)}],[{written(poles)}],{gain:.10g},"n")'


def implementation() -> str:
    """Which foton turns design strings into sections, from the environment variable
    ``TWIND_FOTON`` (``twind --foton``): ``"twind"``, this module, by default, or
    ``"python-foton"``, LIGO's own foton from the optional extra ``twind[foton]``.

    Returns
    -------
    str
        One of :data:`twind.loop.FOTON_READERS`.

    Raises
    ------
    FotonError
        If the variable names neither.
    """
    name = os.environ.get(FOTON_VARIABLE, "twind")
    if name not in FOTON_READERS:
        msg = (f"{FOTON_VARIABLE}={name!r}: the foton reader must be one of "
               f"{', '.join(FOTON_READERS)}")
        raise FotonError(msg)
    return name


def _ligo_sections(design: str, rate_hz: float) -> NDArray[np.float64]:
    """Sections from LIGO's foton (python-foton), as the front end would run them."""
    try:
        import foton  # the optional GPL extra, imported only when a user asks for it
    except ImportError:
        msg = ("TWIND_FOTON=python-foton, but python-foton is not installed: "
               "pip install 'twind[foton]' (Linux x86-64, Python 3.11-3.13)")
        raise FotonError(msg) from None
    _check_rate(rate_hz)
    ligo = foton.FilterDesign("", rate=float(rate_hz))
    if not ligo.filt.filter(design):
        msg = f"python-foton refuses design {design!r} (its reason is printed above)"
        raise FotonError(msg)
    return np.array(ligo.get_sos(), dtype=float)


def design_to_sos(design: str, rate_hz: float,
                  reader: str | None = None) -> NDArray[np.float64]:
    """Parse a foton design string and discretize it.

    Parameters
    ----------
    design : str
        Foton design string.
    rate_hz : float
        Sample rate of the CDS model, e.g. 16384.
    reader : {"twind", "python-foton"}, optional
        Whose foton reads it; :func:`implementation` by default.

    Returns
    -------
    ndarray, shape (n_sections, 6)
        See :func:`zpk_to_sos`.

    Raises
    ------
    FotonError
        From :func:`parse_design` or :func:`zpk_to_sos`; the design string is quoted.
    """
    if (reader or implementation()) == "python-foton":
        return _ligo_sections(design, rate_hz)
    zpk = parse_design(design, rate_hz)
    try:
        return zpk_to_sos(zpk, rate_hz)
    except FotonError as exc:
        msg = f"{exc} in design {design!r}"
        raise FotonError(msg) from None
