"""Transfer functions of single-sine excitations by demodulation: awg's ``sine`` injections
one after another, or a stepped sine made by hand, found in a recording with no events.

Each stretch, its first :data:`SETTLE` left out, is cut into :data:`AVERAGES` blocks; each
block of EXC and of every response is demodulated at the sine's frequency through a Hann
window (which keeps the other sign's image and the loop's transient at other frequencies
out), and the
blocks' complex amplitudes are averaged as Welch averages segments: ``H = <Y X*> / <|X|^2>``,
the coherence ``|<Y X*>|^2 / (<|X|^2> <|Y|^2>)``, so that the errors are Bendat and Piersol's
over the blocks. The frequency is the recognised line's, refined by the phase the EXC
advances from block to block.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind.errors import TwindError

AVERAGES = 10
"""Blocks a sine's stretch is cut into: the estimate's averages."""
CYCLES = 2.0
"""Cycles a block holds at least."""
SETTLE = 0.2
"""Fraction of a stretch left out first, while the loop's response to the sine's switch-on
dies away (diaggui's swept sine settles each step likewise)."""


class DemodulationError(TwindError):
    """A stretch too short to demodulate at its frequency."""


def demodulate(x: NDArray[np.float64], ys: Sequence[NDArray[np.float64]], rate: float,
               f_hz: float, averages: int = AVERAGES
               ) -> tuple[float, NDArray[np.complex128], NDArray[np.float64]]:
    """``Y/EXC`` of each of `ys` at the sine of `x`, near `f_hz`.

    Parameters
    ----------
    x : ndarray
        The EXC samples: one sine, its first :data:`SETTLE` left out.
    ys : sequence of ndarray
        The responses, each as long as `x`.
    rate : float
        Sample rate (Hz).
    f_hz : float
        The sine's frequency, to within a quarter of ``averages * rate / len(x)``.
    averages : int
        Blocks.

    Returns
    -------
    f_hz : float
        The sine's frequency, refined.
    h : ndarray of complex
        One per response.
    coherence : ndarray of float
        One per response.

    Raises
    ------
    DemodulationError
        If a block would hold fewer than :data:`CYCLES` cycles.
    """
    skip = int(SETTLE * len(x))
    x, ys = x[skip:], [y[skip:] for y in ys]
    block = len(x) // averages
    if block * f_hz / rate < CYCLES:
        msg = (f"{len(x) / rate:.1f} s of a {f_hz:.4g} Hz sine after settling: {averages} "
               f"blocks of {CYCLES:g} cycles need {averages * CYCLES / f_hz:.1f} s")
        raise DemodulationError(msg)
    X = _blocks(x, block, averages, rate, f_hz)
    step = np.angle(np.sum(X[1:] * X[:-1].conj())) / (2 * np.pi) - block * f_hz / rate
    f_hz += (step - np.round(step)) * rate / block
    X = _blocks(x, block, averages, rate, f_hz)
    Y = np.stack([_blocks(y, block, averages, rate, f_hz) for y in ys])
    sxy, sxx = Y @ X.conj(), float(np.sum(np.abs(X) ** 2))
    syy = np.sum(np.abs(Y) ** 2, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return f_hz, sxy / sxx, np.abs(sxy) ** 2 / (sxx * syy)


def _blocks(x: NDArray[np.float64], block: int, averages: int, rate: float, f_hz: float
            ) -> NDArray[np.complex128]:
    """Each block's complex amplitude at `f_hz`, its phase that of the block's start."""
    lo = signal.windows.hann(block, sym=False) * np.exp(-2j * np.pi * f_hz *
                                                         np.arange(block) / rate)
    return np.asarray(x[: averages * block], dtype=float).reshape(averages, block) @ lo
