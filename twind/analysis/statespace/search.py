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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind.analysis.identification.data import FitData
from twind.analysis.identification.narrow import SEARCH_Q
from twind.analysis.statespace.model import PlantModel, closed

SHIFT = 1.5
"""A model mode is searched for from its frequency over this factor to its frequency times it."""

FINE_Q = 200.0
"""A moved mode of higher Q is searched again at this Q near the best of the broad sweeps
(the fit then frees its Q)."""
LOCAL = 1.5
"""A closed loop's moved mode is screened on the bins within this factor beyond its searched
range (the change far from the mode is smooth and small)."""
_CHUNK = 64  # trials evaluated together
_CLOSED_CHUNK = 8  # of a closed loop's trials, each a closed loop at every bin


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
    calibrations : mapping of int to float, optional
        The fitted calibration ``g_r`` of each readback whose calibration is free (a closed
        loop's screen refits them at each trial, :class:`_ClosedChange`).
    """

    def __init__(self, data: FitData, model: PlantModel, predicted: NDArray[np.complex128],
                 gain: NDArray[np.complex128], calibrations: Mapping[int, float] | None = None
                 ) -> None:
        self.data, self.model = data, model
        self.calibrations = dict(calibrations or {})
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
        best trial (its drop in chi^2 in units of `unit`) and every sweep's path. In a closed
        loop with other loops closed, each trial's change is the whole closed loop's
        (:class:`_ClosedChange`): the other loops damp and move a mode they see."""
        m = self.model.modal
        f0 = m.w[k] / (2 * math.pi)
        if self.model.feedback:
            change = _ClosedChange(self, k)

            def sweep(trials: NDArray[np.float64], q: float) -> tuple[NDArray, float]:
                return change.sweep(trials, q)
        else:
            A, B = self.model.numerators(k)
            sums = _Sums(self.z, self.G * A, self.G * B)
            old = self.model.kernels(m.w[k], m.q[k])

            def sweep(trials: NDArray[np.float64], q: float) -> tuple[NDArray, float]:
                return self._sweep(sums, old, trials, q)
        best, paths = (-np.inf, f0, m.q[k]), []
        for q in SEARCH_Q:
            trials = grid(f0 / SHIFT, f0 * SHIFT, q, self.model.res)
            drop, path = sweep(trials, q)
            paths.append(path)
            i = int(np.argmax(drop))
            if drop[i] > best[0]:
                best = (float(drop[i]), float(trials[i]), q)
        q = min(FINE_Q, m.q[k]) if m.q[k] > SEARCH_Q[-1] else None
        if q is not None:
            reach = 5 * best[1] / SEARCH_Q[-1]
            trials = grid(best[1] - reach, best[1] + reach, q, self.model.res)
            drop, path = sweep(trials, q)
            paths.append(path)
            i = int(np.argmax(drop))
            if drop[i] > best[0]:
                best = (float(drop[i]), float(trials[i]), q)
        return Sweep(best[0] / unit, best[1], best[2], tuple(paths))

    def _sweep(self, sums: _Sums, old: tuple, trials: NDArray[np.float64], q: float
               ) -> tuple[NDArray[np.float64], float]:
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
        return np.concatenate(drops), path

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
            if not trials.size:  # the moved modes cover the band
                paths.append(path)
                continue
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


class _ClosedChange:
    """A model mode moved, as the closed loops see it: each trial's change of every element
    at the bins within :data:`LOCAL` of the mode's searched range, the whole closed loop
    solved at the bins' centres, and the readbacks' free calibrations refitted to it (a
    closed loop's residuals from a model whose mode is far off have pulled them).

    Parameters
    ----------
    res : Residuals
        Whose model has :attr:`~twind.analysis.statespace.model.PlantModel.feedback`.
    k : int
        The mode.
    """

    def __init__(self, res: Residuals, k: int) -> None:
        model, f = res.model, res.data.frequency_hz
        self.k, self.w0, self.q0 = k, model.modal.w[k], model.modal.q[k]
        f0 = self.w0 / (2 * math.pi)
        self.bins = np.flatnonzero((f >= f0 / SHIFT / LOCAL) & (f <= f0 * SHIFT * LOCAL)
                                   & res.data.mask.any(axis=(1, 2)))
        self.s = 2j * math.pi * f[self.bins]
        self.z, self.G = res.z[self.bins], res.G[self.bins]
        self.open = (model.modal.num_s[k], model.modal.num_1[k])
        self.closed = {}
        for j, fb in model.feedback.items():
            P, K = fb.P[self.bins], fb.K[self.bins]
            self.closed[j] = (fb, P, K, self._column(fb, P, K))
        self._rows(res)

    def _rows(self, res: Residuals) -> None:
        """Each readback's sums over every bin that its calibration's refit needs: the
        whitened data against the unit-calibration model, and the model's own power."""
        g = np.ones(res.z.shape[1])
        self.free = np.zeros(g.size, dtype=bool)
        for r, value in res.calibrations.items():
            if abs(value) > 0:
                g[r], self.free[r] = value, True
        self.g = g
        d = res.z + res.predicted * res.whitener  # the whitened data
        m = res.predicted * res.whitener / g[None, :, None]
        self.d = d[self.bins]
        self.m = m[self.bins]
        self.md = np.sum((np.conj(m) * d).real, axis=(0, 2))
        self.mm = np.sum(np.abs(m) ** 2, axis=(0, 2))

    def _column(self, fb, P: NDArray, K: NDArray) -> NDArray[np.complex128]:  # noqa: ANN001
        """The closed-loop column of plant `P` (..., bins, rows, loops): ``P_R u / u_d``."""
        u = closed(P[..., list(fb.inner), :], K)[..., 0]
        return np.einsum("...rl,...l->...r", P[..., : self.z.shape[1], :], u) / u[..., :1]

    def delta(self, w: NDArray[np.float64], q: float) -> NDArray[np.complex128]:
        """The whitened change of every element at the bins, the mode at each of `w`
        (rad/s), `q`, at the fitted calibrations: (trials, bins, readbacks, drives)."""
        s, w = self.s[None], np.asarray(w, dtype=float)[:, None]
        d0 = 1 / (s * s + s * w / q + w * w) - 1 / (s * s + s * self.w0 / self.q0 + self.w0**2)
        d1 = s * d0
        out = d1[..., None, None] * self.open[0] + d0[..., None, None] * self.open[1]
        for j, (fb, P, K, T) in self.closed.items():
            k_num = fb.modal.num_s[self.k], fb.modal.num_1[self.k]
            moved = P + d1[..., None, None] * k_num[0] + d0[..., None, None] * k_num[1]
            out[..., j] = self._column(fb, moved, K) - T
        return self.G * out

    def drop(self, c: NDArray[np.complex128]) -> NDArray[np.float64]:
        """The drop in chi^2 each trial's whitened change `c` makes (trials, bins, readbacks,
        drives), each free calibration refitted."""
        ax = (1, 3)
        fixed = 2 * np.sum((np.conj(self.z) * c).real, axis=ax) - np.sum(np.abs(c) ** 2, axis=ax)
        dm = c / self.g[:, None]
        md = self.md + np.sum((np.conj(dm) * self.d).real, axis=ax)
        mm = self.mm + np.sum(2 * (np.conj(self.m) * dm).real + np.abs(dm) ** 2, axis=ax)
        # chi^2 at the current calibration, less the best a refitted one reaches
        now = self.mm * self.g**2 - 2 * self.g * self.md
        best = -np.divide(md**2, mm, out=np.zeros_like(mm), where=mm > 0)
        return np.sum(np.where(self.free, now - best, fixed), axis=1)

    def sweep(self, trials: NDArray[np.float64], q: float) -> tuple[NDArray[np.float64], float]:
        """Each trial's drop in chi^2 (the mode at each of `trials`, Hz, at `q`) and the
        sweep's path."""
        drops, path, last = [], 0.0, None
        for chunk in np.array_split(trials, max(1, trials.size // _CLOSED_CHUNK)):
            c = self.delta(2 * math.pi * chunk, q)
            drops.append(self.drop(c))
            c = c.reshape(chunk.size, -1)
            both = c if last is None else np.vstack([last, c])
            dot = np.sum((np.conj(both[:-1]) * both[1:]).real, axis=1)
            norms = np.linalg.norm(both, axis=1)
            cos = dot / np.maximum(norms[:-1] * norms[1:], 1e-300)
            path += float(np.sum(np.arccos(np.clip(np.abs(cos), 0, 1))))
            last = c[-1:]
        return np.concatenate(drops), path


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
