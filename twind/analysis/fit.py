"""Fit an optic's nominal physical parameters to its measured closed-loop transfer functions.

The data are the ``IN1/EXC`` columns of the excited DOFs, each bin weighted by its
Bendat-Piersol error (a local-polynomial estimate by its own); the model is docs/model.md's
``IN1/EXC = (I - P K)^-1 - I`` with the optic's configured mechanics (analytical or
geometric) and controller. ``IN1/EXC`` is fitted rather than the recovered plant because its
errors are those of one estimate, while the plant's mix the correlated errors of IN1 and OUT;
``OUT/EXC = K IN2/EXC`` holds no further information.

Parameters are fitted in ``log(p / p_nominal)`` so every one is positive and the Fisher matrix
compares relative changes. What the data cannot fix (a singular value of the whitened
Jacobian whose direction would have a log-sigma above :data:`MAX_LOG_SIGMA`) is named
unidentifiable, is held at its nominal value and gets no sigma; the fit runs in the remaining
subspace, so no input can make it invert a singular matrix.

Uncertainties are the Cramer-Rao bound of that weighted least squares, with two corrections
taken from the residuals rather than trusted from the coherence: the scatter (a median-based
noise scale ``s``, robust to the heavy tails of errors divided by an estimated coherence) and
the correlation of neighbouring frequency bins (a Hann window correlates the errors of
adjacent bins, so ``n`` bins carry less than ``n`` bins' information). Both enter as a
sandwich covariance ``s^2 A^+ (J^T R J) A^+`` with ``A = J^T J`` and ``R`` the banded bin
correlation.  ``twind bench --suite pull`` checks the result on the twin.

The responses of one optic to one excitation share their noise: around the 40m's POS
resonance the POS and PIT readbacks' noises correlate at 0.99, and residuals taken as
independent count that noise twice. A local-polynomial estimate measures that correlation,
and its residuals are whitened across the responses of each bin with it; a Welch estimate's
coherences do not give it, and its residuals are whitened bin by bin.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.optimize import least_squares

from twind import DOFS, progress
from twind.analysis.tf import Kernel, TFSet
from twind.config import OpticConfig
from twind.errors import TwindError
from twind.loop.damping import sensitivity
from twind.model.plant import Plant
from twind.model.effects import (
    MODE_SEARCH,
    EffectError,
    effect_params,
    effect_scale,
    mode_bands,
    with_effect,
)
from twind.model.params import SOSParams

FIT_PARAMS = ("wire_length_m", "b_m", "R1_m", "coil_N_per_ct", "osem_lever_m",
              "Q_POS", "Q_PIT", "Q_YAW", "Q_SIDE")
MAX_LOG_SIGMA = 1.0
"""A direction of log-parameter space known worse than a factor e is unidentifiable."""
MIN_COHERENCE = 0.5
"""Below this the Bendat-Piersol error (and the estimate's bias) is no longer trustworthy."""
SURE_COHERENCE = 0.95
"""A bin at least this coherent is used whatever its neighbours (a multisine's tone)."""
SMOOTH_BINS = 11
"""Bins chosen by the coherence averaged over this many neighbours."""
CORRELATION_LAGS = 3
"""Neighbouring bins whose error correlation is estimated (Hann: lag 1 dominates)."""
ROUND_EVALUATIONS = 30
"""Residual evaluations per fitted direction in one round of the fit (scipy's default is
100): a well-posed fit converges in a few, a direction the data leave free only runs away."""
_NULL_COMPONENT = 0.05
NARROW_REACH_BINS = 6
"""Bins either side of a narrow mode averaged over the Hann kernel itself (beyond, the mode
is smooth over the kernel, and its two-point rule errs by (1/6)^4 of the mode's tail)."""
_STEP = 1e-4  # log-parameter step of the finite-difference Jacobian


class FitError(TwindError):
    """Parameters cannot be fitted to these measurements."""


# ------------------------------------------------------------------------------ parameters
def param_value(sus: SOSParams, name: str) -> float:
    """The value of fit parameter `name` (``Q_<DOF>`` reads ``sus.Q``)."""
    if name.startswith("Q_"):
        return float(sus.Q[name[2:]])
    return float(getattr(sus, name))


def read_truth(path: str | Path) -> dict[str, float]:
    """Fit-parameter values of a ``truth.json`` (``drifted_params``, Q per DOF), as
    ``tests/data/example_null`` holds them for its simulated optic."""
    try:
        given = json.loads(Path(path).read_text())
        given = given.get("drifted_params", given)
        q = given.get("Q", {})
        return {**{n: float(given[n]) for n in FIT_PARAMS if n in given},
                **{f"Q_{d}": float(v) for d, v in q.items() if f"Q_{d}" in FIT_PARAMS}}
    except (OSError, ValueError, AttributeError, TypeError) as err:
        msg = f"{path}: not a truth file of parameter values ({err})"
        raise FitError(msg) from None


def with_params(sus: SOSParams, values: Mapping[str, float]) -> SOSParams:
    """A copy of `sus` with fit parameters set (``Q_POS`` etc. go into ``Q``)."""
    return sus.updated(**values)


def check_names(names: Sequence[str]) -> list[str]:
    """`names` if every one is a fit parameter; else a FitError listing the valid ones."""
    unknown = [n for n in names if n not in FIT_PARAMS]
    if unknown or not names:
        msg = (f"unknown fit parameter(s) {unknown}; choose from {', '.join(FIT_PARAMS)}"
               if unknown else "no parameter to fit")
        raise FitError(msg)
    return list(dict.fromkeys(names))


# ------------------------------------------------------------------------------ data and model
@dataclass(frozen=True)
class FitData:
    """Measured ``IN1/EXC`` bins a fit uses, with their errors.

    Attributes
    ----------
    frequency_hz : ndarray, shape (nf,)
    rows, cols : list of int
        Model indices (into POS, PIT, YAW, SIDE) of the responses and excited DOFs.
    H, sigma : ndarray, shape (nf, nr, ne)
        Measured ``IN1/EXC`` and the standard error of its real and imaginary parts.
    mask : ndarray of bool, shape (nf, nr, ne)
        Bins used: coherent enough, finite, inside the band.
    averages : int
    resolution_hz : float
        Bin width of a Hann-windowed estimate (0 for a rectangular window).
    kernel : Kernel, optional
        What each estimate sees of the true response, when not the response at its bin (LPM).
    correlation : ndarray of complex, shape (nf, nr, nr, ne), optional
        Correlation of the errors of one bin's responses to one excitation (LPM); the
        residuals are whitened with it, otherwise bin by bin.
    """

    frequency_hz: NDArray[np.float64]
    responses: list[str]
    excited: list[str]
    H: NDArray[np.complex128]
    sigma: NDArray[np.float64]
    mask: NDArray[np.bool_]
    averages: int
    resolution_hz: float = 0.0
    kernel: Kernel | None = None
    correlation: NDArray[np.complex128] | None = None

    @classmethod
    def from_tfset(cls, tfs: TFSet, min_coherence: float = MIN_COHERENCE,
                   band: tuple[float, float] | None = None,
                   whole: Sequence[tuple[float, float]] = ()) -> FitData:
        """The bins of `tfs` worth fitting; a FitError when none is.

        Those whose neighbour-averaged coherence reaches `min_coherence` (or whose own
        reaches :data:`SURE_COHERENCE`); with `min_coherence` <= 0, every response at the
        frequencies where the excited DOF's own response is coherent (``twind diagnose``).
        In the bands `whole` (Hz) every bin is used, coherent or not: chosen by frequency
        alone, their errors are not biased by the choice (where a narrow mode may lie).
        """
        f = tfs.frequency_hz
        H, sigma = tfs.tf["IN1"], tfs.sigma("IN1")
        g2 = tfs.coherence["IN1"]
        # a bin this coherent on its own is no fluke (P < 1e-5 from zero coherence with 5
        # averages): it keeps the tones of a sparse multisine, which smoothing would dilute
        coherent = (_smoothed(g2) >= min_coherence) | (g2 >= max(SURE_COHERENCE, min_coherence))
        if min_coherence <= 0:
            # every response where the excitation reached the optic (its own DOF coherent):
            # the incoherent elements there carry the noise's errors, and together they
            # show a coupling too small to lift one bin out of the noise
            own = [tfs.responses.index(d) for d in tfs.excited]
            driven = _smoothed(g2[:, own, range(len(own))]) >= MIN_COHERENCE
            coherent = np.broadcast_to(driven[:, None, :], g2.shape)
        for lo, hi in whole:
            coherent = coherent | ((f >= lo) & (f <= hi))[:, None, None]
        mask = coherent & np.isfinite(H) & (sigma > 0)
        mask &= (f > 0)[:, None, None]
        if band is not None:
            mask &= ((f >= band[0]) & (f <= band[1]))[:, None, None]
        if not mask.any():
            msg = (f"no bin of {tfs.optic}'s IN1/EXC reaches coherence "
                   f"{min_coherence if min_coherence > 0 else MIN_COHERENCE:g}"
                   + (f" in {band[0]:g}-{band[1]:g} Hz" if band else ""))
            raise FitError(msg)
        resolution = float(np.median(np.diff(f))) if tfs.window == "hann" and f.size > 1 else 0.0
        return cls(f, list(tfs.responses), list(tfs.excited), H, sigma, mask, tfs.averages,
                   resolution, tfs.kernel, tfs.in1_correlation)

    @property
    def bins(self) -> int:
        """Number of complex bins used."""
        return int(self.mask.sum())

    def span(self) -> FitData:
        """The same bins with the arrays cut to the frequencies from the first used bin to
        the last: a measurement up to Nyquist fitted below 30 Hz is evaluated, whitened and
        its neighbouring bins paired there alone."""
        used = np.flatnonzero(self.mask.any(axis=(1, 2)))
        cut = slice(int(used[0]), int(used[-1]) + 1)
        kernel = (None if self.kernel is None
                  else Kernel(self.kernel.offsets_hz, self.kernel.weights[cut]))
        return replace(self, frequency_hz=self.frequency_hz[cut], H=self.H[cut],
                       sigma=self.sigma[cut], mask=self.mask[cut], kernel=kernel,
                       correlation=None if self.correlation is None else self.correlation[cut])

    def whiten(self, model: NDArray[np.complex128]) -> NDArray[np.float64]:
        """``(H - model) / sigma`` over the used bins, real parts then imaginary parts;
        with a :attr:`correlation`, decorrelated across each bin's used responses."""
        if self.correlation is None:
            r = (self.H[self.mask] - model[self.mask]) / self.sigma[self.mask]
        else:
            r = np.where(self.mask, (self.H - model) / np.where(self.mask, self.sigma, 1), 0)
            r = np.einsum("feij,fje->fie", self._whitener, r)[self.mask]
        return np.concatenate([r.real, r.imag])

    def whitened_change(self, dT: NDArray[np.complex128], at: NDArray[np.int64]
                        ) -> NDArray[np.complex128]:
        """What a model change `dT` at bins `at` (sorted; shape (..., len(at), nr, ne))
        takes off :meth:`whiten`'s residuals there, as complex numbers: one per used entry,
        in the order whose real parts, then imaginary parts, :meth:`whiten` lists."""
        used = self.mask[at]
        if self.correlation is None:
            return dT[..., used] / self.sigma[at][used]
        r = np.where(used, dT / np.where(used, self.sigma[at], 1), 0)
        return np.einsum("feij,...fje->...fie", self._whitener[at], r)[..., used]

    @functools.cached_property
    def _whitener(self) -> NDArray[np.complex128]:
        """``L^-1`` per bin and excitation, (nf, ne, nr, nr), with ``L L^H`` the correlation
        of the used responses (zero rows and columns for the unused)."""
        nf, nr, ne = self.H.shape
        out = np.zeros((nf, ne, nr, nr), dtype=complex)
        used = np.moveaxis(self.mask, 2, 1)  # (nf, ne, nr)
        rho = np.moveaxis(self.correlation, 3, 1)  # (nf, ne, nr, nr)
        for pattern in {tuple(u) for u in used.reshape(-1, nr) if u.any()}:
            at = np.all(used == np.array(pattern), axis=2)
            rows = np.flatnonzero(pattern)
            c = rho[at][:, rows][:, :, rows]
            # eigenvalues floored, so that responses correlated to rounding (or a correlation
            # from elsewhere that lost definiteness) still whiten to finite residuals
            w, v = np.linalg.eigh(c)
            c = (v * np.clip(w, 1e-3, None)[:, None, :]) @ np.conj(np.swapaxes(v, 1, 2))
            block = np.linalg.inv(np.linalg.cholesky(c))
            sub = out[at]
            sub[:, rows[:, None], rows[None, :]] = block
            out[at] = sub
        return out


def _smoothed(coherence: NDArray[np.float64], bins: int = SMOOTH_BINS) -> NDArray[np.float64]:
    """Running mean over `bins` neighbouring frequencies.

    Bins are chosen by this, not by their own coherence: with few averages the estimate
    scatters upward, and choosing the bins that happen to look coherent picks exactly those
    whose error the coherence understates.
    """
    return ndimage.uniform_filter1d(coherence, bins, axis=0, mode="nearest")


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
        """The model at `data`'s frequencies, as its estimator sees the TF."""
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


# ------------------------------------------------------------------------------ result
@dataclass
class FitResult:
    """Fitted parameters with calibrated uncertainties.

    Attributes
    ----------
    names : list of str
    values : ndarray
        Fitted values (nominal for unidentifiable ones).
    sigma : ndarray
        One-sigma uncertainties; ``nan`` where unidentifiable.
    covariance : ndarray
        Of ``log(value)``; rows and columns of unidentifiable parameters are ``nan``.
    unidentifiable : list of str
        Parameters or combinations (``"coil_N_per_ct/osem_lever_m"``) the data cannot fix.
    determined : dict
        For each unidentifiable pair, the combination that is determined, ``{value, sigma}``.
    chi2, nu : float, int
        Weighted residual sum of squares and degrees of freedom.
    noise_scale : float
        How much the residuals' scatter (median-based) exceeds the coherence-based errors.
    bin_correlation : list of float
        Correlation of residuals 1, 2, 3 bins apart.
    null, determined_covariance : ndarray
        The unidentifiable coordinate directions (columns) and :attr:`covariance` before
        their rows are blanked, for :meth:`combination_covariance`.
    """

    optic: str
    names: list[str]
    values: NDArray[np.float64]
    sigma: NDArray[np.float64]
    covariance: NDArray[np.float64]
    unidentifiable: list[str]
    determined: dict[str, dict[str, float]]
    chi2: float
    nu: int
    noise_scale: float
    bin_correlation: list[float]
    bins: int
    nominal: NDArray[np.float64] = field(repr=False)
    effect: str | None = None
    min_coherence: float = MIN_COHERENCE  # of the bins fitted (FitData.from_tfset)
    null: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 0)), repr=False)
    determined_covariance: NDArray[np.float64] = field(
        default_factory=lambda: np.zeros((0, 0)), repr=False)

    @property
    def bic(self) -> float:
        """``chi2 + k ln(n)`` with ``k`` = :attr:`rank` over ``n`` real residuals."""
        return self.chi2 + self.rank * math.log(max(2 * self.bins, 1))

    @property
    def rank(self) -> int:
        """Parameter directions the data determined (a coil imbalance's four gains count
        two: their common mode is the coil strength's, their butterfly moves nothing)."""
        return 2 * self.bins - self.nu

    @property
    def chi2_nu(self) -> float:
        """Reduced chi-square of the fit."""
        return self.chi2 / max(self.nu, 1)

    def combination_covariance(self, combos: Sequence[Mapping[str, float]]
                               ) -> NDArray[np.float64]:
        """Covariance of the combinations ``sum w_n p_n`` over an effect's parameters (or
        ``sum w_n log p_n`` over nominal ones), one per mapping ``{name: w_n}`` of `combos`.

        Rows and columns are ``nan`` for a combination that leans on a direction the data
        cannot determine: an imbalance's pitch-like part of four face gains has a sigma, no
        single gain has.
        """
        scale = effect_scale(self.effect) if self.effect else {}
        W = np.array([[c.get(n, 0.0) * scale.get(n, 1.0) for n in self.names] for c in combos])
        cov = W @ self.determined_covariance @ W.T
        if self.null.size:
            leans = (np.linalg.norm(W @ self.null, axis=1)
                     > _NULL_COMPONENT * np.linalg.norm(W, axis=1))
            cov[leans, :] = np.nan
            cov[:, leans] = np.nan
        return cov

    def as_dict(self) -> dict[str, float]:
        """``{name: value}``."""
        return dict(zip(self.names, self.values.tolist(), strict=True))

    def identified(self) -> dict[str, float]:
        """``{name: value}`` of the parameters with a finite sigma (what to pass on)."""
        return {n: float(v) for n, v, s in zip(self.names, self.values, self.sigma,
                                               strict=True) if math.isfinite(s)}

    def to_json(self) -> dict:
        """The ``twind fit --json`` object (unidentifiable sigmas are null)."""
        params = {n: {"value": float(v), "sigma": None if math.isnan(s) else float(s),
                      "start": float(p0)}
                  for n, v, s, p0 in zip(self.names, self.values, self.sigma, self.nominal,
                                         strict=True)}
        return {"optic": self.optic, "effect": self.effect, "params": params,
                "unidentifiable": self.unidentifiable,
                "determined": self.determined, "chi2_nu": self.chi2_nu, "nu": self.nu,
                "noise_scale": self.noise_scale, "bin_correlation": self.bin_correlation,
                "bins": self.bins}

    def pulls(self, truth: Mapping[str, float]) -> str:
        """``name (fitted - truth) / sigma`` of the identified parameters `truth` gives."""
        return ", ".join(f"{n} {(v - truth[n]) / s:+.2f}" for n, v, s in
                         zip(self.names, self.values, self.sigma, strict=True)
                         if n in truth and math.isfinite(s))

    def lines(self) -> list[str]:
        """A human-readable table."""
        out = [f"{self.optic}: {self.bins} bins, chi2/nu = {self.chi2_nu:.3f} "
               f"(noise scale {self.noise_scale:.2f}, bin correlation "
               f"{', '.join(f'{c:+.2f}' for c in self.bin_correlation)})"]
        for n, v, s, p0 in zip(self.names, self.values, self.sigma, self.nominal, strict=True):
            if math.isnan(s):  # held at its start: no fitted value to show
                out.append(f"  {n:15s} {'':12s} {'unidentifiable, held':26s} start {p0:.6g}")
            else:
                out.append(f"  {n:15s} {v:12.6g} {f'+- {s:.4g} ({100 * s / v:.2g} %)':26s} "
                           f"start {p0:.6g}")
        for combo, d in self.determined.items():
            out.append(f"  determined: {combo} = {d['value']:.6g} +- {d['sigma']:.3g}")
        if self.unidentifiable:
            out.append(f"  unidentifiable: {', '.join(self.unidentifiable)}")
        return out


# ------------------------------------------------------------------------------ the fit
def fit(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, params: Sequence[str] = FIT_PARAMS,
        min_coherence: float = MIN_COHERENCE, band: tuple[float, float] | None = None,
        effect: str | None = None, effect_start: Mapping[str, float] | None = None,
        whole: Sequence[tuple[float, float]] = (), unfitted: Sequence[str] = ()
        ) -> FitResult:
    """Fit `params` of `cfg`'s optic to the measured transfer functions `tfs`.

    Parameters
    ----------
    tfs : TFSet or sequence of TFSet
        Closed-loop TFs (``twind tf``) of the optic; several measurements (rounds of a
        campaign) are fitted jointly.
    cfg : OpticConfig
        The optic's configuration: the fit starts from its values; model, controller.
    params : sequence of str
        Names from :data:`FIT_PARAMS`.
    min_coherence : float
        Bins of ``IN1/EXC`` below this coherence are not used.
    band : (float, float), optional
        Only bins in this band (Hz).
    effect : str, optional
        A catalogue entry (:data:`twind.model.effects.CATALOGUE`) fitted together with
        `params`, from zero (the nominal model); its parameters are fitted linearly.
    effect_start : mapping of str to float, optional
        Where the effect's parameters start instead (a narrow mode's frequency, which
        moves nothing at zero coupling, from :func:`twind.analysis.narrow.search`).
    whole : sequence of (float, float)
        Bands (Hz) fitted bin by bin whatever their coherence (:meth:`FitData.from_tfset`).
    unfitted : sequence of str
        Effect parameters held at zero (a coupling to a DOF the measurement does not excite).

    Returns
    -------
    FitResult
    """
    names = check_names(params)
    if effect is not None:
        try:
            names += [n for n in effect_params(effect) if n not in unfitted]
        except EffectError as e:
            raise FitError(str(e)) from None
    sets = [tfs] if isinstance(tfs, TFSet) else list(tfs)
    datas = [FitData.from_tfset(t, min_coherence, band, whole).span() for t in sets]
    models = [ClosedLoopModel.of(cfg, d, effect).for_data(d) for d in datas]
    coords = _Coords(names, cfg.sus, effect, effect_start or {})

    size = sum(2 * d.bins for d in datas)

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        progress.tick()
        values = dict(zip(names, coords.values(x), strict=True))
        try:
            # a trial step far out overflows the loop's matrices: rejected below, not warned
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                r = np.concatenate([d.whiten(m(values))
                                    for d, m in zip(datas, models, strict=True)])
        except np.linalg.LinAlgError:
            r = np.full(size, np.inf)  # a singular loop: a step the optimiser must reject
        # a huge but finite misfit, so that least_squares backs off instead of failing
        return np.nan_to_num(r, nan=1e150, posinf=1e150, neginf=-1e150)

    x = np.zeros(len(names))
    null = np.zeros((len(names), 0))
    for _ in range(4):
        # a direction found unidentifiable stays so (and at nominal): otherwise a weakly
        # determined Q that the fit drives to infinity would flip back and forth
        null = _union(null, _split(_jacobian(residuals, x))[0])
        x = x - null @ (null.T @ x)
        basis = _complement(null)
        converged = True
        if basis.shape[1]:
            # a bounded round: a direction the data do not fix (a Q without its resonance)
            # runs away for ever otherwise; the next round's Jacobian finds it flat
            sol = least_squares(lambda z, b=basis, x0=x: residuals(x0 + b @ z),
                                np.zeros(basis.shape[1]), method="lm", x_scale="jac",
                                max_nfev=ROUND_EVALUATIONS * (basis.shape[1] + 1))
            x = x + basis @ sol.x
            converged = sol.status != 0  # 0: out of evaluations
        J = _jacobian(residuals, x)
        if converged and _union(null, _split(J)[0]).shape[1] == null.shape[1]:
            break
    r = residuals(x)
    return replace(_result(cfg.name, coords, x, r, J, null, datas, effect),
                   min_coherence=min_coherence)


def hann_kernel(resolution_hz: float, width_hz: float
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Offsets (bins) and weights of a Hann-windowed estimate's power kernel,
    ``(sinc d / (1 - d^2))^2`` out to 3 bins (99.99 % of it), sampled finely enough for a
    feature `width_hz` wide (a quarter of it, 1/16 to 1/4 bin)."""
    step = float(np.clip(0.25 * width_hz / resolution_hz, 1 / 16, 1 / 4))
    d = np.linspace(-3.0, 3.0, 2 * round(3 / step) + 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(np.abs(np.abs(d) - 1) < 1e-9, 0.5, np.sinc(d) / (1 - d**2)) ** 2
    return d, w / w.sum()


def _closed_loop(P: NDArray[np.complex128], k: NDArray[np.complex128]
                 ) -> NDArray[np.complex128]:
    """``IN1/EXC`` from the plant and the controller's diagonal at the same frequencies."""
    return sensitivity(P, k) - np.eye(len(DOFS))


def _jacobian(fun, x: NDArray[np.float64]) -> NDArray[np.float64]:  # noqa: ANN001
    """Central differences, ``d residual / d log p``."""
    cols = []
    for i in range(len(x)):
        dx = np.zeros_like(x)
        dx[i] = _STEP
        cols.append((fun(x + dx) - fun(x - dx)) / (2 * _STEP))
    return np.stack(cols, axis=1)


def _split(J: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Orthonormal bases of the unidentifiable and identifiable log-parameter directions."""
    if not np.all(np.isfinite(J)):
        msg = "the model is not finite at these parameters (an unstable or singular loop?)"
        raise FitError(msg)
    _, s, vt = np.linalg.svd(J, full_matrices=False)  # the full U would be bins x bins
    weak = s * MAX_LOG_SIGMA < 1.0
    null = np.hstack([vt[weak].T, _complement(vt.T)])  # fewer residuals than parameters
    return null, vt[~weak].T


def _union(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """`a` extended by the directions of `b` that are substantially new (a null direction
    found again slightly rotated at another point must not widen the span)."""
    out = a
    for v in b.T:
        rest = v - out @ (out.T @ v)
        if np.linalg.norm(rest) > 0.5:
            out = np.hstack([out, (rest / np.linalg.norm(rest))[:, None]])
    return out


def _complement(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Orthonormal basis of the directions orthogonal to the columns of `a`."""
    u, s, _ = np.linalg.svd(a, full_matrices=True)
    return u[:, int(np.sum(s > 1e-6)):]


def _slices(datas: Sequence[FitData]) -> list[tuple[FitData, slice]]:
    """Each data set with its rows of the stacked residual vector."""
    out, start = [], 0
    for d in datas:
        out.append((d, slice(start, start + 2 * d.bins)))
        start += 2 * d.bins
    return out


def _lag_pairs(data: FitData, k: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Indices (into the data's bins) of used bins ``k`` apart in one element."""
    idx = np.full(data.mask.shape, -1)
    idx[data.mask] = np.arange(data.bins)
    both = data.mask[k:] & data.mask[:-k]
    return idx[:-k][both], idx[k:][both]


def _bin_correlation(r: NDArray[np.float64], datas: Sequence[FitData]) -> list[float]:
    """Correlation of whitened complex residuals ``k`` bins apart, pooled over elements."""
    power, lagged = 0.0, np.zeros(CORRELATION_LAGS)
    for data, rows in _slices(datas):
        n = data.bins
        z = r[rows][:n] + 1j * r[rows][n:]
        power += float(np.sum(np.abs(z) ** 2))
        for k in range(1, CORRELATION_LAGS + 1):
            a, b = _lag_pairs(data, k)
            lagged[k - 1] += float(np.real(np.sum(z[b] * np.conj(z[a]))))
    return (lagged / power).tolist() if power > 0 else [0.0] * CORRELATION_LAGS


def _sandwich(J: NDArray[np.float64], rho: list[float], datas: Sequence[FitData]
              ) -> NDArray[np.float64]:
    """``J^T R J`` for errors correlated ``rho[k-1]`` between bins ``k`` apart."""
    B = J.T @ J
    for data, rows in _slices(datas):
        Jd, n = J[rows], data.bins
        for k, c in enumerate(rho, start=1):
            a, b = _lag_pairs(data, k)
            cross = Jd[a].T @ Jd[b] + Jd[a + n].T @ Jd[b + n]  # real with real, imag with imag
            B += c * (cross + cross.T)
    return B


class _Coords:
    """Fit coordinates: ``log(p / p_start)`` for physical parameters, ``(p - p_start) / scale``
    for an effect's (which start at zero, where a logarithm cannot, or where told)."""

    def __init__(self, names: list[str], sus: SOSParams, effect: str | None,
                 effect_start: Mapping[str, float]) -> None:
        self.names = names
        self.log = np.array([n in FIT_PARAMS for n in names])
        scale = effect_scale(effect) if effect else {}
        self.start = np.array([param_value(sus, n) if n in FIT_PARAMS
                               else effect_start.get(n, 0.0) for n in names])
        self.scale = np.array([1.0 if n in FIT_PARAMS else scale[n] for n in names])

    def values(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Parameter values at coordinates `x`."""
        with np.errstate(over="ignore"):  # a trial step to infinity: rejected as a misfit
            return np.where(self.log, self.start * np.exp(x), self.start + self.scale * x)

    def sigma(self, x: NDArray[np.float64], var: NDArray[np.float64]) -> NDArray[np.float64]:
        """One-sigma of each parameter from the variances `var` of the coordinates."""
        width = np.where(self.log, self.values(x), self.scale)
        return np.abs(width) * np.sqrt(np.clip(var, 0, None))


def _result(optic: str, coords: _Coords, x: NDArray, r: NDArray, J: NDArray, null: NDArray,
            datas: Sequence[FitData], effect: str | None) -> FitResult:
    names = coords.names
    chi2 = float(r @ r)
    ident = len(names) - null.shape[1]
    nu = r.size - ident
    # the scatter, robustly: the median of |z|^2 / 2 is ln 2 for Gaussian errors, and unlike
    # chi2/nu it is not pulled up by the heavy tails of errors divided by an estimated sigma
    z2 = r[: r.size // 2] ** 2 + r[r.size // 2 :] ** 2
    scale2 = float(np.median(z2) / 2 / math.log(2)) * r.size / max(nu, 1)
    rho = _bin_correlation(r, datas)
    A_pinv = np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)
    if null.shape[1]:
        proj = np.eye(len(names)) - null @ null.T
        A_pinv = proj @ A_pinv @ proj
    cov = scale2 * A_pinv @ _sandwich(J, rho, datas) @ A_pinv
    lost = np.any(np.abs(null) > _NULL_COMPONENT, axis=1) if null.size else np.zeros(len(names), bool)
    values = coords.values(x)
    sigma = coords.sigma(x, np.diag(cov))
    unident, determined = _name_null(names, null, values, cov, coords.log)
    full = cov.copy()
    sigma[lost] = np.nan
    cov[lost, :] = np.nan
    cov[:, lost] = np.nan
    return FitResult(optic, names, values, sigma, cov, unident, determined, chi2, nu,
                     math.sqrt(scale2), rho, sum(d.bins for d in datas), coords.start, effect,
                     null=null, determined_covariance=full)


def _name_null(names: list[str], null: NDArray, values: NDArray, cov: NDArray,
               log: NDArray[np.bool_]) -> tuple[list[str], dict[str, dict[str, float]]]:
    """Name each unidentifiable direction; for a pair, also the product that is determined."""
    unident, determined = [], {}
    for v in null.T:
        involved = list(np.flatnonzero(np.abs(v) > _NULL_COMPONENT * np.abs(v).max()))
        v = v / v[involved[0]]  # the first parameter, to the power one, leads the name
        if not log[involved].all():  # an effect's parameters enter linearly: a sum
            unident.append(_linear([names[i] for i in involved], v[involved]))
            continue
        unident.append(_monomial([names[i] for i in involved], v[involved]))
        if len(involved) == 2:
            # the direction orthogonal to v within the pair is what the data fix
            i, j = involved
            u = np.zeros(len(names))
            u[i], u[j] = v[j], -v[i]
            u /= u[i]
            var = float(u @ cov @ u)  # u is orthogonal to the null direction
            # the pair's own values: another parameter may be negative (an effect's)
            value = float(np.exp(u[[i, j]] @ np.log(values[[i, j]])))
            determined[_monomial([names[i], names[j]], u[[i, j]])] = {
                "value": value, "sigma": value * math.sqrt(max(var, 0.0))}
    return unident, determined


def _linear(names: list[str], coefs: NDArray) -> str:
    """``a - b + 0.5*c``-style name of ``sum coef_i name_i``."""
    text = ""
    for n, c in zip(names, coefs, strict=True):
        size = "" if abs(abs(c) - 1) < 0.05 else f"{abs(c):.2g}*"
        text += f" {'-' if c < 0 else '+'} {size}{n}"
    return text[3:] if text.startswith(" + ") else text.strip()


def _monomial(names: list[str], powers: NDArray) -> str:
    """``a*b/c^0.5``-style name of ``prod name_i^power_i``."""
    def term(n: str, p: float) -> str:
        p = abs(p)
        return n if abs(p - 1) < 0.05 else f"{n}^{p:.2g}"

    num = [term(n, p) for n, p in zip(names, powers, strict=True) if p > 0]
    den = [term(n, p) for n, p in zip(names, powers, strict=True) if p < 0]
    text = "*".join(num) or "1"
    return text + ("/" + "/".join(den) if den else "")
