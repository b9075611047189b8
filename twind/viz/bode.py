"""Measured transfer functions of an excited degree of freedom (Welch averages)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import signal


@dataclass(frozen=True)
class TransferFunction:
    """``H(f) = P_xy / P_xx`` (scipy's ``csd(x, y)`` convention) with its coherence."""

    freq_hz: NDArray[np.float64]
    response: NDArray[np.complex128]
    coherence: NDArray[np.float64]
    averages: int

    @property
    def magnitude_db(self) -> NDArray[np.float64]:
        return 20 * np.log10(np.abs(self.response))

    @property
    def phase_deg(self) -> NDArray[np.float64]:
        return np.degrees(np.angle(self.response))


def segment_length(n: int, rate_hz: float, min_averages: int = 8,
                   tone_hz: float | None = None) -> int:
    """A Welch segment giving at least `min_averages` segments of `n` samples (50 % overlap
    gives about twice as many averages), at most 64 s long: a power of two, or, for a sine at
    `tone_hz`, a whole number of its periods, so that one bin falls on the tone (within
    1e-4 of a bin) and the plotted point is at the frequency it was measured at.

    Parameters
    ----------
    n : int
        Samples of the measurement.
    rate_hz : float
        Sample rate (Hz).
    min_averages : int
        Fewest non-overlapping segments wanted.
    tone_hz : float, optional
        Frequency of a sine excitation (Hz).

    Returns
    -------
    int
        Samples per segment; all `n` when even 16-sample segments would be too few.
    """
    longest = min(n // min_averages, int(64 * rate_hz))
    if longest < 16:
        return max(1, n)
    if tone_hz is not None and 0 < tone_hz < rate_hz / 2:
        periods = int(np.floor(longest * tone_hz / rate_hz))
        if periods >= 1:
            return int(round(periods * rate_hz / tone_hz))
    return 1 << int(np.floor(np.log2(longest)))


def measure(exc: NDArray[np.float64], outputs: dict[str, NDArray[np.float64]], rate_hz: float,
            nperseg: int | None = None, dynamic_range: float = 1e-4,
            tone_hz: float | None = None) -> dict[str, TransferFunction]:
    """Transfer functions from `exc` to each of `outputs` (same length, same rate); `tone_hz`
    is the frequency of a sine excitation (see :func:`segment_length`).

    Only the bins where the excitation carries power are kept: ``P_xx`` above `dynamic_range`
    times its peak (40 dB by default) and ``f > 0``. Elsewhere the ratio of two noise
    estimates means nothing.

    Parameters
    ----------
    exc : numpy.ndarray
        Samples of the excitation (EXC).
    outputs : dict of str to numpy.ndarray
        Samples of each response (IN1, IN2, ...), by name.
    rate_hz : float
        Sample rate (Hz).
    nperseg : int, optional
        Welch segment length; by default :func:`segment_length`'s.
    dynamic_range : float
        Lowest ``P_xx`` kept, as a fraction of its peak.
    tone_hz : float, optional
        Frequency of a sine excitation (Hz).

    Returns
    -------
    dict of str to TransferFunction
        By the names of `outputs`; empty of bins if `exc` is all zeros.
    """
    exc = np.asarray(exc, dtype=float)
    nperseg = nperseg or segment_length(exc.size, rate_hz,
                                        min_averages=4 if tone_hz else 8, tone_hz=tone_hz)
    kw = {"fs": rate_hz, "nperseg": nperseg, "window": "hann", "detrend": "constant"}
    f, pxx = signal.welch(exc, **kw)
    keep = (f > 0) & (pxx > dynamic_range * pxx.max()) if pxx.max() > 0 else np.zeros(f.size, bool)
    averages = max(1, (exc.size - nperseg) // (nperseg // 2) + 1)
    result = {}
    for name, y in outputs.items():
        _, pxy = signal.csd(exc, y, **kw)
        _, pyy = signal.welch(y, **kw)
        with np.errstate(divide="ignore", invalid="ignore"):
            h = pxy / pxx
            coh = np.abs(pxy) ** 2 / (pxx * pyy)
        result[name] = TransferFunction(f[keep], h[keep], np.nan_to_num(coh[keep]), averages)
    return result
