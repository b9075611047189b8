"""The continuous zero-pole-gain filter (:class:`ZPK`) and the root arithmetic under it:
foton's normalisations of roots written in a plane, quality-factor pairs, and the radial
prewarp of the bilinear transform and its inverse."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

TWO_PI = 2.0 * math.pi

ComplexArray = NDArray[np.complex128]


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
# Roots: foton's normalisations, the prewarp
# ============================================================================================
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


def _prewarp(roots: ComplexArray, rate_hz: float) -> ComplexArray:
    """Move each root radially so its frequency survives the bilinear transform, as foton
    does: ``|r| -> 2 fs tan(|r| / 2 fs)``; a root above the Nyquist frequency folds."""
    out = roots.copy()
    mag = np.abs(roots)
    nz = mag > 0
    out[nz] *= 2.0 * rate_hz * np.tan(mag[nz] / (2.0 * rate_hz)) / mag[nz]
    return out


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
