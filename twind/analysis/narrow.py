"""Where a narrow mode lies: the search that starts a ``bounce_roll`` fit.

A mode narrower than a bin (Q 1000) moves only the bins next to it, and at zero coupling its
frequency moves nothing, so a fit from zero never finds it. The search scans each mode's
frequency over :data:`~twind.model.effects.MODE_SEARCH` in steps of a quarter of a bin (or
of the mode's width, if wider) and fits its couplings linearly at each: to first order a
mode adds ``B(f) h(f; f0)`` to ``IN1/EXC``, with ``B`` smooth in f (the loop around the
coupling pattern) and ``h`` the mode's own response, so ``B`` is computed once on the Hann
kernel's points and every trial frequency costs a product. The best frequency of each mode,
with its couplings, is where the nonlinear fit starts.

The evidence is searched over many frequencies: its p-value carries that look-elsewhere
cost (:func:`p_value`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from twind import DOFS
from twind.analysis.fit import (
    FIT_PARAMS,
    ClosedLoopModel,
    FitData,
    hann_kernel,
    with_params,
)
from twind.config import OpticConfig
from twind.loop.plant import Plant
from twind.model.effects import MODE_SEARCH, mode_bands, with_effect

_REACH_BINS = 3  # the Hann power kernel's reach (99.99 % of it)
_ANGLES = (0.0, math.pi / 2, math.pi / 4)  # ROLL's PIT-like, YAW-like and mixed pattern
_FLAT = 4.0  # chi^2 a trial frequency must gain over the nominal one to be preferred
_UNSEEN_P = 0.05
"""A mode whose best couplings gain less than the noise would at this false-alarm
probability (over the frequencies searched) starts uncoupled at its nominal frequency."""


def bands(cfg: OpticConfig, resolution_hz: float) -> list[tuple[float, float]]:
    """The bands (Hz) a narrow mode of `cfg`'s optic can touch: each search range widened
    by the Hann kernel's reach."""
    return mode_bands(cfg.sus, _REACH_BINS * resolution_hz)


def _cells(cfg: OpticConfig, param: str, resolution_hz: float) -> float:
    dof, lo, hi = MODE_SEARCH[param]
    f0 = cfg.sus.uncoupled_frequencies_hz()[dof]
    return (hi - lo) * f0 / max(resolution_hz, lo * f0 / cfg.sus.Q[dof])


def search(data: FitData, cfg: OpticConfig, values: Mapping[str, float],
           free: Sequence[str] = (), unit: float = 1.0) -> tuple[dict[str, float], float]:
    """Start values of ``bounce_roll`` for `data`, around the nominal model at `values`.

    Parameters
    ----------
    data : FitData
        The measurement, its bins in the modes' bands included (:func:`bands`).
    cfg : OpticConfig
    values : mapping of str to float
        The refitted nominal parameters.
    free : sequence of str
        Those refitted with the effect: what they can absorb of a mode is not its evidence.
    unit : float
        The drop in chi^2 one fitted parameter makes in pure noise (the residuals' scale,
        tails and bin correlation, as ``diagnose`` weighs its likelihood ratios).

    Returns
    -------
    start : dict
        ``vertical``, ``f_vertical_hz``, ``roll``, ``f_roll_hz``, ``roll_angle``.
    path : float
        How far the modes' signatures turn as their frequencies sweep the search ranges
        (radians summed over trials): Davies' look-elsewhere measure (:func:`p_value`).
    """
    model = ClosedLoopModel.of(cfg, data).for_data(data)
    r = data.whiten(model(values))
    Q = _nominal_directions(data, model, values, free)
    nominal = cfg.sus.uncoupled_frequencies_hz()
    signatures = {}
    for param, (dof, lo, hi) in MODE_SEARCH.items():
        patterns = [{"roll_angle": a} for a in _ANGLES] if dof == "ROLL" else [{}]
        cols, grid = _columns(data, cfg, values, dof, patterns,
                              (lo * nominal[dof], hi * nominal[dof]))
        signatures[param] = (cols - (cols @ Q) @ Q.T, grid)
    path = sum(_path(cols) for cols, _ in signatures.values())
    start: dict[str, float] = {}
    found = dict.fromkeys(signatures, np.zeros_like(r))
    for _ in range(2):  # each mode searched again in what the other one leaves
        for param, (cols, grid) in signatures.items():
            dof = MODE_SEARCH[param][0]
            others = r - sum(v for k, v in found.items() if k != param)
            drop, x = _best(cols, others)
            drop /= unit
            k = _choice(drop, x, int(np.argmin(np.abs(grid - nominal[dof]))))
            cells = _cells(cfg, param, data.resolution_hz)
            coupling = "vertical" if dof == "VERT" else "roll"
            if drop[k] < stats.chi2.isf(_UNSEEN_P / cells, x.shape[1]):
                # nothing there: the fit starts this mode uncoupled at its nominal frequency
                start[param], start[coupling] = nominal[dof], 0.0
                found[param] = np.zeros_like(r)
                continue
            start[param] = float(grid[k])
            found[param] = x[k] @ cols[k]
            if dof == "VERT":
                start[coupling] = float(x[k, 0])
            else:
                start[coupling], start["roll_angle"] = _rank_one(x[k])
    return start, path


def p_value(lr: float, dof: int, path: float) -> float:
    """Davies' (1987) bound on the chance that noise alone gives likelihood ratio `lr` at
    the best of a search: ``P(chi2_dof > lr) + path lr^((dof-1)/2) e^(-lr/2) /
    (2^(dof/2) Gamma(dof/2))``, with `path` the search's :func:`search` path. A mode seen
    only through its compliance below resonance hardly turns as its frequency sweeps, and
    is charged little for the search; one seen at its peak is charged for every width."""
    dof = max(dof, 1)
    upcross = path * math.exp((dof - 1) / 2 * math.log(max(lr, 1e-300)) - lr / 2
                              - dof / 2 * math.log(2) - math.lgamma(dof / 2))
    return float(min(1.0, stats.chi2.sf(lr, dof) + upcross))


def _path(cols: NDArray[np.float64]) -> float:
    """Angle the first pattern's (unit) signature turns through along the trial grid."""
    u = cols[:, 0] / np.maximum(np.linalg.norm(cols[:, 0], axis=1, keepdims=True), 1e-300)
    return float(np.sum(np.arccos(np.clip(np.abs(np.sum(u[1:] * u[:-1], axis=1)), 0, 1))))


def _nominal_directions(data: FitData, model: Callable[[Mapping[str, float]], NDArray],
                        values: Mapping[str, float], free: Sequence[str]
                        ) -> NDArray[np.float64]:
    """Orthonormal basis of what the free nominal parameters change (whitened)."""
    base = data.whiten(model(values))
    cols = []
    for name in free:
        step = {**values, name: values[name] * (1 + 1e-4)}
        cols.append((data.whiten(model(step)) - base) / 1e-4)
    if not cols:
        return np.zeros((base.size, 0))
    u, sv, _ = np.linalg.svd(np.array(cols).T, full_matrices=False)
    return u[:, sv > 1e-9 * sv.max()]


def _choice(drop: NDArray[np.float64], x: NDArray[np.float64], at_nominal: int) -> int:
    """The trial frequency to start from: the best one with physical couplings (a product
    of two small fractions, below 1), unless the nominal frequency fits about as well (a
    mode seen only through its compliance below resonance leaves its frequency free)."""
    drop = np.where(np.abs(x).max(axis=1) < 1.0, drop, -np.inf)
    best = int(np.argmax(drop))
    return at_nominal if drop[best] - drop[at_nominal] < _FLAT else best


def _columns(data: FitData, cfg: OpticConfig, values: Mapping[str, float], dof: str,
             patterns: Sequence[dict], band: tuple[float, float]
             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Whitened change of the data's bins per unit coupling of each pattern, for every trial
    frequency in `band`: shape (trials, patterns, residuals), and the trial frequencies.
    Every used bin counts: below its resonance a mode also adds its static compliance."""
    res = data.resolution_hz
    sus = with_params(cfg.sus, {k: v for k, v in values.items() if k in FIT_PARAMS})
    plant = Plant.from_params(sus, replace(cfg, sus=sus).mechanics())
    width = band[0] / sus.Q[dof]
    step = 0.25 * max(res, width)
    grid = np.arange(band[0], band[1] + step / 2, step)
    f = data.frequency_hz
    used = data.mask.any(axis=(1, 2))
    near = (f > band[0] - _REACH_BINS * res) & (f < band[1] + _REACH_BINS * res)
    # the Hann kernel sampled finely next to the band, its two-point rule elsewhere (an LPM
    # estimate's own kernel is left to the fit: the search only has to start it nearby)
    fine = hann_kernel(res, width) if res > 0 else (np.zeros(1), np.ones(1))
    groups = [(np.flatnonzero(used & near), *fine),
              (np.flatnonzero(used & ~near), *_two_point(res))]
    rows = [DOFS.index(x) for x in data.responses]
    cols = [DOFS.index(x) for x in data.excited]
    loops = [_loop_at(cfg, plant, f[bins, None] + res * d) for bins, d, _ in groups]
    out = np.zeros((grid.size, len(patterns), 2 * data.bins))
    zero = data.whiten(np.zeros(data.H.shape, dtype=complex))  # whiten is affine in the model
    for p, pattern in enumerate(patterns):
        coupled = with_effect(plant, sus, "bounce_roll", {"vertical": 1.0, "roll": 1.0,
                                                          **pattern})
        j = coupled.mechanics.index(dof)
        c = np.outer(plant.input_matrix @ coupled.sensing[:, j],
                     coupled.actuation[j] @ plant.output_matrix)
        parts = [(bins, w, _first_order(loop, c, rows, cols), loop[3])
                 for (bins, _, w), loop in zip(groups, loops, strict=True)]
        for g, f0 in enumerate(grid):
            dT = np.zeros(data.H.shape, dtype=complex)
            for bins, w, B, s in parts:
                h = 1 / (coupled.mechanics.M[j, j] * (s**2 + s * 2 * np.pi * f0 / sus.Q[dof]
                                                      + (2 * np.pi * f0) ** 2))
                dT[bins] = np.einsum("k,bkij->bij", w, B * h[..., None, None])
            out[g, p] = zero - data.whiten(dT)
    return out, grid


def _loop_at(cfg: OpticConfig, plant: Plant, at: NDArray[np.float64]
             ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The loop at frequencies `at` (bins, points): sensitivity ``(1 - P K)^-1``, the
    controller, the drive's delay and pole, and ``s``."""
    flat = at.ravel()
    s = 2j * np.pi * flat
    K = cfg.loop().controller(flat)[:, :, None] * np.eye(len(DOFS))
    S = np.linalg.inv(np.eye(len(DOFS)) - plant.response(flat) @ K)
    drive = np.exp(-s * plant.delay_s) / (1 + s / (2 * np.pi * plant.drive_pole_hz))
    return S, K, drive, s.reshape(at.shape)


def _first_order(loop: tuple[NDArray, NDArray, NDArray, NDArray], c: NDArray[np.float64],
                 rows: list[int], cols: list[int]) -> NDArray[np.complex128]:
    """``B`` of ``dT = B h``: the closed loop's first-order response to a plant term ``c h``
    (c the coupling pattern in the DOF basis, h the mode's response)."""
    S, K, drive, s = loop
    B = (S @ (c[None] * drive[:, None, None]) @ K @ S)[:, rows][:, :, cols]
    return B.reshape(*s.shape, len(rows), len(cols))


def _two_point(res: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """ClosedLoopModel's rule away from narrow features: f +- res / sqrt(3), or f itself."""
    if res <= 0:
        return np.zeros(1), np.ones(1)
    return np.array([-1, 1]) / math.sqrt(3.0), np.array([0.5, 0.5])


def _best(cols: NDArray[np.float64], r: NDArray[np.float64]
          ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Least-squares couplings of each trial's columns to the residual `r`, and the drop in
    chi^2 each makes."""
    A = np.einsum("gpn,gqn->gpq", cols, cols)
    b = np.einsum("gpn,n->gp", cols, r)
    x = np.linalg.solve(A + 1e-30 * np.eye(A.shape[1]), b[..., None])[..., 0]
    return np.einsum("gp,gp->g", x, b), x


def _rank_one(x: NDArray[np.float64]) -> tuple[float, float]:
    """ROLL's coupling and pattern angle from its three linear components: the PIT-like,
    YAW-like and mixed (angle pi/4) patterns' couplings, as the dominant term of the
    symmetric 2x2 coupling they make."""
    zz, yy, mixed = x
    # the mixed pattern is (z + y)(z + y)^T / 2: it adds mixed/2 to zz, yy and the cross term
    C = np.array([[zz + mixed / 2, mixed / 2], [mixed / 2, yy + mixed / 2]])
    lam, vec = np.linalg.eigh(C)
    k = int(np.argmax(np.abs(lam)))
    return float(lam[k]), float(math.atan2(vec[1, k], vec[0, k]) % math.pi)
