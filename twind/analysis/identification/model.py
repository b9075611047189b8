"""The closed-loop model a fit evaluates: ``IN1/EXC = (I - P K)^-1 - I`` of the configured
optic, averaged over the estimator's window, with an effect of the catalogue if asked."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.analysis.estimation.tf import Kernel
from twind.analysis.identification.data import FitData
from twind.analysis.identification.params import FIT_PARAMS, with_params
from twind.config import OpticConfig
from twind.loop.damping import sensitivity
from twind.model.effects import MODE_SEARCH, mode_bands, with_effect
from twind.model.params import SOSParams
from twind.model.plant import Plant


NARROW_REACH_BINS = 6
"""Bins either side of a narrow mode averaged over the Hann kernel itself (beyond, the mode
is smooth over the kernel, and its two-point rule errs by (1/6)^4 of the mode's tail)."""


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
        self._narrow: tuple[NDArray, NDArray, NDArray, NDArray] | None = None

    @functools.cached_property
    def _k(self) -> NDArray[np.complex128]:
        # when first needed: a model made only to be cut down to a measurement's bins
        # (for_data) would otherwise evaluate the filters at every bin up to Nyquist
        return self.cfg.loop().controller(self._at)

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
        plant = Plant.from_params(sus, replace(self.cfg, sus=sus).mechanics())
        if self.effect:
            plant = with_effect(plant, sus, self.effect,
                                {k: v for k, v in values.items() if k not in FIT_PARAMS})
        return self.response(plant)

    def response(self, plant: Plant) -> NDArray[np.complex128]:
        """``IN1/EXC`` of the configured loop around any `plant`, shape (len(f), 4, 4)."""
        T = self._averaged(_closed_loop(plant.response(self._at), self._k))
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
        d, w = hann_kernel(self.resolution_hz, width)
        at = (self.f[near, None] + self.resolution_hz * d).ravel()
        k = self.cfg.loop().controller(at)
        fine = _closed_loop(plant.response(at), k).reshape(near.size, d.size, *T.shape[1:])
        T = T.copy()
        T[near] = np.einsum("k,fkij->fij", w, fine)
        return T

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
        bins, at, weights, k = self._narrow
        mech = plant.mechanics
        modes = [math.sqrt(mech.K[i, i] / mech.M[i, i]) / (2 * math.pi)
                 for i, d in enumerate(mech.dofs) if d in ("VERT", "ROLL")]
        # further out a mode is smooth over the kernel and the two-point rule holds
        near = np.flatnonzero(np.min(np.abs(self.f[bins, None] - np.array(modes)), axis=1)
                              < NARROW_REACH_BINS * self.resolution_hz)
        if near.size:
            at = at.reshape(bins.size, weights.size)[near].ravel()
            k = k.reshape(bins.size, weights.size, *k.shape[1:])[near].reshape(-1, *k.shape[1:])
            fine = _closed_loop(plant.response(at), k).reshape(near.size, weights.size,
                                                              *T.shape[1:])
            T = T.copy()
            T[bins[near]] = np.einsum("k,fkij->fij", weights, fine)
        return T

    def _narrow_grid(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Bins where a narrow mode may lie, their Hann-kernel frequencies and weights, and
        the controller there."""
        sus = self.cfg.sus
        near = np.zeros(self.f.size, dtype=bool)
        for lo, hi in mode_bands(sus, NARROW_REACH_BINS * self.resolution_hz):
            near |= (self.f > lo) & (self.f < hi)
        bins = np.flatnonzero(near)
        nominal = sus.uncoupled_frequencies_hz()
        width = min(lo * nominal[dof] / sus.Q[dof] for dof, lo, _ in MODE_SEARCH.values())
        d, w = hann_kernel(self.resolution_hz, width)
        at = (self.f[bins, None] + self.resolution_hz * d).ravel()
        k = self.cfg.loop().controller(at)
        return bins, at, w, k

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
    feature `width_hz` wide (a quarter of it, 1/16 to 1/4 bin).

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
    step = float(np.clip(0.25 * width_hz / resolution_hz, 1 / 16, 1 / 4))
    d = np.linspace(-3.0, 3.0, 2 * round(3 / step) + 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(np.abs(np.abs(d) - 1) < 1e-9, 0.5, np.sinc(d) / (1 - d**2)) ** 2
    return d, w / w.sum()


def _closed_loop(P: NDArray[np.complex128], k: NDArray[np.complex128]
                 ) -> NDArray[np.complex128]:
    """``IN1/EXC`` from the plant and the controller's diagonal at the same frequencies."""
    return sensitivity(P, k) - np.eye(len(DOFS))
