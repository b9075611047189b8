"""Foton filter *design strings*: parse them into continuous zpk, discretize them for the CDS.

A foton design string is what a commissioner types into foton (and what a filter file keeps
on its ``# DESIGN`` lines), e.g. ``zpk([0],[30],6.283185307179586,"n")`` or
``zpk([1],[10],1,"n")gain(3)``.  Factors written one after the other (optionally joined by
``*``) multiply.  Whitespace, newlines, backslash line continuations and ``%`` comments
(which IIRrational writes inside ``zpk`` vectors) are ignored.

Conventions, and where they come from
-------------------------------------
The foton C++ sources (gds ``iirutil``/``FilterDesign``) are not in the public stores
searched, so the conventions below are pinned down from public code that talks to foton:

* [K] KAGRA ``kontrol`` (github.com/terrencetec/kontrol, ``kontrol/core/foton.py``:
  ``tf2zpk``/``tf2foton``/``zpk2tf``).
* [W] LIGO ``foton.py`` python bindings by C. Wipf (``ZPK_add``, ``gain_add``,
  ``butter_add`` ..., ``iir2zpk(filt, plane, prewarp=True)``), as kept in IIRrational.
* [M] IIRrational (L. McCuller) ``conversion.filter2fotonZPK`` and ``ZPKTF.xfer_eval``.
* [V] a public MATLAB script translating ``# DESIGN`` lines of aLIGO DAQ filters:
  ``zpk([...],[...],1,"n")`` -> ``zpk(-2*pi*[...], -2*pi*[...], 1)`` normalised by its DC
  response, and ``ellip("LowPass",5,1,60,128)`` -> ``ellip(5,1,60,2*pi*128,'s')``.
* [G] gwpy ``signal.filter_design.bilinear_zpk``: analog roots given in Hz map to
  ``s = -2*pi*f``.

``zpk(zeros, poles, gain[, plane])``, plane default ``"s"`` ([K] ``zpk2tf``):

* ``"s"``: roots in rad/s exactly as written (a stable pole has a negative real part);
  ``H(s) = gain * prod(s - z) / prod(s - p)``.
* ``"f"``: roots in Hz, *same sign* as the s-plane, ``s_root = 2*pi*root`` ([K] ``tf2zpk``,
  [M]; [K] ``zpk2tf`` negates them, contradicting its own ``tf2zpk``); the gain keeps its
  s-plane meaning, ``H(s) = gain * prod(s - 2 pi z)/prod(s - 2 pi p)`` ([M] scales the gain
  by ``(2 pi)**(n_z - n_p)`` from its Hz-root form; [W] ``ZPK_add`` does the same).
* ``"n"``: roots in Hz with the sign *flipped*, so stable roots have a positive real part,
  ``s_root = -2*pi*root`` ([K], [M], [V], [G]); the gain is the DC gain: every non-zero root
  contributes ``(1 - s/s_root)`` and a root at the origin contributes ``s/(2*pi)`` (unity
  at 1 Hz) ([K] ``tf2zpk``/``zpk2tf``, [M] ``root_gain``).  A lone real right-half-plane root
  is normalised by its signed value, so the DC gain is exactly ``gain`` (choice; [K] and [M]
  differ on it).

Complex roots are written ``a+i*b``, ``a-i*b`` ([V], [K]), ``a + b*i`` ([M]); ``bi``, ``b*j``
are accepted too.  They must come in conjugate pairs (the filter has real coefficients).
Vector elements are separated by ``;`` (also ``,``).

Other functions ([W] for the argument lists):

* ``gain(g[, "scalar"|"dB"])`` ([W] ``gain_add`` writes ``"db"``/``"scalar"``).
* ``notch(f, Q, depth_dB)``: ``(s^2 + a w/Q s + w^2)/(s^2 + w/Q s + w^2)``,
  ``a = 10**(-|depth|/20)``, so the response at ``f`` is exactly ``-|depth|`` dB.
* ``resgain(f, Q, height_dB)``: ``(s^2 + g w/Q s + w^2)/(s^2 + w/Q s + w^2)``,
  ``g = 10**(height/20)``, response at ``f`` exactly ``height`` dB, unity at DC and
  high frequency.  (That the poles carry the written ``Q`` is an assumption.)
* ``butter(type, order, f1[, f2])``, ``cheby1(type, order, ripple_dB, f1[, f2])``,
  ``cheby2(type, order, atten_dB, f1[, f2])``, ``ellip(type, order, ripple_dB, atten_dB,
  f1[, f2])`` with type ``"LowPass"``, ``"HighPass"``, ``"BandPass"``, ``"BandStop"``: the
  analog (s-plane) prototypes of MATLAB/scipy (``analog=True``) with the edges ``2*pi*f``
  ([V]); band types need ``f2 > f1``.  Orders 1..20.
* ``pole(f, gain)``, ``zero(f, gain)``, ``pole2(f, Q, gain)``, ``zero2(f, Q, gain)``: the
  ``"n"``-plane real root at ``f`` / root pair at ``f`` with quality ``Q``, DC gain ``gain``
  (an optional 4th/3rd argument may only be ``"n"``).
* ``rpoly(num, den, gain)``: ``gain * num(s)/den(s)``, coefficients in descending powers of
  ``s`` in rad/s ([W] ``iir2poly`` doc, [K] ``rpoly2tf``).

z-plane designs (``sos``, ``zroots``, ``direct``) have no continuous zpk and are refused;
``poly`` and foton's other functions are not implemented (unknown-function error).

Discretization
--------------
foton converts s-plane designs with the bilinear transform and prewarps the roots by
default ([W]: ``iir2zpk(..., prewarp=True)``; ``iir2poly(..., unwarp=True)`` undoes the
warping on the way back).  The exact formula is not in the public sources; we use per-root
prewarping: every s-plane root ``r`` below the Nyquist frequency is moved radially to
``|r'| = 2 fs tan(|r| / (2 fs))`` (angle, hence Q, kept), then ``s -> 2 fs (z-1)/(z+1)``.
Each root's factor is normalised at DC so the DC gain is exact; roots at the origin map to
``z = 1``.  For a Butterworth low-pass this is exactly the textbook prewarped design
(``scipy.signal.butter(..., fs=fs)``).  Roots at or above Nyquist are mapped without
prewarping.  More zeros than poles is refused (the bilinear transform would put poles on the
unit circle at Nyquist).

What the bilinear transform cannot keep is the high-frequency asymptote: each pole in excess
of the zeros makes the discrete response differ by ``tan(x)/x - 1 ~ x^2/3``, ``x = pi f/fs``
(1.2e-4 at 100 Hz for 16384 Hz); the nominal FM2 (8 poles) is therefore 1e-3 off at 100 Hz,
as any bilinear CDS implementation of it is.
"""

from __future__ import annotations

import math
import numbers
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

__all__ = [
    "NOMINAL_FM1",
    "NOMINAL_FM2",
    "NOMINAL_FM3",
    "ZPK",
    "design_to_sos",
    "parse_design",
    "zpk_to_sos",
]

TWO_PI = 2.0 * math.pi
MAX_ORDER = 20  # foton's own limit for a single design (10 second-order sections)

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
        num = np.prod(s - self.zeros[None, :], axis=1)
        den = np.prod(s - self.poles[None, :], axis=1)
        return (self.gain * num / den).reshape(f.shape)

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
    """Builds FotonErrors that always name the design string."""

    def __init__(self, design: str) -> None:
        self.design = design

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
    def __init__(self, design: str) -> None:
        self.fail = _Failer(design)
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
            if name.text in _DIGITAL_FUNCTIONS:
                raise self.fail(f"{name.text}() is a z-plane (digital) design and has no "
                                "continuous zpk")
            raise self.fail(f"unknown foton function {name.text!r}")
        with np.errstate(all="ignore"):
            factor = func(name.text, args, self.fail)
        if not factor.is_finite():
            raise self.fail(f"{name.text}(): numbers out of range give a non-finite filter")
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
                num = self._expect("num", "a number after 'i*'")
                return 1j * float(num.text)
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
                   f"more than foton's {2 * MAX_ORDER}")
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
# Plane conversions
# ============================================================================================
_PLANES = ("s", "f", "n")


def _zpk_from_plane(zeros: ComplexArray, poles: ComplexArray, gain: float,
                    plane: str) -> ZPK:
    """Convert roots and gain written in foton plane `plane` to an s-plane ZPK."""
    if plane == "s":
        return ZPK(zeros, poles, gain)
    if plane == "f":
        return ZPK(TWO_PI * zeros, TWO_PI * poles, gain)
    z_s, p_s = -TWO_PI * zeros, -TWO_PI * poles
    return ZPK(z_s, p_s, gain * _dc_norm(p_s) / _dc_norm(z_s))


def _dc_norm(roots: ComplexArray, origin: float = TWO_PI) -> float:
    """Product turning prod(s - r) into prod(1 - s/r), with s/origin for the roots at 0.

    foton's "n" plane writes a root at the origin as s/(2 pi), unity at 1 Hz.
    """
    nonzero = roots[roots != 0]
    n_origin = roots.size - nonzero.size
    return float(np.real(np.prod(-nonzero))) * origin**n_origin


def _pair_hz(f_hz: float, q: float) -> ComplexArray:
    """s-plane roots of s^2 + (w/Q) s + w^2 with w = 2 pi f."""
    w = TWO_PI * f_hz
    disc = 1.0 - 1.0 / (4.0 * q * q)
    if disc >= 0:
        im = w * math.sqrt(disc)
        return np.array([complex(-w / (2 * q), im), complex(-w / (2 * q), -im)])
    re_ = w * math.sqrt(-disc)
    return np.array([complex(-w / (2 * q) + re_), complex(-w / (2 * q) - re_)])


def _dc_unity(zeros: ComplexArray, poles: ComplexArray, dc_gain: float) -> ZPK:
    """s-plane ZPK with non-zero roots and the given DC gain."""
    return ZPK(zeros, poles, dc_gain * _dc_norm(poles) / _dc_norm(zeros))


# ============================================================================================
# foton functions
# ============================================================================================
FotonFunction = Callable[[str, Sequence[Arg], _Failer], ZPK]


def _f_zpk(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    _arity(fname, args, 3, 4, fail)
    zeros = _paired(_vector_arg(fname, args, 0, "zeros", fail), fname, "zero", fail)
    poles = _paired(_vector_arg(fname, args, 1, "poles", fail), fname, "pole", fail)
    gain = _real(fname, args, 2, "gain", fail)
    plane = _string(fname, args, 3, "plane", fail) if len(args) == 4 else "s"
    if plane not in _PLANES:
        raise fail(f'{fname}(): plane must be one of "s", "f", "n", got "{plane}"')
    return _zpk_from_plane(zeros, poles, gain, plane)


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
    return ZPK(zeros, poles, gain * num[0] / den[0])


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
    return ZPK(np.empty(0, complex), np.empty(0, complex), g)


def _only_n_plane(fname: str, args: Sequence[Arg], n_base: int, fail: _Failer) -> None:
    _arity(fname, args, n_base, n_base + 1, fail)
    if len(args) > n_base:
        plane = _string(fname, args, n_base, "plane", fail)
        if plane != "n":
            raise fail(f'{fname}(): only the normalised plane "n" is supported, got "{plane}"')


def _f_pole(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    _only_n_plane(fname, args, 2, fail)
    f = _positive(fname, args, 0, "frequency", fail)
    root = np.array([-TWO_PI * f + 0j])
    gain = _real(fname, args, 1, "gain", fail)
    none = np.empty(0, complex)
    return _dc_unity(none, root, gain) if fname == "pole" else _dc_unity(root, none, gain)


def _f_pole2(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    _only_n_plane(fname, args, 3, fail)
    pair = _pair_hz(_positive(fname, args, 0, "frequency", fail),
                    _positive(fname, args, 1, "Q", fail))
    gain = _real(fname, args, 2, "gain", fail)
    none = np.empty(0, complex)
    return _dc_unity(none, pair, gain) if fname == "pole2" else _dc_unity(pair, none, gain)


def _f_notch(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
    _arity(fname, args, 3, 3, fail)
    f = _positive(fname, args, 0, "frequency", fail)
    q = _positive(fname, args, 1, "Q", fail)
    level = _real(fname, args, 2, "depth" if fname == "notch" else "height", fail)
    # Zero damping = pole damping * ratio, so |H(i w0)| = ratio exactly.
    ratio = 10.0 ** (-abs(level) / 20.0) if fname == "notch" else 10.0 ** (level / 20.0)
    if not (math.isfinite(ratio) and ratio > 0):
        raise fail(f"{fname}(): {level!r} dB is out of range")
    poles = _pair_hz(f, q)
    zeros = _pair_hz(f, q / ratio)
    return _dc_unity(zeros, poles, 1.0)


_BAND_TYPES = {"lowpass": "lowpass", "highpass": "highpass",
               "bandpass": "bandpass", "bandstop": "bandstop"}


def _band_edges(fname: str, args: Sequence[Arg], k: int, btype: str,
                fail: _Failer) -> float | list[float]:
    needs_two = btype in ("bandpass", "bandstop")
    if len(args) != k + 1 + needs_two:
        want = "f1 and f2" if needs_two else "only f1"
        raise fail(f"{fname}(): a {btype} design takes {want} after its other arguments, "
                   f"got {len(args)} arguments in all")
    f1 = _positive(fname, args, k, "f1", fail)
    if not needs_two:
        return TWO_PI * f1
    f2 = _positive(fname, args, k + 1, "f2", fail)
    if f2 <= f1:
        raise fail(f"{fname}(): f2 must be above f1, got f1={f1!r}, f2={f2!r}")
    return [TWO_PI * f1, TWO_PI * f2]


def _f_iir(fname: str, args: Sequence[Arg], fail: _Failer) -> ZPK:
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
    wn = _band_edges(fname, args, 2 + n_spec, btype, fail)
    design = {"butter": signal.butter, "cheby1": signal.cheby1,
              "cheby2": signal.cheby2, "ellip": signal.ellip}[fname]
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            z, p, k = design(order, *spec, wn, btype=btype, analog=True, output="zpk")
    except (ValueError, ArithmeticError) as exc:
        raise fail(f"{fname}(): cannot design this filter ({exc})") from None
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(p)) and np.isfinite(k)):
        raise fail(f"{fname}(): the design has non-finite roots or gain")
    return ZPK(z, p, float(np.real(k)))


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
}
_DIGITAL_FUNCTIONS = ("sos", "zroots", "direct")


# ============================================================================================
# Public API
# ============================================================================================
def parse_design(design: str) -> ZPK:
    """Parse a whole foton design string into one continuous zpk.

    Parameters
    ----------
    design : str
        E.g. ``'zpk([1],[10],1,"n")gain(3)'``; factors multiply.  An empty string is unity.

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
    return _parsed(design)


@lru_cache(maxsize=4096)
def _parsed(design: str) -> ZPK:
    """A design parsed once (a ZPK is immutable): a fit evaluates the damping loop's filter
    responses thousands of times, and parsing was most of the fit's time."""
    return _Parser(design).parse()


def _prewarp(roots: ComplexArray, rate_hz: float) -> ComplexArray:
    """Move each root radially so its frequency survives the bilinear transform."""
    out = roots.copy()
    mag = np.abs(roots)
    below = (mag > 0) & (mag < math.pi * rate_hz)
    out[below] *= 2.0 * rate_hz * np.tan(mag[below] / (2.0 * rate_hz)) / mag[below]
    return out


def _bilinear_factors(roots: ComplexArray, rate_hz: float) -> tuple[ComplexArray, float]:
    """z-plane roots and gain of prod(1 - s/r) (s for r = 0) under s -> 2fs(z-1)/(z+1).

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
    gain = np.prod(1.0 - c / nonzero) * c ** int(origin.sum())
    return zr.astype(complex), float(np.real(gain))


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
    if not (isinstance(rate_hz, numbers.Real) and math.isfinite(rate_hz) and rate_hz > 0):
        msg = f"sample rate must be a positive number of Hz, got {rate_hz!r}"
        raise FotonError(msg)
    n_excess = zpk.zeros.size - zpk.poles.size
    if n_excess > 0:
        msg = (f"filter has {zpk.zeros.size} zeros but only {zpk.poles.size} poles; the "
               "bilinear transform would put poles at the Nyquist frequency")
        raise FotonError(msg)
    with np.errstate(all="ignore"):
        # k prod(s - r) = k prod(-r) prod(1 - s/r) s^m: the per-factor form keeps DC exact.
        dc_gain = zpk.gain * _dc_norm(zpk.zeros, origin=1.0) / _dc_norm(zpk.poles, origin=1.0)
        zd, gz = _bilinear_factors(zpk.zeros, rate_hz)
        pd, gp = _bilinear_factors(zpk.poles, rate_hz)
        kd = dc_gain * gz / gp
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


def design_to_sos(design: str, rate_hz: float) -> NDArray[np.float64]:
    """Parse a foton design string and discretize it.

    Parameters
    ----------
    design : str
        Foton design string.
    rate_hz : float
        Sample rate of the CDS model, e.g. 16384.

    Returns
    -------
    ndarray, shape (n_sections, 6)
        See :func:`zpk_to_sos`.

    Raises
    ------
    FotonError
        From :func:`parse_design` or :func:`zpk_to_sos`; the design string is quoted.
    """
    zpk = parse_design(design)
    try:
        return zpk_to_sos(zpk, rate_hz)
    except FotonError as exc:
        msg = f"{exc} in design {design!r}"
        raise FotonError(msg) from None
