"""Where a measurement shows resonances, read from the data alone: the peaks of each coherent
element's magnitude.

A model's mode found elsewhere in a measurement must be found where the data show a peak:
a screen of the model's mode against the residuals (:mod:`~twind.analysis.statespace.search`)
also rises where moving the mode merely fills some other misfit, a neighbouring mode's or a
coupling's. So the places a diagnosis tries for a moved mode are the data's own peaks
(:func:`measured_peaks`), as a commissioner reads a transfer function before comparing it
with the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind.analysis.identification.data import FitData

MIN_RUN = 5
"""Coherent bins in a row a peak is looked for in."""
PROMINENCE = 0.2
"""The least a peak stands above the valleys either side (natural log of the magnitude: a
fifth, 22 %)."""
NOISE_PROMINENCE = 4.0
"""...and at least this many times the relative error of the bins there."""
HALF_POWER = 0.5 * np.log(2.0)
"""3 dB of magnitude, in its natural log: where a resonance's width is read."""


@dataclass(frozen=True)
class Peak:
    """A resonance peak of one measured element.

    Attributes
    ----------
    f_hz : float
        Where it stands (the largest bin, refined by a parabola through its neighbours).
    width_hz : float
        Its width 3 dB below its top (at least a bin; its prominence's width where it
        stands less than 3 dB out).
    prominence : float
        How far it stands above the valleys either side (natural log of the magnitude).
    element : tuple of int
        (readback, drive).
    """

    f_hz: float
    width_hz: float
    prominence: float
    element: tuple[int, int]


def measured_peaks(data: FitData) -> list[Peak]:
    """Every peak of every element's magnitude over its runs of coherent bins, standing out
    of its neighbours by :data:`PROMINENCE` and by :data:`NOISE_PROMINENCE` relative errors,
    in ascending frequency."""
    out = []
    f = data.frequency_hz
    df = float(np.median(np.diff(f))) if f.size > 1 else 1.0
    for r in range(data.H.shape[1]):
        for d in range(data.H.shape[2]):
            for run in _runs(data.mask[:, r, d]):
                out += _run_peaks(f[run], data.H[run, r, d], data.sigma[run, r, d], df, (r, d))
    return sorted(out, key=lambda p: p.f_hz)


def _runs(mask: NDArray[np.bool_]) -> list[NDArray[np.intp]]:
    """Runs of consecutive True of at least :data:`MIN_RUN`."""
    idx = np.flatnonzero(mask)
    if not idx.size:
        return []
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    return [x for x in runs if x.size >= MIN_RUN]


def _run_peaks(f: NDArray[np.float64], h: NDArray[np.complex128], sigma: NDArray[np.float64],
               df: float, element: tuple[int, int]) -> list[Peak]:
    """The peaks of one run of coherent bins."""
    mag = np.abs(h)
    y = np.log(np.maximum(mag, 1e-300))
    rel = np.minimum(sigma / np.maximum(mag, 1e-300), 1.0)
    at, props = signal.find_peaks(y, prominence=PROMINENCE)
    out = []
    for i, p in zip(at, props["prominences"], strict=True):
        if p < NOISE_PROMINENCE * float(np.median(rel[max(i - 2, 0): i + 3])):
            continue
        w = signal.peak_widths(y, [i], rel_height=min(HALF_POWER / p, 1.0))[0][0]
        shift = 0.0
        if 0 < i < y.size - 1:  # a parabola through the bin and its neighbours
            a, b, c = y[i - 1], y[i], y[i + 1]
            den = a - 2 * b + c
            shift = 0.5 * (a - c) / den if den < 0 else 0.0
        out.append(Peak(float(f[i] + shift * df), max(float(w) * df, df), float(p), element))
    return out
