"""The numerical designs behind the waveforms: tapers, multisine periods, noise shaping.

Shared by :mod:`twind.excitation.checks` (which needs the true peak and RMS of what will be
sent) and :mod:`twind.excitation.waveforms` (which sends it); the expensive designs are cached
so that checking and then starting an excitation computes them once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind.errors import FotonError
from twind.excitation.request import ExcitationError
from twind.loop.foton import design_to_sos

MAX_PERIOD = 2**22
"""Longest multisine period (samples): 256 s at 16384 Hz, 32 MB as float64."""

TONE_TOLERANCE = 0.01
"""A multisine tone may move by this fraction of itself to land on the period's grid; when
even the longest period cannot do that, tones move by up to half its resolution."""

NOISE_PEAK_SIGMAS = 6.0
"""Gaussian noise is taken to peak at this many times its RMS (see ``check``)."""


# -- taper --------------------------------------------------------------------------------------
def taper(idx: NDArray[np.int64], n_ramp: int, end: int | None) -> NDArray[np.float64]:
    """Raised-cosine window of an excitation at absolute sample indices.

    Parameters
    ----------
    idx : ndarray of int
        Sample indices, 0 = the excitation's first sample.
    n_ramp : int
        Samples in each ramp; 0 = no taper.
    end : int or None
        One past the last sample, for the closing ramp; None = no closing ramp.

    Returns
    -------
    ndarray
        ``0.5 (1 - cos(pi n / n_ramp))`` over the first `n_ramp` samples (0 at sample 0),
        its mirror image over the last `n_ramp` (0 at sample ``end - 1``), 1 in between.
        Each value depends on its own index only, so blocks of any size agree bit for bit.
    """
    w = np.ones(idx.shape)
    if n_ramp <= 0:
        return w
    head = idx < n_ramp
    w[head] = 0.5 * (1.0 - np.cos(math.pi * idx[head] / n_ramp))
    if end is not None:
        tail = idx >= end - n_ramp
        w[tail] *= 0.5 * (1.0 - np.cos(math.pi * (end - 1 - idx[tail]) / n_ramp))
    return w


# -- multisine ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class MultisinePlan:
    """One period of a Schroeder-phased multisine, normalised to a peak of 1.

    Attributes
    ----------
    period : ndarray
        ``n_period`` samples, read-only; ``max |period| == 1``.
    freqs : ndarray
        The tones actually sent (Hz): the requested ones moved onto the period's grid.
    rms : float
        RMS of `period` (so the multisine's RMS is ``amp * rms``).
    """

    period: NDArray[np.float64]
    freqs: NDArray[np.float64]
    rms: float


def multisine_tones(freq: float | None, f_stop: float | None, n_tones: int | None,
                    freqs: tuple[float, ...] | None) -> NDArray[np.float64]:
    """The requested tones: `freqs` as given, or `n_tones` log-spaced from `freq` to `f_stop`.

    Parameters
    ----------
    freq : float or None
        Lowest tone (Hz), when `freqs` is None.
    f_stop : float or None
        Highest tone (Hz), when `freqs` is None and `n_tones` > 1.
    n_tones : int or None
        Number of tones, when `freqs` is None.
    freqs : tuple of float or None
        The tones (Hz), in any order; they take precedence over the three above.

    Returns
    -------
    numpy.ndarray
        The tones (Hz), ascending.

    Examples
    --------
    >>> multisine_tones(1.0, 100.0, 3, None)
    array([  1.,  10., 100.])
    """
    if freqs is not None:
        return np.sort(np.asarray(freqs, dtype=float))
    assert freq is not None and n_tones is not None  # check() guarantees it
    if n_tones == 1:
        return np.array([freq])
    assert f_stop is not None
    return np.geomspace(freq, f_stop, n_tones)


def _grid(tones: NDArray[np.float64], rate_hz: float) -> tuple[int, NDArray[np.int64]]:
    """Shortest power-of-two period whose bins hold every tone within TONE_TOLERANCE.

    A period of N samples makes the signal exactly periodic only if every tone is a whole
    number of cycles per period, i.e. a multiple of ``rate / N``; then its peak over one
    period is its peak for ever, which is what a limit check needs.
    """
    gaps = np.diff(tones)
    n = 2**8
    while True:
        df = rate_hz / n
        bins = np.rint(tones / df).astype(np.int64)
        close = np.all(np.abs(bins * df - tones) <= TONE_TOLERANCE * tones)
        # df below each gap keeps neighbouring tones in different bins.
        apart = gaps.size == 0 or df < 0.5 * float(np.min(gaps))
        if (close and apart) or n >= MAX_PERIOD:
            break
        n *= 2
    if np.any(bins < 1):
        raise ExcitationError(
            f"the tone at {tones[0]:.6g} Hz is below {df / 2:.6g} Hz, half the frequency "
            f"resolution of the longest multisine period ({n} samples, {n / rate_hz:g} s)",
            "freq")
    if np.any(np.diff(bins) == 0):
        j = int(np.flatnonzero(np.diff(bins) == 0)[0])
        raise ExcitationError(
            f"tones {tones[j]:.6g} Hz and {tones[j + 1]:.6g} Hz are closer than the "
            f"{df:.6g} Hz resolution of the longest multisine period ({n / rate_hz:g} s); "
            "use fewer tones or a higher lowest tone", "n_tones")
    if np.any(2 * bins >= n):
        raise ExcitationError(f"a tone lands at or above the Nyquist frequency "
                              f"{rate_hz / 2:g} Hz", "f_stop")
    return n, bins


def schroeder_phases(freqs: NDArray[np.float64], period_s: float) -> NDArray[np.float64]:
    """Schroeder phases (radians) for equal-amplitude tones at any frequencies.

    The multisine then behaves like a chirp that visits each tone for an equal share of
    the period, which keeps the crest factor near that of a single sine instead of the
    ``sqrt(2 N)`` of tones that all start in phase.  For harmonic tones ``k / T`` this is
    Schroeder's ``-pi k (k - 1) / N``.

    Parameters
    ----------
    freqs : ndarray
        Tones (Hz), increasing.
    period_s : float
        Period of the multisine (s).

    Returns
    -------
    ndarray
        ``phi_k = phi_{k-1} - 2 pi (f_k - f_{k-1}) T (k - 1) / N``, ``phi_1 = 0``.
    """
    n = freqs.size
    k = np.arange(n)
    # group delay of tone k: the time the equivalent chirp reaches it, T (k - 1) / N
    steps = -2.0 * math.pi * np.diff(freqs) * period_s * k[:-1] / n
    return np.concatenate([[0.0], np.cumsum(steps)]) % (2 * math.pi)


@lru_cache(maxsize=4)
def multisine_plan(tones: tuple[float, ...], rate_hz: float) -> MultisinePlan:
    """Design one period of the multisine of `tones` at `rate_hz` (cached).

    Parameters
    ----------
    tones : tuple of float
        Requested tones (Hz), increasing, distinct, below Nyquist.
    rate_hz : float
        Model rate.

    Returns
    -------
    MultisinePlan

    Raises
    ------
    ExcitationError
        If the tones cannot be told apart within the longest period.
    """
    f = np.asarray(tones, dtype=float)
    n, bins = _grid(f, rate_hz)
    actual = bins * (rate_hz / n)
    # The chirp Schroeder's phases imitate must span the signal's own fundamental period,
    # not the (longer) grid period: harmonics of 1 Hz on a 128 s grid would otherwise get
    # phase steps of whole turns, i.e. all tones in phase, the worst crest factor.
    fundamental = int(np.gcd.reduce(bins))
    phases = schroeder_phases(actual, n / (fundamental * rate_hz))
    # One inverse FFT gives the exact period; sin(x + phi) = cos(x + phi - pi/2).
    spec = np.zeros(n // 2 + 1, dtype=complex)
    spec[bins] = 0.5 * n * np.exp(1j * (phases - 0.5 * math.pi))
    period = np.fft.irfft(spec, n)
    period /= np.max(np.abs(period))
    period.flags.writeable = False  # cached and shared between waveforms
    return MultisinePlan(period, actual, float(np.sqrt(np.mean(period**2))))


# -- noise shaping ------------------------------------------------------------------------------
@dataclass(frozen=True)
class NoiseShape:
    """Shaping sections of a noise excitation and the RMS they give unit white noise.

    Attributes
    ----------
    sections : ndarray, shape (n, 6)
        Second-order sections (scipy layout); read-only, as the design is cached.
    gain_rms : float
        RMS of the output for unit-variance white input, in the steady state.
    """

    sections: NDArray[np.float64]
    gain_rms: float

    @property
    def sos(self) -> NDArray[np.float64]:
        """A writeable copy of `sections` (scipy's sosfilt refuses read-only arrays)."""
        return np.array(self.sections)


def _grid_for(sos: NDArray[np.float64]) -> NDArray[np.float64]:
    """Frequencies (rad/sample) fine enough to integrate ``|H|^2`` of `sos` accurately.

    A uniform grid, a logarithmic one for low-frequency features, and around every pole
    a cluster of points spaced by fractions of its bandwidth ``1 - |p|`` — a high-Q
    resonance or a pole near DC would fall between the points of any uniform grid.
    """
    parts = [np.linspace(0.0, math.pi, 2**14 + 1), np.geomspace(1e-9, math.pi, 2**12)]
    offsets = np.geomspace(1e-3, 1e3, 1201)  # 1.2 % steps: trapezoid error ~1e-5
    offsets = np.concatenate([-offsets[::-1], [0.0], offsets])
    for sec in sos:
        for p in np.roots(sec[3:]):
            width = max(1.0 - abs(p), 1e-12)
            parts.append(abs(np.angle(p)) + width * offsets)
    w = np.concatenate(parts)
    return np.unique(np.clip(w, 0.0, math.pi))


def noise_gain(sos: NDArray[np.float64]) -> float:
    """RMS of the output of `sos` driven by unit-variance white noise.

    Parseval: the output variance is ``(1/pi) * integral_0^pi |H(e^jw)|^2 dw``, i.e.
    ``sum |H|^2 df`` over 0..Nyquist normalised by the Nyquist frequency.  It is computed
    from the sections' response on a pole-refined grid, not by filtering noise, so the RMS
    of the excitation is exactly what the request says rather than a random estimate.

    Parameters
    ----------
    sos : ndarray, shape (n, 6)
        Stable second-order sections.

    Returns
    -------
    float
        The RMS gain (0 for a filter without gain, inf if it is not finite).
    """
    w = _grid_for(sos)
    _, h = signal.sosfreqz(sos, worN=w)
    with np.errstate(all="ignore"):
        p = np.abs(h) ** 2
        # trapezoid rule written out: np.trapezoid is numpy >= 2 only
        var = float(np.sum(0.5 * (p[1:] + p[:-1]) * np.diff(w)) / math.pi)
    return math.sqrt(var) if math.isfinite(var) else math.inf


@lru_cache(maxsize=16)
def noise_shape(shape: str, rate_hz: float) -> NoiseShape:
    """Discretise a foton design string for shaping noise, and its RMS gain (cached).

    Parameters
    ----------
    shape : str
        Foton design string, e.g. ``'butter("BandPass",4,1,30)'``.
    rate_hz : float
        Model rate.

    Returns
    -------
    NoiseShape

    Raises
    ------
    ExcitationError
        If foton cannot read the design (its message), the filter is not strictly stable
        (its noise would grow without bound), or it has no gain.
    """
    try:
        sos = design_to_sos(shape, rate_hz)
    except FotonError as exc:
        raise ExcitationError(str(exc), "shape") from None
    poles = np.concatenate([np.roots(sec[3:]) for sec in sos]) if sos.size else np.array([])
    radius = float(np.max(np.abs(poles))) if poles.size else 0.0
    if not radius < 1.0:
        raise ExcitationError(f"the shaping filter {shape!r} is not stable (a pole at "
                              f"|z| = {radius:.12g}; integrators and right-half-plane poles "
                              "have no finite noise RMS)", "shape")
    gain = noise_gain(sos)
    if not (gain > 0.0 and math.isfinite(gain)):
        raise ExcitationError(f"the shaping filter {shape!r} has no finite, nonzero noise "
                              f"gain (RMS gain {gain:g}); it cannot be scaled to an RMS",
                              "shape")
    sos = np.array(sos, dtype=float)
    sos.flags.writeable = False
    return NoiseShape(sos, gain)
