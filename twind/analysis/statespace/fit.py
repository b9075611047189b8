"""Fit what a real measurement adds to a state-space model, and the changes a diagnosis tries.

The free parameters are the calibration of every readback the data determine (real, sign
included), of every drive but the first (one drive's is not separable from the readbacks':
only their products reach the data), the delay and low-pass every channel shares, and the
effects' own.

The likelihood is the one the errors have. A Welch estimate's standard error comes from its
own coherence over ``n`` averages, an estimate with ``2n - 2`` degrees of freedom: the real
and imaginary parts of a residual over it follow Student's t with as many (with 5 averages,
one bin in a thousand lies beyond 4.5 sigma, not one in 150 000), and where the coherence
happened high a cluster of neighbours looks like a narrow feature. Least squares would chase
those; the fits here maximise the t likelihood (:class:`Noise`), whose deviance drops are
likelihood ratios. The uncertainties are the Cramer-Rao bound of that likelihood with the
bins' correlation, as an SOS fit's (:mod:`twind.analysis.identification.fit`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import optimize, stats
from scipy.optimize import least_squares

from twind import progress
from twind.analysis.identification.data import MIN_COHERENCE, FitData
from twind.analysis.identification.fit import bin_correlation, sandwich
from twind.analysis.identification.params import FitError
from twind.analysis.statespace.measurement import PlantSet
from twind.analysis.statespace.model import Effect, PlantModel, loop_feedback, other_loops
from twind.config.statespace import StateSpaceOptic

_STEP = 1e-6
"""Relative step of the forward differences."""

MAX_EVALUATIONS = 200
"""Residual evaluations a fit takes at most (a well-posed one converges in tens)."""

NULL_COMPONENT = 0.05
"""A parameter with more than this share of an undetermined direction gets no sigma."""

MIN_GAIN_SNR = 5.0
"""A readback's calibration is fitted only where the model's response there, over the
errors, adds up to this: elsewhere (a coupling the model has none of) it is undetermined and
held at 1."""

MOST_MOVED = 3.0
"""The most a fit moves a model mode's frequency, as a factor."""

ROBUST_SCALE = 3.0
"""Residuals (in sigmas) beyond which the first fit, before the noise is known, weighs a bin
less than least squares."""


@dataclass(frozen=True)
class Noise:
    """The errors' distribution over the measurement's sigmas: Student's t with `dof` degrees
    of freedom (each real and imaginary part), times `scale`."""

    scale: float
    dof: float

    @classmethod
    def of(cls, residual: NDArray[np.float64], averages: int) -> Noise:
        """The noise of residuals `residual` of an estimate over `averages` averages: the t
        distribution most likely to have made them, its degrees of freedom at most
        ``2 averages - 2`` (what a coherence-based sigma of that many averages would give
        alone; a chance high coherence is common, and neighbours share it, so the data
        usually ask for fewer)."""
        most = float(max(2 * averages - 2, 2))
        r = np.asarray(residual, dtype=float)
        scale0 = float(np.median(np.abs(r)) / stats.t.ppf(0.75, most))

        def minus_log_likelihood(p: NDArray[np.float64]) -> float:
            dof, scale = p
            return -float(np.sum(stats.t.logpdf(r, dof, scale=scale)))

        got = optimize.minimize(minus_log_likelihood, [most, scale0], method="L-BFGS-B",
                                bounds=[(1.0, most), (1e-6 * scale0, 10 * scale0)])
        dof, scale = got.x
        return cls(max(float(scale), 1e-12), float(dof))

    @property
    def width(self) -> float:
        """The Cauchy loss's scale that makes least squares this likelihood's maximum."""
        return math.sqrt(self.dof) * self.scale

    def deviance(self, residual: NDArray[np.float64]) -> float:
        """``-2 ln L`` up to a constant."""
        return float((self.dof + 1) * np.sum(np.log1p(residual**2 / (self.dof * self.scale**2))))

    @property
    def information(self) -> float:
        """Fisher information of one residual's location, times the scale squared."""
        return (self.dof + 1) / (self.dof + 3)


@dataclass
class PlantFit:
    """A fitted state-space model: nuisance parameters and effects.

    Attributes
    ----------
    names : list of str
        ``g_<r>``, ``g_d<j>``, ``tau_s``, ``inv_lp_hz``, then ``<effect key>.<param>``.
    values, sigma : ndarray
        Fitted values and one-sigma errors (NaN: not determined by the data).
    chi2 : float
    nu : int
        Real residuals less determined directions.
    noise_scale : float
        The residuals' robust scatter over the measurement's errors.
    bin_correlation : list of float
        Of neighbouring bins' residuals.
    bins : int
        Complex bins fitted.
    effects : list of (Effect, dict)
        The effects and their own values.
    nuisance : dict
        Every nuisance value, fitted or held.
    residual : ndarray
        Whitened residuals, real parts then imaginary parts.
    """

    names: list[str]
    values: NDArray[np.float64]
    sigma: NDArray[np.float64]
    chi2: float
    nu: int
    noise_scale: float
    bin_correlation: list[float]
    bins: int
    effects: list[tuple[Effect, dict[str, float]]] = field(default_factory=list)
    nuisance: dict[str, float] = field(default_factory=dict)
    residual: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False)
    deviance: float = math.nan
    """``-2 ln L`` under the fit's noise (NaN for the first, provisional fit)."""

    @property
    def rank(self) -> int:
        """Directions the data determined."""
        return 2 * self.bins - self.nu

    @property
    def chi2_nu(self) -> float:
        """Reduced chi-square."""
        return self.chi2 / max(self.nu, 1)

    def error(self, name: str) -> float | None:
        """A parameter's sigma, None where the data did not determine it or it was held."""
        if name not in self.names:
            return None
        s = float(self.sigma[self.names.index(name)])
        return None if math.isnan(s) else s

    def own(self, effect: Effect) -> dict[str, float]:
        """An effect's values by its own parameter names."""
        return next(v for e, v in self.effects if e.key() == effect.key())


def fit_data(H: NDArray, sigma: NDArray, mask: NDArray, f: NDArray, readbacks: Sequence[str],
             drives: Sequence[str], averages: int, resolution_hz: float) -> FitData:
    """The bins a fit uses, cut to the span of the used ones."""
    if not mask.any():
        msg = "no coherent bin to fit: every element is below the coherence of noise"
        raise FitError(msg)
    return FitData(f, list(readbacks), list(drives), H, sigma, mask, averages,
                   resolution_hz).span()


@dataclass(frozen=True)
class Baseline:
    """What a state-space optic's diagnosis and fit start from: the measurement's bins, the
    model at them, the nuisance parameters fitted (the model unchanged) and the noise."""

    data: FitData
    model: PlantModel
    free: list[str]
    noise: Noise
    fit: PlantFit


def fit_baseline(plant: PlantSet, optic: StateSpaceOptic,
                 min_coherence: float = MIN_COHERENCE) -> Baseline:
    """The model, its calibrations, delay and low-pass (and, for a closed loop, the other
    loops' gain) fitted to `plant`: first with a Cauchy loss from the median ratios
    (:func:`start_gains`), whose residuals give the noise (:meth:`Noise.of`), then with the
    noise's own likelihood.

    Raises
    ------
    FitError
        If no bin of the measurement is coherent.
    """
    data = fit_data(plant.H, plant.sigma, plant.coherent(min_coherence), plant.frequency_hz,
                    plant.readbacks, plant.drives, plant.averages, plant.resolution_hz)
    loops = other_loops(optic, plant.drives, plant.readbacks, data.frequency_hz,
                        data.resolution_hz)
    model = PlantModel(optic.modal(plant.drives, plant.readbacks), data.frequency_hz,
                       data.resolution_hz, loops,
                       loop_feedback(optic, plant.drives, plant.readbacks, data.frequency_hz))
    progress.note("calibrations, delay and low-pass")
    start = {"tau_s": 0.0, "inv_lp_hz": 0.0, **({"loops": 1.0} if loops is not None else {})}
    gains = start_gains(data, model, start)
    free = [*gains, *(f"g_d{j}" for j in range(1, len(plant.drives))), "tau_s", "inv_lp_hz",
            *(["loops"] if loops is not None else [])]
    first = fit_plant(data, model, start | gains, free)
    noise = Noise.of(first.residual, data.averages)
    return Baseline(data, model, free, noise,
                    fit_plant(data, model, first.nuisance, free, noise=noise))


def start_gains(data: FitData, model: PlantModel, nuisance: Mapping[str, float]
                ) -> dict[str, float]:
    """Each readback's calibration where the data determine it (the model's response over
    the errors adds up to :data:`MIN_GAIN_SNR`), from the median over its bins of the
    measured-to-modelled ratio, its sign the median cosine of the ratio's phase: a mode far
    off its frequency, a few bins grossly wrong, leaves it where the rest put it. The others
    are held at 1."""
    M = model(nuisance | {f"g_{i}": 1.0 for i in range(len(data.responses))})
    out = {}
    for i in range(len(data.responses)):
        used = data.mask[:, i]
        m, h, s = M[:, i][used], data.H[:, i][used], data.sigma[:, i][used]
        if float(np.sum(np.abs(m / s) ** 2)) < MIN_GAIN_SNR**2:
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = h / m
        ratio = ratio[np.isfinite(ratio) & (ratio != 0)]
        sign = 1.0 if np.median(ratio.real / np.abs(ratio)) >= 0 else -1.0
        out[f"g_{i}"] = sign * float(np.median(np.abs(ratio)))
    return out


def fit_plant(data: FitData, model: PlantModel, nuisance: Mapping[str, float],
              free: Sequence[str], effects: Sequence[tuple[Effect, Mapping[str, float]]] = (),
              noise: Noise | None = None, new: Effect | None = None,
              limits: Mapping[str, tuple[float, float]] | None = None) -> PlantFit:
    """The most likely nuisance parameters `free` (from `nuisance`) and effects' own
    parameters (from their values).

    Parameters
    ----------
    data : FitData
        The measurement's used bins.
    model : PlantModel
        At ``data.frequency_hz``.
    nuisance : mapping of str to float
        Every nuisance value: the start of those free, the value of the others.
    free : sequence of str
        The nuisance parameters fitted.
    effects : sequence of (Effect, mapping)
        Effects and the values their parameters start from.
    noise : Noise, optional
        The errors' distribution; without it, a provisional fit with a Cauchy loss of
        scale :data:`ROBUST_SCALE` (a model grossly wrong in a few bins, a narrow mode off
        its frequency, then leaves the calibrations where the rest of the data put them),
        whose residuals give the noise.
    new : Effect, optional
        One of `effects` whose parameters are fitted alone first, the others held where
        they start (a search's start, far from where the nuisance parameters' least squares
        would first pull it).
    limits : mapping of str to (float, float), optional
        Positive parameters (``key.param``) held within a range, e.g. a resonance's
        frequency away from where a moved mode lies.

    Returns
    -------
    PlantFit

    Raises
    ------
    FitError
        If the model is not finite where the fit starts.
    """
    problem = _Problem(data, model, nuisance, free, effects, limits or {})
    width = noise.width if noise else ROBUST_SCALE
    x = problem.x0
    if new is not None:
        x = problem.solve(x, [i for i, n in enumerate(problem.names)
                              if n.startswith(f"{new.key()}.")], width)
    x = problem.solve(x, list(range(len(problem.names))), width)
    return problem.result(x, noise)


class _Problem:
    """A fit's parameters, their coordinates and bounds, residuals and Jacobian."""

    def __init__(self, data: FitData, model: PlantModel, nuisance: Mapping[str, float],
                 free: Sequence[str], effects: Sequence[tuple[Effect, Mapping[str, float]]],
                 limits: Mapping[str, tuple[float, float]]) -> None:
        self.data, self.model, self.effects = data, model, list(effects)
        self.names = list(free) + [f"{e.key()}.{p}" for e, own in effects for p in own]
        self.start = {**nuisance, **{f"{e.key()}.{p}": v for e, own in effects
                                     for p, v in own.items()}}
        self.coords = [_Coordinate.of(n, limits) for n in self.names]
        self.x0 = np.array([c.to(self.start[n]) for c, n in zip(self.coords, self.names,
                                                                   strict=True)])
        r0 = self.residuals(self.x0)
        if not np.all(np.abs(r0) < 1e150):
            msg = "the model is not finite where the fit starts"
            raise FitError(msg)

    def unpack(self, x: NDArray[np.float64]) -> tuple[dict, list]:
        """Nuisance values and effects' values at coordinates `x`."""
        values = dict(self.start)
        values.update({n: c.value(v) for n, c, v in zip(self.names, self.coords, x, strict=True)})
        nuis = {k: v for k, v in values.items() if "." not in k}
        eff = [(e, {p: values[f"{e.key()}.{p}"] for p in own}) for e, own in self.effects]
        return nuis, eff

    def residuals(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Whitened residuals at `x` (huge but finite where the model is not)."""
        progress.tick()
        nuis, eff = self.unpack(x)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            r = self.data.whiten(self.model(nuis, eff))
        return np.nan_to_num(r, nan=1e150, posinf=1e150, neginf=-1e150)

    def jacobian(self, x: NDArray[np.float64], which: Sequence[int]) -> NDArray[np.float64]:
        """Columns `which`: those of parameters the model is linear in from its
        derivatives, the others by forward differences."""
        nuis, eff = self.unpack(x)
        parts = self.model.parts(nuis, eff)
        base = self.data.whiten(parts.out)
        cols = []
        for i in which:
            name = self.names[i]
            d = self.model.derivative(parts, name, eff)
            if d is not None:
                cols.append(-_whitened(self.data, d) * self.coords[i].width(x[i]))
                continue
            step = _STEP * max(1.0, abs(x[i]))
            moved = x.copy()
            moved[i] += step
            nm, em = self.unpack(moved)
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                cols.append((self.data.whiten(self.model(nm, em)) - base) / step)
        return np.nan_to_num(np.stack(cols, axis=1), nan=0.0, posinf=0.0, neginf=0.0)

    def solve(self, x: NDArray[np.float64], which: Sequence[int], width: float
              ) -> NDArray[np.float64]:
        """`x` with its coordinates `which` fitted (the others held), a Cauchy loss of
        scale `width`."""
        if not which:
            return x
        idx = np.array(which)

        def fun(z: NDArray[np.float64]) -> NDArray[np.float64]:
            full = x.copy()
            full[idx] = z
            return self.residuals(full)

        def jac(z: NDArray[np.float64]) -> NDArray[np.float64]:
            full = x.copy()
            full[idx] = z
            return self.jacobian(full, which)

        sol = least_squares(fun, x[idx], jac=jac, method="trf", loss="cauchy", f_scale=width,
                            x_scale="jac", ftol=1e-6, xtol=1e-6, max_nfev=MAX_EVALUATIONS)
        out = x.copy()
        out[idx] = sol.x
        return out

    def result(self, x: NDArray[np.float64], noise: Noise | None) -> PlantFit:
        """The fit at `x`."""
        r = self.residuals(x)
        J = self.jacobian(x, range(len(self.names))) if self.names else np.zeros((r.size, 0))
        nuis, eff = self.unpack(x)
        return _result(self.data, self.names, self.coords, x, r, J, nuis, eff, noise)


def _whitened(data: FitData, d: NDArray[np.complex128]) -> NDArray[np.float64]:
    """A change of the modelled measurement as :meth:`FitData.whiten` weighs it."""
    z = data.whitened_change(d, np.arange(d.shape[0]))
    return np.concatenate([z.real, z.imag])


_LOG_PARAMS = ("inv_lp_hz", "inv_pole_hz", "inv_zero_hz")
"""Positive parameters without bounds, fitted in their logarithm."""
_TINY = 1e-6
"""Where a positive parameter at zero starts (a low-pass at 1 MHz: none)."""
RANGES = {"log_f": (-math.log(MOST_MOVED), math.log(MOST_MOVED), False),
          "log_q": (-math.log(1e4), math.log(1e4), False),
          "q": (0.5, 1e6, True), "f_hz": (1e-3, 1e4, True)}
"""Bounded parameters (lowest, highest, in the logarithm): a mode moved at most a factor
:data:`MOST_MOVED` and its Q changed at most 1e4 times; a resonance's Q at least 0.5 (below,
two real poles and no mode)."""


@dataclass(frozen=True)
class _Coordinate:
    """How a parameter is fitted: as it is, in its logarithm, or within (lo, hi) through a
    tanh (so that the fit is unbounded and the value is not)."""

    kind: str  # "linear", "log" or "range"
    lo: float = 0.0
    hi: float = 0.0
    log: bool = False

    @classmethod
    def of(cls, name: str, limits: Mapping[str, tuple[float, float]]) -> _Coordinate:
        """The coordinate of parameter `name` (ranges in `limits` first)."""
        param = name.rpartition(".")[2] if "." in name else name
        if name in limits:
            return cls("range", *limits[name], True)
        if param in RANGES:
            return cls("range", *RANGES[param])
        return cls("log") if param in _LOG_PARAMS else cls("linear")

    def _ends(self) -> tuple[float, float]:
        return (math.log(self.lo), math.log(self.hi)) if self.log else (self.lo, self.hi)

    def to(self, value: float) -> float:
        """The coordinate of `value`."""
        if self.kind == "linear":
            return value
        if self.kind == "log":
            return math.log(max(value, _TINY))
        a, b = self._ends()
        v = math.log(max(value, 1e-300)) if self.log else value
        return math.atanh(max(min(2 * (v - a) / (b - a) - 1, 0.999999), -0.999999))

    def value(self, x: float) -> float:
        """The value at coordinate `x`."""
        if self.kind == "linear":
            return x
        if self.kind == "log":
            return math.exp(min(x, 700.0))
        a, b = self._ends()
        v = a + (b - a) * (1 + math.tanh(x)) / 2
        return math.exp(v) if self.log else v

    def width(self, x: float) -> float:
        """d value / d coordinate at `x`."""
        if self.kind == "linear":
            return 1.0
        if self.kind == "log":
            return self.value(x)
        a, b = self._ends()
        dv = (b - a) * (1 - math.tanh(x) ** 2) / 2
        return dv * self.value(x) if self.log else dv


def _result(data: FitData, names: list[str], coords: list[_Coordinate], x: NDArray,
            r: NDArray, J: NDArray, nuisance: dict, effects: list, noise: Noise | None
            ) -> PlantFit:
    """Values, sigmas and the fit's statistics (robust scale, bin correlation, rank,
    deviance).

    A direction of the parameters is determined when the data fix it better than its
    natural scale (:func:`_scale`: a factor e for a frequency, Q or corner, all of a
    calibration or an amplitude, a millisecond of delay); the rank counts those, and a
    parameter with a share of an undetermined direction has no sigma."""
    chi2 = float(r @ r)
    z2 = r[: r.size // 2] ** 2 + r[r.size // 2:] ** 2
    sigma = np.full(len(names), np.nan)
    rank = 0
    values = np.array([c.value(v) for c, v in zip(coords, x, strict=True)])
    median = float(np.median(z2) / 2 / math.log(2))  # the residuals' variance, robustly
    if names:
        width = np.array([c.width(v) for c, v in zip(coords, x, strict=True)])
        scale = np.array([_scale(n, c, v, w, names, values)
                          for n, c, v, w in zip(names, coords, values, width, strict=True)])
        Js = J * scale
        _, sv, vt = np.linalg.svd(Js, full_matrices=False)
        level = math.sqrt(median)
        weak = sv < level
        rank = int((~weak).sum())
    nu = r.size - rank
    scale2 = median * r.size / max(nu, 1)
    rho = bin_correlation(r, [data])
    if names and rank:
        keep = vt[~weak]
        inv = (keep.T / sv[~weak] ** 2) @ keep  # the pseudo-inverse of Js^T Js, determined part
        var = noise.scale**2 / noise.information if noise else scale2
        cov_s = var * inv @ sandwich(Js, rho, [data]) @ inv
        lost = (np.abs(vt[weak]).max(axis=0) > NULL_COMPONENT if weak.any()
                else np.zeros(len(names), bool))
        sd = np.sqrt(np.clip(np.diag(cov_s), 0, None)) * scale * width
        sigma = np.where(lost, np.nan, sd)
    return PlantFit(names, values, sigma, chi2, nu, math.sqrt(scale2), rho, data.bins,
                    effects, nuisance, r, noise.deviance(r) if noise else math.nan)


def _scale(name: str, coord: _Coordinate, value: float, width: float, names: Sequence[str],
           values: NDArray) -> float:
    """The natural scale of a coordinate: how well it must be known to count as determined
    (a factor e of a positive value, all of a calibration, a millisecond of delay, one of an
    amplitude or a coupling, all of a resonance's largest numerator)."""
    param = name.rpartition(".")[2] if "." in name else name
    if coord.kind == "log":
        return 1.0
    if coord.kind == "range":  # a unit of its (log-)value, in coordinates
        unit = abs(value) if coord.log else 1.0
        return unit / max(width, 1e-300)
    if name.startswith("g_"):
        return max(abs(value), 1e-300)
    if param == "tau_s":
        return 1e-3
    if param.startswith("b") and param[1:].isdigit():
        key = name.rpartition(".")[0]
        return max(max(abs(v) for n, v in zip(names, values, strict=True)
                       if n.startswith(f"{key}.b")), 1e-300)
    return 1.0
