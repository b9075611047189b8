"""Where a state-space diagnosis starts each change: scans of the residuals that cost a few
products per trial.

Around a fitted model (its calibrations, delay and effects held), a change of one mode's
section, ``dS = d(1/den) num_1 + d(s/den) num_s``, whitens to ``dq0 B + dq1 A`` with ``A``,
``B`` the whitened numerators per bin: the drop in chi^2 it makes, ``2 <z, delta> -
|delta|^2``, needs only their sums over the elements at each bin, so a trial frequency costs
a pass over the bins. A mode in no model, with a real numerator per element, is fitted
linearly at each trial frequency. Each sweep also measures how far its signature turns
(Davies' look-elsewhere path, :func:`twind.analysis.identification.narrow.p_value`), so that
the p-value of what it finds pays for where it looked.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind.analysis.identification.data import FitData
from twind.analysis.identification.narrow import SEARCH_Q
from twind.analysis.statespace.model import PlantModel

SHIFT = 1.5
"""A model mode is searched for from its frequency over this factor to its frequency times it."""

FINE_Q = 200.0
"""A moved mode of higher Q is searched again at this Q near the best of the broad sweeps
(the fit then frees its Q)."""
_CHUNK = 64  # trials evaluated together


@dataclass(frozen=True)
class Sweep:
    """A scan's best trial, its drop in chi^2, and each sweep's look-elsewhere path (rad)."""

    drop: float
    f_hz: float
    q: float
    paths: tuple[float, ...]
    coefficients: NDArray[np.float64] | None = None


class Residuals:
    """A fitted model's whitened residuals and what a change of its plant whitens to.

    Parameters
    ----------
    data : FitData
    model : PlantModel
    predicted : ndarray
        The fitted model at the data's bins (nf, readbacks, drives).
    gain : ndarray
        ``g_r g_d L C_r``: what turns a change of the plant into one of the measurement
        (nf, readbacks, drives).
    """

    def __init__(self, data: FitData, model: PlantModel, predicted: NDArray[np.complex128],
                 gain: NDArray[np.complex128]) -> None:
        self.data, self.model = data, model
        self.whitener = np.where(data.mask, 1.0 / np.where(data.mask, data.sigma, 1.0), 0.0)
        self.z = np.where(data.mask, (data.H - predicted) * self.whitener, 0.0)
        self.G = gain * self.whitener
        self.predicted = predicted

    def power(self, change: NDArray[np.complex128]) -> float:
        """The whitened power of a change of the plant."""
        return float(np.sum(np.abs(self.G * change) ** 2))

    def linear(self, column: NDArray[np.complex128]) -> tuple[float, float]:
        """The drop in chi^2 a real multiple of a whitened `column` makes at best, and the
        multiple."""
        proj = float(np.sum((np.conj(self.z) * column).real))
        norm = float(np.sum(np.abs(column) ** 2))
        return (proj * proj / norm, proj / norm) if norm > 0 else (0.0, 0.0)

    # ---------------------------------------------------------------- a model mode moved
    def moved(self, k: int, unit: float) -> Sweep:
        """Mode `k` moved over ``[f / SHIFT, f SHIFT]`` at each of
        :data:`~twind.analysis.identification.narrow.SEARCH_Q`, then as narrow as the data
        resolve (:data:`FINE_Q`, or its own Q if lower) within a few widths of the best: the
        best trial (its drop in chi^2 in units of `unit`) and every sweep's path."""
        m = self.model.modal
        sums = _Sums(self.z, self.G * m.num_s[k], self.G * m.num_1[k])
        old = self.model.kernels(m.w[k], m.q[k])
        f0 = m.w[k] / (2 * math.pi)
        best, paths = (-np.inf, f0, m.q[k]), []
        for q in SEARCH_Q:
            drop, trials, path = self._sweep(sums, old, grid(f0 / SHIFT, f0 * SHIFT, q,
                                                             self.model.res), q)
            paths.append(path)
            i = int(np.argmax(drop))
            if drop[i] > best[0]:
                best = (float(drop[i]), float(trials[i]), q)
        q = min(FINE_Q, m.q[k]) if m.q[k] > SEARCH_Q[-1] else None
        if q is not None:
            reach = 5 * best[1] / SEARCH_Q[-1]
            drop, trials, path = self._sweep(sums, old, grid(best[1] - reach, best[1] + reach,
                                                             q, self.model.res), q)
            paths.append(path)
            i = int(np.argmax(drop))
            if drop[i] > best[0]:
                best = (float(drop[i]), float(trials[i]), q)
        return Sweep(best[0] / unit, best[1], best[2], tuple(paths))

    def _sweep(self, sums: _Sums, old: tuple, trials: NDArray[np.float64], q: float
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        """Each trial's drop in chi^2 for a mode moved from `old` (its kernels) to the
        frequencies `trials` at `q`, and the sweep's path."""
        drops, path, last = [], 0.0, None
        for chunk in np.array_split(trials, max(1, trials.size // _CHUNK)):
            d0, d1 = self.model.kernels_many(2 * math.pi * chunk, q)
            d0, d1 = d0 - old[0], d1 - old[1]
            drops.append(2 * sums.project(d0, d1) - sums.norm2(d0, d1))
            if last is not None:  # the turn between this chunk and the last
                d0, d1 = np.vstack([last[0], d0]), np.vstack([last[1], d1])
            path += sums.path(d0, d1)
            last = (d0[-1:], d1[-1:])
        return np.concatenate(drops), trials, path

    # ---------------------------------------------------------------- a mode in no model
    def resonance(self, unit: float, avoid: Sequence[tuple[float, float]] = ()) -> Sweep:
        """A mode with a real numerator per element, anywhere in the data's band but the
        ranges `avoid` (Hz: where a mode of the model was moved, which it would only
        duplicate), at each of :data:`~twind.analysis.identification.narrow.SEARCH_Q`."""
        f = self.data.frequency_hz[self.data.mask.any(axis=(1, 2))]
        lo, hi = max(float(f[0]), 1e-3), float(f[-1])
        Gz = (np.conj(self.z) * self.G).reshape(self.z.shape[0], -1)  # (nf, elements)
        G2 = (np.abs(self.G) ** 2).reshape(self.z.shape[0], -1)
        best, paths = (-np.inf, lo, SEARCH_Q[0], None), []
        for q in SEARCH_Q:
            trials = grid(lo, hi, q, self.model.res)
            trials = trials[~np.any([(trials > a) & (trials < b) for a, b in avoid], axis=0)] \
                if avoid else trials
            path, last = 0.0, None
            for chunk in np.array_split(trials, max(1, trials.size // _CHUNK)):
                q0, _ = self.model.kernels_many(2 * math.pi * chunk, q)
                proj = (q0 @ Gz).real  # (trials, elements)
                norm = np.abs(q0) ** 2 @ G2
                with np.errstate(divide="ignore", invalid="ignore"):
                    drop = np.where(norm > 0, proj**2 / norm, 0.0).sum(axis=1)
                    coef = np.where(norm > 0, proj / norm, 0.0)
                i = int(np.argmax(drop))
                if drop[i] > best[0]:
                    best = (float(drop[i]), float(chunk[i]), q, coef[i])
                # the angle the stacked signature turns between neighbouring trials
                both = q0 if last is None else np.vstack([last, q0])
                cross = (np.conj(both[:-1]) * both[1:]).real @ G2
                n2 = np.abs(both) ** 2 @ G2
                cos = cross.sum(axis=1) / np.sqrt(np.maximum(n2[:-1].sum(axis=1)
                                                             * n2[1:].sum(axis=1), 1e-300))
                path += float(np.sum(np.arccos(np.clip(np.abs(cos), 0, 1))))
                last = q0[-1:]
            paths.append(path)
        return Sweep(best[0] / unit, best[1], best[2], tuple(paths), best[3])


class _Sums:
    """Sums over the elements, bin by bin, of a mode's whitened numerators against the
    residuals and each other."""

    def __init__(self, z: NDArray, A: NDArray, B: NDArray) -> None:
        ax = (1, 2)
        self.U1 = np.sum(np.conj(z) * A, axis=ax)
        self.U0 = np.sum(np.conj(z) * B, axis=ax)
        self.V11 = np.sum(np.abs(A) ** 2, axis=ax)
        self.V00 = np.sum(np.abs(B) ** 2, axis=ax)
        self.V10 = np.sum(np.conj(A) * B, axis=ax)

    def project(self, d0: NDArray, d1: NDArray) -> NDArray[np.float64]:
        """``<z, delta>`` for each trial's change (trials, nf)."""
        return (d1 @ self.U1 + d0 @ self.U0).real

    def norm2(self, d0: NDArray, d1: NDArray) -> NDArray[np.float64]:
        """``|delta|^2`` for each trial."""
        return (np.abs(d1) ** 2 @ self.V11 + np.abs(d0) ** 2 @ self.V00
                + 2 * (np.conj(d1) * d0 @ self.V10).real)

    def path(self, d0: NDArray, d1: NDArray) -> float:
        """The angle the trials' changes turn through, neighbour to neighbour."""
        if d0.shape[0] < 2:
            return 0.0
        a0, a1, b0, b1 = d0[:-1], d1[:-1], d0[1:], d1[1:]
        dot = ((np.conj(a1) * b1) @ self.V11 + (np.conj(a0) * b0) @ self.V00
               + (np.conj(a1) * b0) @ self.V10 + (np.conj(a0) * b1) @ np.conj(self.V10)).real
        norms = self.norm2(d0, d1)
        cos = dot / np.sqrt(np.maximum(norms[:-1] * norms[1:], 1e-300))
        return float(np.sum(np.arccos(np.clip(np.abs(cos), 0, 1))))


def grid(lo: float, hi: float, q: float, res: float) -> NDArray[np.float64]:
    """A search's trial frequencies from `lo` to `hi` in steps of a quarter of a bin or of
    the width."""
    out, f = [], lo
    while f <= hi:
        out.append(f)
        f += 0.25 * max(res, f / q)
    return np.array(out)
