"""The foton functions (``zpk``, ``pole``, ``notch``, ``butter``, ``sos``, ``comb``, ...):
each turns its arguments into a continuous :class:`~twind.loop.foton.zpk.ZPK`, with the
poles foton adds and the stability it demands; :data:`_FUNCTIONS` names them for the
parser."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind.loop.foton.arguments import (
    Arg,
    _arity,
    _Failer,
    _fmt,
    _order,
    _paired,
    _positive,
    _real,
    _string,
    _vector_arg,
)
from twind.loop.foton.zpk import (
    TWO_PI,
    ZPK,
    ComplexArray,
    _normalised,
    _pair,
    _unwarped,
    _zpk_from_plane,
)

# ============================================================================================
# Planes and foton's additions
# ============================================================================================
_PLANES = ("s", "f", "n")
_NONE = np.empty(0, complex)


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
