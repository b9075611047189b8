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
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind.analysis.identification.data import FitData
from twind.analysis.identification.model import NARROW_REACH_BINS
from twind.analysis.identification.narrow import SEARCH_Q
from twind.analysis.statespace.model import PlantModel, closed_first

SHIFT = 2.0
"""A model mode is looked for from its frequency over this factor to its frequency times it
(within the coherent band): a real suspension's mode may sit 60 % off its model's."""

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


WINDOW = 1.3
"""A screen weighs a trial's mode over the bins within this factor of its frequency."""
MOST_AMPLITUDE = 5.0
"""A moved mode's amplitude at most this many times the model's, and at least its inverse."""


@dataclass(frozen=True)
class Profile:
    """A model mode screened over trial frequencies at several Qs
    (:meth:`Residuals.profile`).

    Attributes
    ----------
    f_hz : ndarray, shape (trials,)
    q : ndarray, shape (qs,)
    drop, amplitude : ndarray, shape (qs, trials)
        Each trial's drop in chi^2 (noise units) at each Q, and the amplitude (of the
        model's) it was reached with.
    paths : tuple of float
        Each Q's sweep's look-elsewhere path (rad).
    """

    f_hz: NDArray[np.float64]
    q: NDArray[np.float64]
    drop: NDArray[np.float64]
    amplitude: NDArray[np.float64]
    paths: tuple[float, ...]

    def best(self, near: NDArray[np.bool_], qs: NDArray[np.bool_]) -> tuple[int, int]:
        """The (Q, trial) of the largest drop among the trials `near` and the Qs `qs`."""
        d = np.where(qs[:, None] & near[None, :], self.drop, -np.inf)
        j, i = np.unravel_index(int(np.argmax(d)), d.shape)
        return int(j), int(i)


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
    def profile(self, k: int, unit: float, trials: NDArray[np.float64]) -> Profile:
        """Mode `k` moved to each of the frequencies `trials` (Hz, ascending) at each of
        :data:`~twind.analysis.identification.narrow.SEARCH_Q` and as narrow as the data
        resolve (:data:`FINE_Q`, or its own Q if lower): each trial's best drop in chi^2 (in
        units of `unit`), its Q and amplitude, and every sweep's path.

        Open loop, the mode's amplitude is refitted at each trial (between 0 and
        :data:`MOST_AMPLITUDE` of the model's): a calibration or a modal mass a little off
        leaves its place where it is. In a closed loop with other loops closed, each trial's
        change is the whole closed loop's (:class:`_ClosedChange`, its amplitude the
        model's): the other loops damp and move a mode they see."""
        m = self.model.modal
        qs = [*SEARCH_Q, *([min(FINE_Q, m.q[k])] if m.q[k] > SEARCH_Q[-1] else [])]
        if self.model.feedback:
            change = _ClosedChange(self, k)
            sweeps = [(*change.sweep(trials, q), np.ones(trials.size)) for q in qs]
        else:
            sweeps = [self._free_sweep(k, trials, q) for q in qs]
        return Profile(trials, np.asarray(qs), np.array([x[0] for x in sweeps]) / unit,
                       np.array([x[2] for x in sweeps]), tuple(x[1] for x in sweeps))

    def _free_sweep(self, k: int, trials: NDArray[np.float64], q: float
                    ) -> tuple[NDArray[np.float64], float, NDArray[np.float64]]:
        """Each trial's drop in chi^2 for mode `k` moved to the frequencies `trials` at `q`,
        its amplitude refitted (:meth:`profile`); the sweep's path; the amplitudes. A run of
        neighbouring trials is weighed over the bins within :data:`WINDOW` of it and of the
        mode's own frequency, the mode removed and put back there alone: beyond, the change
        is a smooth tail (below both places, a change of the static compliance, which the
        calibrations take up) that the full fit of the change weighs. So a run costs its own
        stretch of bins, not the whole band."""
        A, B = self.model.numerators(k)
        GA, GB = self.G * A, self.G * B
        q0, q1 = self.model.kernels(self.model.modal.w[k], self.model.modal.q[k])
        u = self.z + q1[:, None, None] * GA + q0[:, None, None] * GB  # the mode removed
        sums = _Sums(u, GA, GB)
        z2, u2 = (np.sum(np.abs(x) ** 2, axis=(1, 2)) for x in (self.z, u))
        f0 = self.model.modal.w[k] / (2 * math.pi)
        drops, amps, path = [], [], 0.0
        for run in _runs(trials, q, self.model.res):
            at = self._window(np.array([min(run[0], f0), max(run[-1], f0)]))
            part, last = sums.window(at), None
            const = float(np.sum(z2[at]) - np.sum(u2[at]))
            for chunk in np.array_split(run, max(1, run.size // _CHUNK)):
                d0, d1 = self.model.kernels_many(2 * math.pi * chunk, q, at)
                proj, norm = part.project(d0, d1), part.norm2(d0, d1)
                a = np.clip(np.divide(proj, norm, out=np.zeros_like(proj), where=norm > 0),
                            0.0, MOST_AMPLITUDE)
                drops.append(const + 2 * a * proj - a * a * norm)
                amps.append(a)
                if last is not None:
                    d0, d1 = np.vstack([last[0], d0]), np.vstack([last[1], d1])
                path += part.path(d0, d1)
                last = (d0[-1:], d1[-1:])
        return np.concatenate(drops), path, np.concatenate(amps)

    def _window(self, run: NDArray[np.float64]) -> slice:
        """The bins within :data:`WINDOW` of a run of trial frequencies (at least
        :data:`~twind.analysis.identification.model.NARROW_REACH_BINS` either side)."""
        f = self.model.f
        lo = np.searchsorted(f, run[0] / WINDOW) - NARROW_REACH_BINS
        hi = np.searchsorted(f, run[-1] * WINDOW) + NARROW_REACH_BINS
        return slice(max(int(lo), 0), min(int(hi), f.size))

    # ---------------------------------------------------------------- a mode in no model
    def resonance(self, unit: float, trials: NDArray[np.float64]) -> Sweep:
        """A mode with a real numerator per element at each of the frequencies `trials` (Hz,
        ascending) at each of :data:`~twind.analysis.identification.narrow.SEARCH_Q`, each
        weighed over the bins within :data:`WINDOW` of it: the best, its numerators and each
        sweep's path over the trials."""
        Gz = (np.conj(self.z) * self.G).reshape(self.z.shape[0], -1)  # (nf, elements)
        G2 = (np.abs(self.G) ** 2).reshape(self.z.shape[0], -1)
        best, paths = (-np.inf, float(trials[0]) if trials.size else 1.0, SEARCH_Q[0], None), []
        for q in SEARCH_Q:
            path = 0.0
            for run in _runs(trials, q, self.model.res):
                at, last = self._window(run), None
                for chunk in np.array_split(run, max(1, run.size // _CHUNK)):
                    q0, _ = self.model.kernels_many(2 * math.pi * chunk, q, at)
                    proj = (q0 @ Gz[at]).real  # (trials, elements)
                    norm = np.abs(q0) ** 2 @ G2[at]
                    with np.errstate(divide="ignore", invalid="ignore"):
                        drop = np.where(norm > 0, proj**2 / norm, 0.0).sum(axis=1)
                        coef = np.where(norm > 0, proj / norm, 0.0)
                    i = int(np.argmax(drop))
                    if drop[i] > best[0]:
                        best = (float(drop[i]), float(chunk[i]), q, coef[i])
                    # the angle the stacked signature turns between neighbouring trials
                    both = q0 if last is None else np.vstack([last, q0])
                    cross = (np.conj(both[:-1]) * both[1:]).real @ G2[at]
                    n2 = np.abs(both) ** 2 @ G2[at]
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
        u = closed_first(P[..., list(fb.inner), :], K)
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

    def window(self, at: slice) -> _Sums:
        """The sums at the bins `at` alone."""
        part = object.__new__(_Sums)
        for name in ("U1", "U0", "V11", "V00", "V10"):
            setattr(part, name, getattr(self, name)[at])
        return part

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


def _runs(trials: NDArray[np.float64], q: float, res: float) -> list[NDArray[np.float64]]:
    """`trials` split where neighbours lie more than two steps of :func:`grid` apart."""
    if trials.size < 2:
        return [trials] if trials.size else []
    step = 0.25 * np.maximum(res, trials[:-1] / q)
    cut = np.flatnonzero(np.diff(trials) > 2 * step) + 1
    return np.split(trials, cut)


def grid(lo: float, hi: float, q: float, res: float) -> NDArray[np.float64]:
    """A search's trial frequencies from `lo` to `hi` in steps of a quarter of a bin or of
    the width."""
    out, f = [], lo
    while f <= hi:
        out.append(f)
        f += 0.25 * max(res, f / q)
    return np.array(out)
