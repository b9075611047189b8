"""Pintelon and Schoukens' local polynomial method (LPM): transfer functions of a record
excited by arbitrary noise, with the leakage removed and the noise level taken from the data.

Over ``2 n + 1`` neighbouring bins of the whole record's DFT,

    Y(k + r) = G(k + r) U(k + r) + T(k + r) + V(k + r),   r = -n .. n,

``G`` and the transient ``T`` are polynomials of degree ``R`` in ``r``. ``T`` is what a
Welch estimate calls leakage: the record's start and end conditions, of the system and of
the noise's own filter alike. It is smooth in frequency (it has the system's poles), and a
Welch estimate leaves it in every segment, correlated over the width of a resonance.
Here it is fitted and removed, so the residual ``V`` is the noise, independent from bin to
bin. The residuals' power gives the noise variance with ``q = 2 n + 1 - 2 (R + 1)`` degrees
of freedom, smoothed over neighbouring windows, and so the standard error of ``G`` without
Bendat-Piersol's approximations.

The windows do not overlap, so the estimates at their centres are independent. They must be
narrower than the resonances, or G's curvature over a window is counted as noise: 15 bins
of ``1 / T`` against the 40m damping loops' ~0.14 Hz wide resonances want records of 5
minutes or more (a 110 s record's windows, 0.14 Hz, overstate the errors at the resonances
several times over).

Source: R. Pintelon, J. Schoukens, G. Vandersteen, K. Barbe, "Estimation of nonparametric
noise and FRF models for multivariable systems, Part I: Theory", Mech. Syst. Signal Process.
24 (2010) 573-595, eqs. (10)-(20).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import fft, signal, special, stats

from twind.errors import TwindError

HALF_WIDTH = 7
"""``n``: windows of 15 bins of the whole record."""
ORDER = 2
"""``R``: G and T quadratic over a window (Pintelon's usual choice); q = 9."""
SMOOTH_WINDOWS = 7
"""Windows over which the noise variance is smoothed (:func:`_smoothed_variance`)."""
GUARD = 0.01
"""Level of the test that a window holds more noise than the smoothed spectrum gives it
(:func:`_smoothed_variance`)."""
CHUNK = 20000
"""Windows solved at once."""


class LPMError(TwindError):
    """A record the local polynomial method cannot estimate from."""


@dataclass(frozen=True)
class LPMEstimate:
    """Transfer functions of several responses to one excitation, one per window.

    Attributes
    ----------
    frequency_hz : ndarray, shape (nw,)
        Centre of each window.
    tf, sigma : ndarray, shape (n_responses, nw)
        ``G`` at the centre and its standard error (of the real and of the imaginary part,
        each ``|dG| / sqrt(2)`` on average, as Bendat-Piersol's is).
    coherence : ndarray, shape (n_responses, nw)
        Power the excitation explains over the window's total, as a Welch coherence is.
    dof : int
        Degrees of freedom of each noise variance: ``q`` of its window, about three times
        that after smoothing.
    offsets_hz : ndarray, shape (2 n + 1,)
        Of the window's bins from its centre.
    weights : ndarray of complex, shape (nw, 2 n + 1)
        The estimate is linear in the true response: ``tf = sum_r weights[:, r]
        G(frequency_hz + offsets_hz[r])`` without noise. A G that is a polynomial of
        degree R over the window comes out exact; the curvature of a resonance beyond that
        comes out as this sum, which a model can then predict exactly.
    correlation : ndarray of complex, shape (nw, m, m), optional
        Correlation of the errors of the `correlated` responses' estimates (their noises'
        in the window, smoothed over windows by :func:`_correlation`). The readbacks of
        one optic share their noise: around the 40m's POS resonance POS and PIT IN1
        correlate at 0.99, and a fit that took them as independent would count that noise
        twice.
    """

    frequency_hz: NDArray[np.float64]
    tf: NDArray[np.complex128]
    sigma: NDArray[np.float64]
    coherence: NDArray[np.float64]
    dof: int
    offsets_hz: NDArray[np.float64]
    weights: NDArray[np.complex128]
    correlation: NDArray[np.complex128] | None = None

    @property
    def averages(self) -> int:
        """The Welch averages whose errors are as uncertain: ``|error / sigma|^2 / 2`` is
        F(2, 2 q) here, F(2, 2 n - 2) for ``n`` Bendat-Piersol averages."""
        return self.dof + 1


def lpm(U: NDArray[np.complex128], Y: NDArray[np.complex128], df: float,
        half_width: int = HALF_WIDTH, order: int = ORDER,
        correlated: Sequence[int] = ()) -> LPMEstimate:
    """Local polynomial estimates from DFT bins ``0, df, 2 df, ...`` of one record.

    Parameters
    ----------
    U : ndarray of complex, shape (nk,)
        The excitation's DFT.
    Y : ndarray of complex, shape (n_responses, nk)
        The responses' DFTs, scaled as `U`.
    df : float
        Bin spacing (Hz): 1 / record length.
    half_width, order : int
        ``n`` and ``R``.
    correlated : sequence of int
        Responses whose errors' correlation is estimated (:attr:`LPMEstimate.correlation`).

    Returns
    -------
    LPMEstimate

    Raises
    ------
    LPMError
        If a window leaves no degree of freedom for the noise, or `Y` does not match `U`.
    """
    U = np.asarray(U, dtype=np.complex128)
    Y = np.atleast_2d(np.asarray(Y, dtype=np.complex128))
    width, p = 2 * half_width + 1, 2 * (order + 1)
    if width <= p:
        msg = (f"windows of {width} bins hold no degree of freedom for the noise beside "
               f"{p} polynomial coefficients (order {order}): widen them")
        raise LPMError(msg)
    if Y.shape[-1] != U.size:
        msg = f"responses of {Y.shape[-1]} bins for an excitation of {U.size}"
        raise LPMError(msg)
    n_win = (U.size - 1) // width  # from bin 1: DC is the mean, removed by any detrend
    if n_win < 1:
        msg = f"{U.size} bins hold no window of {width}"
        raise LPMError(msg)
    r = (np.arange(width) - half_width) / half_width  # scaled: a well-conditioned basis
    poly = r[:, None] ** np.arange(order + 1)  # (width, R + 1)
    G = np.empty((Y.shape[0], n_win), dtype=np.complex128)
    var_v, explained = np.empty(G.shape), np.empty(G.shape)
    gain = np.empty(n_win)
    weights = np.empty((n_win, width), dtype=np.complex128)
    m = len(correlated)
    cross = np.empty((n_win, m, m), dtype=np.complex128)
    for a in range(0, n_win, CHUNK):  # an hour at 16 kHz is millions of windows
        w = np.arange(a, min(a + CHUNK, n_win))
        idx = 1 + w[:, None] * width + np.arange(width)
        G[:, w], var_v[:, w], gain[w], explained[:, w], weights[w], cross[w] = _windows(
            U[idx], Y[:, idx], poly, list(correlated))
    smooth, dof = _smoothed_variance(var_v, width - p)
    with np.errstate(invalid="ignore"):
        sig = np.sqrt(smooth * gain / 2)
        coh = np.nan_to_num(explained / (explained + width * smooth))
    bad = ~np.isfinite(G) | ~np.isfinite(sig)
    G[bad], sig[bad], coh[bad] = np.nan, np.nan, 0.0
    f = (1 + np.arange(n_win) * width + half_width) * df
    return LPMEstimate(f, G, sig, coh, dof, (np.arange(width) - half_width) * df, weights,
                       _correlation(cross, width - p) if m else None)


def _windows(Uw: NDArray[np.complex128], Yw: NDArray[np.complex128], poly: NDArray[np.float64],
             correlated: list[int]) -> tuple[NDArray, ...]:
    """From the windows' bins ``Uw`` (nw, width) and ``Yw`` (n_responses, nw, width): G at
    each centre, the noise variance of a bin of Y (both (n_responses, nw)), the factor
    ``[(K^H K)^-1]_00`` (nw,) that makes the latter G's, the power the excitation explains
    (n_responses, nw), the weights of the true response in G (nw, width), and the noise
    covariance of the `correlated` responses (nw, m, m)."""
    nw, width = Uw.shape
    # the excitation's columns normalised per window, so that K's columns are comparable
    scale = np.sqrt(np.mean(np.abs(Uw) ** 2, axis=1))
    scale = np.where(scale > 0, scale, 1.0)
    K = np.concatenate([(Uw / scale[:, None])[:, :, None] * poly,
                        np.broadcast_to(poly, (nw, width, poly.shape[1]))], axis=2)
    Q, R = np.linalg.qr(K)  # (nw, width, p), (nw, p, p)
    Yw = np.moveaxis(Yw, 0, -1)  # (nw, width, n_responses)
    proj = np.conj(np.swapaxes(Q, 1, 2)) @ Yw
    E = Yw - Q @ proj
    var_v = np.sum(np.abs(E) ** 2, axis=1) / (width - K.shape[2])
    Ec = E[:, :, correlated]
    cross = np.swapaxes(Ec, 1, 2) @ np.conj(Ec)  # [i, j]: sum of E_i conj(E_j)
    # a window the excitation leaves (nearly) empty, as between a multisine's tones, has no
    # estimate: its R is made invertible and its G marked bad
    d = np.abs(np.diagonal(R, axis1=1, axis2=2))
    empty = d.min(axis=1) <= 1e-9 * d.max(axis=1)
    R[empty] = np.eye(R.shape[1])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        rinv = np.linalg.inv(R)
        # G = row 0 of R^-1 Q^H Y: a weighted sum of the window's Y = G_true U + ...
        row = (rinv[:, 0, :, None] * np.conj(np.swapaxes(Q, 1, 2))).sum(axis=1) / scale[:, None]
        G = np.einsum("wk,wkr->wr", row, Yw)
        gain = np.sum(np.abs(rinv[:, 0, :]) ** 2, axis=1) / scale**2
        explained = np.abs(G) ** 2 * np.sum(np.abs(Uw) ** 2, axis=1)[:, None]
    G[empty] = np.nan
    return G.T, var_v.T, gain, explained.T, row * Uw, cross


def _smoothed_variance(var: NDArray[np.float64], q: int) -> tuple[NDArray[np.float64], int]:
    """The noise variances of neighbouring windows, smoothed, and their degrees of freedom.

    One window's variance has ``q`` (9) degrees of freedom: it scatters by a third, and a
    fit weighted by it gives the windows where it came out low the most weight, with
    uncertainties that trust them. Where the noise spectrum is smooth on the scale of a few
    windows (windows narrow against the resonances), a quadratic in ``log var`` over
    :data:`SMOOTH_WINDOWS` (Savitzky-Golay) follows a resonance's peak and has about three
    times the degrees of freedom. The log's bias, ``psi(q) - ln q``
    for a chi-square of ``2 q``, is taken out.

    Where the spectrum is not smooth on that scale, a quadratic understates its bumps: below
    2 Hz the 40m's IN1 noise falls by decades over the 7 windows (2 Hz) of a one-minute
    record, with the damped resonances on it, and a bump's variance can come out several
    times too small. A window whose own variance exceeds the smoothed one beyond chance (the
    ratio's F(2 q, 2 dof) tail at :data:`GUARD`) keeps its own, larger and with ``q``
    degrees of freedom; the ones returned are the smoothed windows'.
    """
    span = _span(var.shape[-1])
    if span < 5 or not np.all(np.isfinite(var) & (var > 0)):
        return var, q
    smooth = np.exp(_quadratic(np.log(var), span, -1) + math.log(q) - special.digamma(q))
    dof = int(q / np.sum(signal.savgol_coeffs(span, 2) ** 2))
    above = var > smooth * stats.f.isf(GUARD, 2 * q, 2 * dof)
    return np.where(above, var, smooth), dof


def _span(n: int) -> int:
    """Windows smoothed over: :data:`SMOOTH_WINDOWS`, or the odd number of the `n` there
    are if fewer (below 5 a quadratic is not worth smoothing with)."""
    return min(SMOOTH_WINDOWS, n - (1 - n % 2))


def _quadratic(x: NDArray, span: int, axis: int) -> NDArray:
    """`x` (real or complex) smoothed by a quadratic over `span` windows (Savitzky-Golay)."""
    if np.iscomplexobj(x):
        return _quadratic(x.real, span, axis) + 1j * _quadratic(x.imag, span, axis)
    return signal.savgol_filter(x, span, 2, axis=axis)


def _correlation(cross: NDArray[np.complex128], q: int) -> NDArray[np.complex128]:
    """Correlation matrices of the responses' noises, from the windows' sums of residual
    products (nw, m, m) of ``q`` degrees of freedom, smoothed over :data:`SMOOTH_WINDOWS`.

    Smoothed as a chain of regressions, ``R = L D L^H`` with ``L`` unit lower triangular:
    the fraction of each noise's variance the ones before it leave (``D``, a quadratic in
    its log as the variances are; ``q - i`` degrees of freedom against the variance's
    ``q``) and its regression on them (``L``, linearly: it may change sign). Where two
    readbacks share 0.99 of their noise, what a fit learns from their difference rests on
    the 2 % left over; a smoothed correlation misplaces that by its own size where the
    correlation turns, and ``1 - |rho|^2`` of a few windows' estimate is biased low.
    """
    m = cross.shape[1]
    d = np.sqrt(np.einsum("wii->wi", cross).real)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = cross / (d[:, :, None] * d[:, None, :])
    good = np.all(np.isfinite(rho), axis=(1, 2))
    # a window with a silent response has no correlation; identical responses, one of 1
    rho = np.where(good[:, None, None], rho, np.eye(m)) + 1e-12 * np.eye(m)
    span = _span(len(rho))
    if span < 5:
        return rho
    c = np.linalg.cholesky(rho)
    diag = np.einsum("wii->wi", c).real
    bias = special.digamma(q) - special.digamma(q - np.arange(m))
    left = np.exp(_quadratic(2 * np.log(diag), span, 0) + bias)
    unit = np.tril(_quadratic(c / diag[:, None, :], span, 0), -1) + np.eye(m)
    cov = unit @ (left[:, :, None] * np.conj(np.swapaxes(unit, 1, 2)))
    d = np.sqrt(np.einsum("wii->wi", cov).real)
    return cov / (d[:, :, None] * d[:, None, :])


def lpm_tfs(x: NDArray[np.float64], ys: Sequence[NDArray[np.float64]], rate: float,
            half_width: int = HALF_WIDTH, order: int = ORDER,
            max_hz: float | None = None, correlated: Sequence[int] = ()) -> LPMEstimate:
    """Transfer functions ``y / x`` of several responses to one excitation, by the LPM.

    Parameters
    ----------
    x : ndarray
        Excitation samples.
    ys : sequence of ndarray
        Responses, each as long as `x`.
    rate : float
        Sample rate (Hz).
    half_width, order : int
        Window half-width ``n`` (bins of ``rate / len(x)``) and polynomial order ``R``.
    max_hz : float, optional
        Estimates up to here are those of the whole band (default: Nyquist); a few
        windows beyond are estimated too.
    correlated : sequence of int
        Responses whose errors' correlation is estimated.

    Returns
    -------
    LPMEstimate
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 1 or any(np.shape(y) != x.shape for y in ys):
        msg = f"responses of {[np.shape(y) for y in ys]} samples for an excitation of {x.shape}"
        raise LPMError(msg)
    # Past max_hz: the window holding it, and the windows its smoothing reaches, so that
    # estimates up to max_hz do not depend on where the cut falls.
    reach = (SMOOTH_WINDOWS // 2 + 2) * (2 * half_width + 1)
    keep = x.size // 2 + 1 if max_hz is None else min(
        x.size // 2 + 1, int(np.ceil(max_hz * x.size / rate)) + reach)
    U = fft.rfft(x)[:keep]
    Y = np.stack([fft.rfft(np.asarray(y, dtype=np.float64))[:keep] for y in ys])
    return lpm(U, Y, rate / x.size, half_width, order, correlated)
