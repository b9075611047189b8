"""From a design to the CDS's second-order sections: the bilinear transform with foton's
per-root prewarp (:func:`zpk_to_sos`), and :func:`design_to_sos` by twind's reader or,
when :func:`implementation` says so, by LIGO's python-foton."""

from __future__ import annotations

import math
import os

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind.errors import FotonError
from twind.loop import FOTON_READERS, FOTON_VARIABLE
from twind.loop.foton.arguments import _check_rate
from twind.loop.foton.parser import parse_design
from twind.loop.foton.zpk import ZPK, ComplexArray, _prewarp


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
