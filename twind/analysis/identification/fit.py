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

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from twind import progress
from twind.analysis.estimation.tfset import TFSet
from twind.analysis.identification.data import MIN_COHERENCE, FitData
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.params import FIT_PARAMS, FitError, check_names, param_value
from twind.analysis.identification.result import NULL_COMPONENT, FitResult, name_null
from twind.config import OpticConfig
from twind.model.effects import EffectError, effect_params, effect_scale
from twind.model.params import SOSParams


MAX_LOG_SIGMA = 1.0
"""A direction of log-parameter space known worse than a factor e is unidentifiable."""


CORRELATION_LAGS = 3
"""Neighbouring bins whose error correlation is estimated (Hann: lag 1 dominates)."""


ROUND_EVALUATIONS = 30
"""Residual evaluations per fitted direction in one round of the fit (scipy's default is
100): a well-posed fit converges in a few, a direction the data leave free only runs away."""


_STEP = 1e-4  # log-parameter step of the finite-difference Jacobian


# ------------------------------------------------------------------------------ the fit
def fit(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, params: Sequence[str] = FIT_PARAMS,
        min_coherence: float = MIN_COHERENCE, band: tuple[float, float] | None = None,
        effect: str | None = None, effect_start: Mapping[str, float] | None = None,
        whole: Sequence[tuple[float, float]] = (), unfitted: Sequence[str] = (),
        held: Mapping[str, float] | None = None) -> FitResult:
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
        moves nothing at zero coupling, from :func:`twind.analysis.identification.narrow.search`).
    whole : sequence of (float, float)
        Bands (Hz) fitted bin by bin whatever their coherence (:meth:`FitData.from_tfset`).
    unfitted : sequence of str
        Effect parameters held at zero (a coupling to a DOF the measurement does not excite).
    held : mapping of str to float, optional
        Effect parameters held at these values (a frequency being profiled).

    Returns
    -------
    FitResult
    """
    names = check_names(params)
    if effect is not None:
        try:
            names += [n for n in effect_params(effect)
                      if n not in unfitted and n not in (held or {})]
        except EffectError as e:
            raise FitError(str(e)) from None
    sets = [tfs] if isinstance(tfs, TFSet) else list(tfs)
    datas = [FitData.from_tfset(t, min_coherence, band, whole).span() for t in sets]
    models = [ClosedLoopModel.of(cfg, d, effect).for_data(d) for d in datas]
    coords = _Coords(names, cfg.sus, effect, effect_start or {})

    size = sum(2 * d.bins for d in datas)

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        progress.tick()
        values = {**(held or {}), **dict(zip(names, coords.values(x), strict=True))}
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


def bin_correlation(r: NDArray[np.float64], datas: Sequence[FitData]) -> list[float]:
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


def sandwich(J: NDArray[np.float64], rho: list[float], datas: Sequence[FitData]
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
    rho = bin_correlation(r, datas)
    A_pinv = np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)
    if null.shape[1]:
        proj = np.eye(len(names)) - null @ null.T
        A_pinv = proj @ A_pinv @ proj
    cov = scale2 * A_pinv @ sandwich(J, rho, datas) @ A_pinv
    lost = np.any(np.abs(null) > NULL_COMPONENT, axis=1) if null.size else np.zeros(len(names), bool)
    values = coords.values(x)
    sigma = coords.sigma(x, np.diag(cov))
    unident, determined = name_null(names, null, values, cov, coords.log)
    full = cov.copy()
    sigma[lost] = np.nan
    cov[lost, :] = np.nan
    cov[:, lost] = np.nan
    return FitResult(optic, names, values, sigma, cov, unident, determined, chi2, nu,
                     math.sqrt(scale2), rho, sum(d.bins for d in datas), coords.start, effect,
                     null=null, determined_covariance=full)
