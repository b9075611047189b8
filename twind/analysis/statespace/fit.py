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
from threadpoolctl import threadpool_limits

from twind import progress
from twind.analysis.identification.data import MIN_COHERENCE, FitData
from twind.analysis.identification.fit import bin_correlation, sandwich
from twind.analysis.identification.params import FitError
from twind.analysis.statespace.measurement import PlantSet
from twind.analysis.statespace.model import (
    Effect,
    PlantModel,
    loop_feedback,
    modelled,
    other_loops,
    stage_inputs,
)
from twind.config.statespace import StateSpaceOptic

_STEP = 1e-6
"""Relative step of the forward differences."""

MAX_EVALUATIONS = 200
"""Residual evaluations a fit takes at most (a well-posed one converges in tens)."""

NULL_COMPONENT = 0.05
"""A parameter with more than this share of an undetermined direction gets no sigma."""

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
    cov: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 0)), repr=False)
    """The values' covariance (NaN in the rows and columns of those with no sigma)."""

    def wald(self, effect: Effect) -> float | None:
        """Wald's statistic of `effect` against the model without it (its parameters at
        :meth:`Effect.null`): ``d^T C^-1 d`` over its parameters; None when one has no
        sigma."""
        own = self.own(effect)
        if effect.family == "resonance":  # no mode is its numerators at 0, whatever f and Q
            own = {p: v for p, v in own.items() if p.startswith("b")}
        idx = [self.names.index(f"{effect.key()}.{p}") for p in own]
        c = self.cov[np.ix_(idx, idx)] if self.cov.size else np.full((1, 1), np.nan)
        if not np.all(np.isfinite(c)):
            return None
        null = effect.null(own)
        d = np.array([own[p] - null[p] for p in own])
        try:
            return float(d @ np.linalg.solve(c, d))
        except np.linalg.LinAlgError:
            return None

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
    model at them, the nuisance parameters fitted (the model unchanged), the noise, which
    elements the model has (the range each nuisance parameter may take is the model's
    :attr:`~twind.analysis.statespace.model.PlantModel.bounds`)."""

    data: FitData
    model: PlantModel
    free: list[str]
    noise: Noise
    fit: PlantFit
    modelled: NDArray[np.bool_]


one_blas_thread = threadpool_limits.wrap(limits=1, user_api="blas")
"""Runs a fit, or a diagnosis made of fits, on one BLAS thread. OpenBLAS's threaded
reductions differ in their last bits from run to run, and a diagnosis chooses its changes
along a path of local fits that such a difference can redirect: one six-drive file gave
chi2/nu 1.2e3 with 7 claims in one run and 2.2e3 with 8 in the next. On one thread a file
gives the same result every time, as fast (the Jacobians are tall and thin: a second thread
mostly waits)."""


@one_blas_thread
def fit_baseline(plant: PlantSet, optic: StateSpaceOptic,
                 min_coherence: float = MIN_COHERENCE) -> Baseline:
    """The model, its calibrations, delay and low-pass (and, for a closed loop, the other
    loops' gain) fitted to `plant`.

    Only the elements the model has (:func:`~twind.analysis.statespace.model.modelled`)
    calibrate: a readback or drive none of whose coherent elements the model reaches is
    held at 1. The calibrations start from the data's own ratios to the model
    (:func:`start_gains`), the delay and low-pass from the best of a grid, and every one
    stays within a physical range (:func:`nuisance_limits`): a fit cannot run away to a
    corner a million times above the band. The first fit takes a Cauchy loss (grossly wrong
    bins, a mode far off its frequency, cannot drag it); its residuals on the modelled
    elements give the noise (:meth:`Noise.of`), and the second maximises that likelihood.

    Raises
    ------
    FitError
        If no bin of the measurement is coherent.
    """
    data = fit_data(plant.H, plant.sigma, plant.coherent(min_coherence), plant.frequency_hz,
                    plant.readbacks, plant.drives, plant.averages, plant.resolution_hz)
    loops = other_loops(optic, plant.drives, plant.readbacks, data.frequency_hz,
                        data.resolution_hz)
    extra = stage_inputs(optic, plant.drives)
    model = PlantModel(optic.modal(plant.drives, plant.readbacks), data.frequency_hz,
                       data.resolution_hz, loops,
                       loop_feedback(optic, plant.drives, plant.readbacks, data.frequency_hz),
                       optic.modal(extra, plant.readbacks) if extra else None)
    inside = modelled(optic, plant.drives, plant.readbacks, data.frequency_hz)
    progress.note("calibrations, delay and low-pass")
    start = {"tau_s": 0.0, "inv_lp_hz": 0.0, **({"loops": 1.0} if loops is not None else {})}
    gains = start_gains(data, model, start, inside)
    free = [*gains, "tau_s", "inv_lp_hz", *(["loops"] if loops is not None else [])]
    model.bounds = limits = nuisance_limits(data, gains)
    start = start | gains | _lag_start(data, model, start | gains, limits)
    first = fit_plant(data, model, start, free)
    noise = Noise.of(first.residual[modelled_entries(data, inside)], data.averages)
    return Baseline(data, model, free, noise,
                    fit_plant(data, model, first.nuisance, free, noise=noise), inside)


def modelled_entries(data: FitData, inside: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Which of :meth:`FitData.whiten`'s residuals (real parts, then imaginary) belong to
    elements the model has (all, if none does)."""
    own = np.broadcast_to(inside[None], data.mask.shape)[data.mask]
    if not own.any():
        own = np.ones_like(own)
    return np.concatenate([own, own])


MOST_CALIBRATED = 1e4
"""A calibration stays within this factor of where the data's ratios to the model put it."""
DELAY_S = (-0.02, 0.05)
"""The delay's range (s): a digital system's delays and the anti-aliasing filters' lags are
a few ms; tens of ms is already a phase of a cycle at the top of a 0-20 Hz band."""
LOWPASS_REACH = 3.0
"""A low-pass corner lies at least this far below the band's top (a corner beyond is no
low-pass the band can tell from a delay)."""


def recalibrated(data: FitData, model: PlantModel, fit: PlantFit, free: Sequence[str],
                 inside: NDArray[np.bool_], noise: Noise,
                 limits: Mapping[str, tuple[float, float]]) -> PlantFit:
    """`fit` with the calibrations it left undetermined or consistent with zero started
    again from the data's ratios to the model as `fit` changes it, and refitted (kept if
    the deviance falls). A mode far from where the model has it makes a readback's ratio to
    the model mostly a ratio of misplaced peaks: a calibration started there may take the
    wrong sign, which its range then keeps (:func:`nuisance_limits`)."""
    lost = [n for n in free if n.startswith("g_") and not n.startswith("g_d")
            and (fit.error(n) is None or abs(fit.nuisance[n]) < 2 * fit.error(n))]
    if not lost:
        return fit
    unit = {k: (1.0 if k.startswith("g_") else v) for k, v in fit.nuisance.items()}
    gains = {n: g for n, g in start_gains(data, model, unit, inside, fit.effects).items()
             if n in lost}
    if not gains:
        return fit
    model.bounds.update(nuisance_limits(data, gains))
    again = fit_plant(data, model, {**fit.nuisance, **gains}, free, fit.effects, noise=noise,
                      limits=limits)
    return again if again.deviance < fit.deviance else fit


def nuisance_limits(data: FitData, gains: Mapping[str, float]
                    ) -> dict[str, tuple[float, float]]:
    """The physical range of each nuisance parameter: each calibration within
    :data:`MOST_CALIBRATED` of its start, its sign kept; the delay in :data:`DELAY_S`; the
    low-pass's corner (``1 / inv_lp_hz``) above the band's top over :data:`LOWPASS_REACH`
    (at 1e4 times the top it is none)."""
    top = float(data.frequency_hz[data.mask.any(axis=(1, 2))].max())
    out = {"tau_s": DELAY_S, "inv_lp_hz": (1e-4 / top, LOWPASS_REACH / top)}
    for name, g in gains.items():
        lo, hi = abs(g) / MOST_CALIBRATED, abs(g) * MOST_CALIBRATED
        out[name] = (lo, hi) if g > 0 else (-hi, -lo)
    return out


def _lag_start(data: FitData, model: PlantModel, nuisance: Mapping[str, float],
               limits: Mapping[str, tuple[float, float]]) -> dict[str, float]:
    """The delay and low-pass of a grid over their ranges that fits best (the calibrations
    where they start, a Cauchy loss): where the fit of them all starts."""
    lo, hi = limits["inv_lp_hz"]
    best, out = math.inf, {"tau_s": 0.0, "inv_lp_hz": lo}
    for tau in np.linspace(*DELAY_S, 15):
        for inv in np.geomspace(lo, hi, 6):
            r = data.whiten(model(nuisance | {"tau_s": tau, "inv_lp_hz": inv}))
            cost = float(np.sum(np.log1p((r / ROBUST_SCALE) ** 2)))
            if cost < best:
                best, out = cost, {"tau_s": float(tau), "inv_lp_hz": float(inv)}
    return out


MIN_RATIO_BINS = 3
"""Coherent bins an element needs to start its calibration from."""


def start_gains(data: FitData, model: PlantModel, nuisance: Mapping[str, float],
                inside: NDArray[np.bool_],
                effects: Sequence[tuple[Effect, Mapping[str, float]]] = ()) -> dict[str, float]:
    """The calibrations the data's own ratios to the model (changed by `effects`) give:
    ``g_<r>`` of each readback and ``g_d<j>`` of each drive but the first of its group (only
    products of a readback's and a drive's calibrations reach the data) that a coherent
    element the model has joins.

    Each such element's own calibration (:func:`_element_gain`) is split into a
    readback's and a drive's part: their log magnitudes by least squares, their signs as the
    elements that tell theirs most surely agree (:func:`_signs`).
    """
    M = model(nuisance, effects)
    nr, nd = inside.shape
    elements = {}
    for r in range(nr):
        for d in range(nd):
            used = np.flatnonzero(data.mask[:, r, d]) if inside[r, d] else np.zeros(0, int)
            g = _element_gain(data.H[used, r, d], M[used, r, d], data.sigma[used, r, d])
            if g is not None:
                elements[r, d] = (math.log(abs(g[0])), math.copysign(1.0, g[0]), g[1], g[2])
    return _split(elements)


def _element_gain(h: NDArray[np.complex128], m: NDArray[np.complex128],
                  sigma: NDArray[np.float64]) -> tuple[float, int, float] | None:
    """One element's calibration (sign included), its bins and how surely they tell its
    sign (how much the Cauchy loss rises with the sign turned; none where it falls): the
    median of the ratio's magnitude (its sign the median cosine of its phase over the lower
    half of the band, where a delay turns it least) or the least-squares ratio, whichever
    fits with the smaller Cauchy loss. The median holds where a few bins are grossly
    wrong (a mode off its frequency); the least squares where the model's shape differs
    from the data's over most bins and its few large ones decide (a coupling the model has
    only weakly)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = h / m
    ok = np.isfinite(ratio) & (ratio != 0) & (sigma > 0)
    if ok.sum() < MIN_RATIO_BINS:
        return None
    h, m, sigma, ratio = h[ok], m[ok], sigma[ok], ratio[ok]
    low = ratio[: max(MIN_RATIO_BINS, ratio.size // 2)]
    median = math.copysign(float(np.median(np.abs(ratio))),
                           float(np.median(low.real / np.abs(low))) or 1.0)
    w = 1.0 / sigma**2
    norm = float(np.sum(w * np.abs(m) ** 2))
    lsq = float(np.sum(w * (np.conj(m) * h).real)) / norm if norm > 0 else 0.0

    def cost(g: float) -> float:
        return float(np.sum(np.log1p(np.abs((h - g * m) / sigma / ROBUST_SCALE) ** 2)))

    best = min((g for g in (median, lsq) if g != 0 and math.isfinite(g)), key=cost,
               default=None)
    if best is None:
        return None
    return best, int(ok.sum()), max(cost(-best) - cost(best), 0.0)


def _split(elements: Mapping[tuple[int, int], tuple[float, float, int, float]]
           ) -> dict[str, float]:
    """Readbacks' and drives' calibrations from each element's log ratio, sign, bins and
    sign's sureness (:func:`start_gains`): the first drive of each group of elements joined
    by shared readbacks and drives is held at 1."""
    rows, cols = sorted({r for r, _ in elements}), sorted({d for _, d in elements})
    sign, refs = _signs(elements, cols)
    names = [("r", r) for r in rows] + [("d", d) for d in cols if d not in refs]
    index = {n: k for k, n in enumerate(names)}
    A, y, w = np.zeros((len(elements), len(names))), np.zeros(len(elements)), np.zeros(len(elements))
    for k, ((r, d), (log, _, n, _)) in enumerate(elements.items()):
        A[k, index[("r", r)]] = 1.0
        if ("d", d) in index:
            A[k, index[("d", d)]] = 1.0
        y[k], w[k] = log, math.sqrt(n)
    logs = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)[0] if names else []
    out = {}
    for (kind, i), log in zip(names, logs, strict=True):
        out[f"g_{i}" if kind == "r" else f"g_d{i}"] = sign[(kind, i)] * math.exp(log)
    return out


def _signs(elements: Mapping[tuple[int, int], tuple[float, float, int, float]],
           cols: Sequence[int]) -> tuple[dict[tuple[str, int], float], list[int]]:
    """Each readback's and drive's sign, the first drive of each group of joined elements
    positive: taken along the elements that tell theirs most surely (a spanning tree of the
    surest), then each flipped while that agrees with more of the elements, weighed by
    their sureness. Taken along whichever element came first, one weak element (a coupling
    the model has only faintly, in the wrong phase) would set a drive's sign against its
    own collocated readback's, and the calibration's range would keep it there."""
    tree = _surest_tree(elements)
    sign: dict[tuple[str, int], float] = {}
    refs = []
    for d0 in cols:  # each group's first drive: calibration 1
        if ("d", d0) in sign:
            continue
        refs.append(d0)
        sign[("d", d0)] = 1.0
        queue = [("d", d0)]
        while queue:
            node = queue.pop()
            for other, s in tree.get(node, []):
                if other not in sign:  # s = sign(readback) sign(drive)
                    sign[other] = s * sign[node]
                    queue.append(other)
    for _ in range(len(sign)):
        flips = [n for n in sign if (n[0] == "r" or n[1] not in refs)
                 and _agreement(elements, sign, n) < 0]
        if not flips:
            break
        sign[flips[0]] *= -1.0
    return sign, refs


def _surest_tree(elements: Mapping[tuple[int, int], tuple[float, float, int, float]]
                 ) -> dict[tuple[str, int], list[tuple[tuple[str, int], float]]]:
    """A spanning forest of the elements (readbacks and drives its nodes), the surest of their
    signs first (Kruskal's): each node's neighbours with the element's sign."""
    parent: dict[tuple[str, int], tuple[str, int]] = {}

    def root(node: tuple[str, int]) -> tuple[str, int]:
        while parent.setdefault(node, node) != node:
            node = parent[node]
        return node

    tree: dict[tuple[str, int], list[tuple[tuple[str, int], float]]] = {}
    for (r, d), (_, s, _, _) in sorted(elements.items(), key=lambda e: -e[1][3]):
        a, b = root(("r", r)), root(("d", d))
        if a != b:
            parent[a] = b
            tree.setdefault(("r", r), []).append((("d", d), s))
            tree.setdefault(("d", d), []).append((("r", r), s))
    return tree


def _agreement(elements: Mapping[tuple[int, int], tuple[float, float, int, float]],
               sign: Mapping[tuple[str, int], float], node: tuple[str, int]) -> float:
    """How much the elements through `node` agree with the signs (their sureness summed,
    negative where they disagree)."""
    return sum(sure * s * sign[("r", r)] * sign[("d", d)]
               for (r, d), (_, s, _, sure) in elements.items() if node in (("r", r), ("d", d)))


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
        Parameters (``key.param``) held within a range, e.g. a resonance's frequency away
        from where a moved mode lies, besides the nuisance's ranges (``model.bounds``).

    Returns
    -------
    PlantFit

    Raises
    ------
    FitError
        If the model is not finite where the fit starts.
    """
    problem = _Problem(data, model, nuisance, free, effects, {**model.bounds, **(limits or {})})
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
          "q": (2.0, 1e6, True), "f_hz": (1e-3, 1e4, True)}
"""Bounded parameters (lowest, highest, in the logarithm): a mode moved at most a factor
:data:`MOST_MOVED` and its Q changed at most 1e4 times; a resonance's Q at least 2 (below,
a peak wider than its frequency: a slope of the band, which no data resolve as a mode)."""


@dataclass(frozen=True)
class _Coordinate:
    """How a parameter is fitted: as it is, in its logarithm, or within (lo, hi) through a
    tanh (so that the fit is unbounded and the value is not), in the logarithm of its
    magnitude for a range of one sign (`sign` -1: a negative range)."""

    kind: str  # "linear", "log" or "range"
    lo: float = 0.0
    hi: float = 0.0
    log: bool = False
    sign: float = 1.0

    @classmethod
    def of(cls, name: str, limits: Mapping[str, tuple[float, float]]) -> _Coordinate:
        """The coordinate of parameter `name` (ranges in `limits` first: positive or
        negative ones in the logarithm, others as they are)."""
        param = name.rpartition(".")[2] if "." in name else name
        if name in limits:
            lo, hi = limits[name]
            if lo > 0:
                return cls("range", lo, hi, True)
            if hi < 0:
                return cls("range", -hi, -lo, True, -1.0)
            return cls("range", lo, hi, False)
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
        v = math.log(max(self.sign * value, 1e-300)) if self.log else value
        return math.atanh(max(min(2 * (v - a) / (b - a) - 1, 0.999999), -0.999999))

    def value(self, x: float) -> float:
        """The value at coordinate `x`."""
        if self.kind == "linear":
            return x
        if self.kind == "log":
            return math.exp(min(x, 700.0))
        a, b = self._ends()
        v = a + (b - a) * (1 + math.tanh(x)) / 2
        return self.sign * math.exp(v) if self.log else v

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
    cov = np.full((len(names), len(names)), np.nan)
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
        unit = scale * width
        cov = cov_s * np.outer(unit, unit)
        cov[lost] = cov[:, lost] = np.nan
        sigma = np.sqrt(np.clip(np.diag(cov), 0, None))
    return PlantFit(names, values, sigma, chi2, nu, math.sqrt(scale2), rho, data.bins,
                    effects, nuisance, r, noise.deviance(r) if noise else math.nan, cov)


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
        if name in ("tau_s",):
            unit = 1e-3
        return unit / max(abs(width), 1e-300)
    if name.startswith("g_"):
        return max(abs(value), 1e-300)
    if param == "tau_s":
        return 1e-3
    if param.startswith("b") and param[1:].isdigit():
        key = name.rpartition(".")[0]
        return max(max(abs(v) for n, v in zip(names, values, strict=True)
                       if n.startswith(f"{key}.b")), 1e-300)
    return 1.0
