"""The closed-loop model a fit evaluates: ``IN1/EXC = (I - P K)^-1 - I`` of the configured
optic, averaged over the estimator's window, with an effect of the catalogue if asked."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.analysis.estimation.tfset import Kernel
from twind.analysis.identification.data import FitData
from twind.analysis.identification.params import FIT_PARAMS, with_params
from twind.config import OpticConfig
from twind.loop.damping import sensitivity
from twind.model.effects import MODE_SEARCH, mode_bands, with_effect
from twind.model.params import SOSParams
from twind.model.plant import Plant


NARROW_REACH_BINS = 6
"""Bins either side of a narrow mode averaged over the Hann kernel itself (beyond, the mode
is smooth over the kernel, and its two-point rule errs by (1/6)^4 of the mode's tail); and
the reach, in bins of complex distance ``|f - f0 - i f0/2Q|``, within which a damped mode of
the closed loop is averaged so."""


class ClosedLoopModel:
    """``IN1/EXC`` (all four DOFs) of an optic's damping loop as a function of its fit
    parameters, at fixed frequencies, as a spectral estimate of resolution `resolution_hz`
    or with `kernel` sees it.

    A Hann-windowed Welch estimate is the true TF averaged over the window's power kernel,
    whose second moment is 1/3 bin^2: to second order it is the mean of the TF half a
    kernel width either side, ``f +- resolution / sqrt(3)``.  Near the closed-loop
    resonances (a few bins wide at 0.04 Hz) leaving this out biases the fitted Qs by
    several sigma; periodic excitations analysed with a rectangular window need none.
    An LPM estimate's kernel is exact: the columns of the `excited` DOFs are its weighted
    sums of the TF over each window.
    Near the damped modes of the closed loop (Q about 5) the expansion fails as the
    resolution coarsens: bins within :data:`NARROW_REACH_BINS` of them are averaged over the
    Hann power kernel itself (the two-point rule errs there by up to 0.4, 1.1 and 2.5 sigma
    of a nominal ETMX's 10-average estimate at 0.05, 0.1 and 0.25 Hz).
    A plant with VERT and ROLL modes (Q 1000: narrower than a bin) is averaged over the Hann
    power kernel itself (:func:`hann_kernel`) within :data:`NARROW_REACH_BINS` of them: there
    a bin's estimate is the mode's area under the kernel, which the two-point rule misses.
    """

    def __init__(self, cfg: OpticConfig, f_hz: NDArray[np.float64],
                 resolution_hz: float = 0.0, effect: str | None = None,
                 kernel: Kernel | None = None, excited: Sequence[str] = ()) -> None:
        self.cfg, self.effect = cfg, effect
        self.f = np.asarray(f_hz, dtype=float)
        self.kernel, self.excited = kernel, list(excited)
        a = resolution_hz / math.sqrt(3.0)
        if kernel is not None:
            self._at = (self.f[:, None] + kernel.offsets_hz).ravel()
        else:
            self._at = np.concatenate([self.f - a, self.f + a]) if a > 0 else self.f
        self.resolution_hz = resolution_hz
        self._narrow: KernelGrid | None = None

    @functools.cached_property
    def damped(self) -> KernelGrid | None:
        """Bins within :data:`NARROW_REACH_BINS` of a damped mode of the configured closed
        loop, averaged over the Hann power kernel (a fit moves the modes by a small part of
        that reach); None for an LPM's kernel, at zero resolution or with no bin so near."""
        if self.kernel is not None or self.resolution_hz <= 0:
            return None
        modes = np.array(self.cfg.closed_loop_modes)
        if not modes.size:
            return None
        half = modes[:, 0] / (2 * modes[:, 1])
        reach = np.min(np.hypot(self.f[:, None] - modes[:, 0], half), axis=1)
        bins = np.flatnonzero(reach < NARROW_REACH_BINS * self.resolution_hz)
        return self._grid(bins, 2 * float(half.min())) if bins.size else None

    @functools.cached_property
    def _points(self) -> NDArray[np.float64]:
        """Every frequency a response is taken at: the estimator's, then the damped modes'."""
        return self._at if self.damped is None else np.concatenate([self._at,
                                                                     self.damped.points])

    @functools.cached_property
    def _k(self) -> NDArray[np.complex128]:
        # when first needed: a model made only to be cut down to a measurement's bins
        # (for_data) would otherwise evaluate the filters at every bin up to Nyquist
        return self.cfg.loop().controller(self._points)

    @classmethod
    def of(cls, cfg: OpticConfig, data: FitData, effect: str | None = None) -> ClosedLoopModel:
        """The model at `data`'s frequencies, as its estimator sees the TF.

        Parameters
        ----------
        cfg : OpticConfig
            The optic and its damping loop.
        data : FitData
            The measured bins (their frequencies, resolution, kernel and excited DOFs).
        effect : str, optional
            A catalogue entry (or combination) the model holds.

        Returns
        -------
        ClosedLoopModel
        """
        return cls(cfg, data.frequency_hz, data.resolution_hz, effect, data.kernel,
                   data.excited)

    def sus(self, values: Mapping[str, float]) -> SOSParams:
        """The configured suspension with the nominal parameters of `values` set."""
        return with_params(self.cfg.sus, {k: v for k, v in values.items() if k in FIT_PARAMS})

    def __call__(self, values: Mapping[str, float]) -> NDArray[np.complex128]:
        """``IN1/EXC``, shape (len(f), 4, 4); `values` may hold the effect's parameters."""
        sus = self.sus(values)
        plant = self.cfg.plant(sus)
        if self.effect:
            plant = with_effect(plant, sus, self.effect,
                                {k: v for k, v in values.items() if k not in FIT_PARAMS})
        return self.response(plant)

    def response(self, plant: Plant) -> NDArray[np.complex128]:
        """``IN1/EXC`` of the configured loop around any `plant`, shape (len(f), 4, 4)."""
        closed = _closed_loop(plant.response(self._points), self._k)
        T = self._averaged(closed[: self._at.size])
        if self.damped is not None:
            T = self.damped.put(T, closed[self._at.size :])
        if self.kernel is None and self.resolution_hz > 0 and {"VERT", "ROLL"} & set(
                plant.mechanics.dofs):
            T = self._with_narrow(plant, T)
        if self.kernel is None and self.resolution_hz > 0:
            for body in (d for d in plant.mechanics.dofs if d.startswith("BODY")):
                T = self._with_body(plant, body, T)
        return T

    def _with_body(self, plant: Plant, body: str, T: NDArray[np.complex128]
                   ) -> NDArray[np.complex128]:
        """A ``resonance`` `body` narrower than two bins, averaged over the Hann power
        kernel within :data:`NARROW_REACH_BINS` of it (its coordinate has unit mass)."""
        mech = plant.mechanics
        i = mech.index(body)
        f0, width = math.sqrt(mech.K[i, i]) / (2 * math.pi), mech.C[i, i] / (2 * math.pi)
        near = np.flatnonzero(np.abs(self.f - f0) < NARROW_REACH_BINS * self.resolution_hz)
        if width >= 2 * self.resolution_hz or not near.size:
            return T
        return self._grid(near, width).average(plant, T)

    def _averaged(self, T: NDArray[np.complex128]) -> NDArray[np.complex128]:
        if self.kernel is not None:
            T = T.reshape(self.f.size, self.kernel.offsets_hz.size, len(DOFS), len(DOFS))
            out = T[:, self.kernel.offsets_hz.size // 2].copy()  # the centre: not excited
            for j, d in enumerate(self.excited):
                m = DOFS.index(d)
                out[:, :, m] = np.einsum("fr,fri->fi", self.kernel.weights[:, :, j],
                                         T[:, :, :, m])
            return out
        return 0.5 * (T[: self.f.size] + T[self.f.size :]) if self._at is not self.f else T

    def _with_narrow(self, plant: Plant, T: NDArray[np.complex128]) -> NDArray[np.complex128]:
        if self._narrow is None:
            self._narrow = self._narrow_grid()
        mech = plant.mechanics
        modes = [math.sqrt(mech.K[i, i] / mech.M[i, i]) / (2 * math.pi)
                 for i, d in enumerate(mech.dofs) if d in ("VERT", "ROLL")]
        # further out a mode is smooth over the kernel and the two-point rule holds
        near = (np.min(np.abs(self.f[self._narrow.bins, None] - np.array(modes)), axis=1)
                < NARROW_REACH_BINS * self.resolution_hz)
        return self._narrow.average(plant, T, near) if near.any() else T

    def _narrow_grid(self) -> KernelGrid:
        """Bins where a narrow mode may lie."""
        sus = self.cfg.sus
        near = np.zeros(self.f.size, dtype=bool)
        for lo, hi in mode_bands(sus, NARROW_REACH_BINS * self.resolution_hz):
            near |= (self.f > lo) & (self.f < hi)
        nominal = sus.uncoupled_frequencies_hz()
        width = min(lo * nominal[dof] / sus.Q[dof] for dof, lo, _ in MODE_SEARCH.values())
        return self._grid(np.flatnonzero(near), width)

    def _grid(self, bins: NDArray[np.intp], width_hz: float) -> KernelGrid:
        """The Hann power kernel about each of `bins`, fine enough for `width_hz`."""
        d, w = hann_kernel(self.resolution_hz, width_hz)
        at = (self.f[bins, None] + self.resolution_hz * d).round(9)
        # neighbouring bins' kernels share most of their frequencies: each is taken once
        points, inverse = np.unique(at, return_inverse=True)
        return KernelGrid(bins, points, inverse.reshape(at.shape), w,
                           self.cfg.loop().controller(points))

    def for_data(self, data: FitData) -> Callable[[Mapping[str, float]], NDArray]:
        """The model shaped like `data` (its responses and excited DOFs; zeros in unused
        bins), evaluated only at the frequencies `data` uses."""
        keep = data.mask.any(axis=(1, 2))
        kernel = (Kernel(self.kernel.offsets_hz, self.kernel.weights[keep])
                  if self.kernel is not None else None)
        sub = ClosedLoopModel(self.cfg, self.f[keep], self.resolution_hz, self.effect,
                              kernel, self.excited)
        rows = [DOFS.index(d) for d in data.responses]
        cols = [DOFS.index(d) for d in data.excited]

        def predict(values: Mapping[str, float]) -> NDArray[np.complex128]:
            out = np.zeros(data.H.shape, dtype=complex)
            out[keep] = sub(values)[:, rows][:, :, cols]
            return out

        return predict


def hann_kernel(resolution_hz: float, width_hz: float
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Offsets (bins) and weights of a Hann-windowed estimate's power kernel,
    ``(sinc d / (1 - d^2))^2`` out to 3 bins (99.99 % of it), sampled finely enough for a
    feature `width_hz` wide (a quarter of it or finer, 1/16 to 1/4 bin, a whole fraction of a
    bin so that neighbouring bins' kernels share their frequencies).

    Parameters
    ----------
    resolution_hz : float
        The estimate's bin width (Hz).
    width_hz : float
        The narrowest feature to resolve (Hz): a mode's full width.

    Returns
    -------
    offsets : ndarray
        In bins, from -3 to 3.
    weights : ndarray
        Summing to 1.
    """
    per_bin = math.ceil(1 / np.clip(0.25 * width_hz / resolution_hz, 1 / 16, 1 / 4))
    d = np.arange(-3 * per_bin, 3 * per_bin + 1) / per_bin  # whole bins fall on it
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(np.abs(np.abs(d) - 1) < 1e-9, 0.5, np.sinc(d) / (1 - d**2)) ** 2
    return d, w / w.sum()


@dataclass(frozen=True)
class KernelGrid:
    """Bins of a Hann-windowed estimate averaged over its power kernel: their indices, the
    frequencies their kernels reach (each once), where each bin's kernel lies among them,
    the kernel's weights and the controller at those frequencies."""

    bins: NDArray[np.intp]
    points: NDArray[np.float64]
    inverse: NDArray[np.intp]
    weights: NDArray[np.float64]
    k: NDArray[np.complex128]

    def average(self, plant: Plant, T: NDArray[np.complex128],
                rows: NDArray[np.bool_] | None = None) -> NDArray[np.complex128]:
        """`T` with its `bins` (those of `rows`) replaced by `plant`'s closed loop averaged
        over the kernel."""
        if rows is None:
            return self.put(T, _closed_loop(plant.response(self.points), self.k))
        used, where = np.unique(self.inverse[rows], return_inverse=True)
        closed = _closed_loop(plant.response(self.points[used]), self.k[used])
        T = T.copy()
        T[self.bins[rows]] = np.einsum("k,fkij->fij", self.weights,
                                       closed[where.reshape(rows.sum(), -1)])
        return T

    def put(self, T: NDArray[np.complex128], closed: NDArray[np.complex128]
            ) -> NDArray[np.complex128]:
        """`T` with its `bins` replaced by the kernel's average of `closed`, the closed
        loop at :attr:`points`."""
        T = T.copy()
        T[self.bins] = np.einsum("k,fkij->fij", self.weights, closed[self.inverse])
        return T


def _closed_loop(P: NDArray[np.complex128], k: NDArray[np.complex128]
                 ) -> NDArray[np.complex128]:
    """``IN1/EXC`` from the plant and the controller's diagonal at the same frequencies."""
    return sensitivity(P, k) - np.eye(len(DOFS))
