"""Reading a foton design string: the tokenizer, the recursive-descent parser
(``design := { NAME '(' args ')' [ '*' ] }``) and :func:`parse_design`, with its cache;
:func:`n_plane_design` writes roots back as a design string."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike

from twind.errors import FotonError
from twind.loop.foton.arguments import Arg, _check_rate, _Failer
from twind.loop.foton.functions import _FUNCTIONS
from twind.loop.foton.zpk import TWO_PI, ZPK


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
