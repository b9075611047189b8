"""Where a mode lies: the searches that start a ``bounce_roll`` or a ``resonance`` fit.

A mode narrower than a bin (Q 1000) moves only the bins next to it, and at zero coupling its
frequency moves nothing, so a fit from zero never finds it. The search scans each mode's
frequency over :data:`~twind.model.effects.MODE_SEARCH` in steps of a quarter of a bin (or
of the mode's width, if wider) and fits its couplings linearly at each: to first order a
mode adds ``B(f) h(f; f0)`` to ``IN1/EXC``, with ``B`` smooth in f (the loop around the
coupling pattern) and ``h`` the mode's own response, so ``B`` is computed once on the Hann
kernel's points and every trial frequency costs a product. Far from the mode ``h`` is smooth
in its frequency: there every trial's column is a combination of a few shapes, and the
search works in short coordinates (:class:`_Reduced`) that keep every inner product it
takes. The best frequency of each mode, with its couplings, is where the nonlinear fit
starts.

A ``resonance`` (a mode in no list) may lie anywhere in the measured band, with any Q and
any coupling over POS/PIT/YAW/SIDE (:func:`search_resonance`). The same first-order columns
are built for each trial frequency over every bin, one per entry of the symmetric coupling
matrix, with the nominal directions projected out; the trial is judged by the best
coupling a body can make (``g g^T``: rank one, positive) over a grid of directions, and the
best trial's, refined, starts the fit.

The evidence is searched over many frequencies: its p-value carries that look-elsewhere
cost (:func:`p_value`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import optimize, stats

from twind import DOFS
from twind.analysis.identification.data import FitData
from twind.analysis.identification.model import NARROW_REACH_BINS, ClosedLoopModel, hann_kernel
from twind.analysis.identification.params import FIT_PARAMS, with_params
from twind.config import OpticConfig
from twind.loop.damping import sensitivity
from twind.model.effects import BODY_DOFS, MODE_SEARCH, mode_bands, with_effect
from twind.model.params import SOSParams
from twind.model.plant import Plant

_REACH_BINS = 3  # the Hann power kernel's reach (99.99 % of it)
_ANGLES = (0.0, math.pi / 2, math.pi / 4)  # ROLL's PIT-like, YAW-like and mixed pattern
_FLAT = 4.0  # chi^2 a trial frequency must gain over the nominal one to be preferred
_SHAPE_TOL = 1e-10  # singular values kept of a mode's response far from it, relative
_UNSEEN_P = 0.05
"""A mode whose best couplings gain less than the noise would at this false-alarm
probability (over the frequencies searched) starts uncoupled at its nominal frequency."""


def bands(cfg: OpticConfig, resolution_hz: float) -> list[tuple[float, float]]:
    """The bands (Hz) a narrow mode of `cfg`'s optic can touch: each search range widened
    by the Hann kernel's reach.

    Parameters
    ----------
    cfg : OpticConfig
    resolution_hz : float
        The measurement's bin width (Hz).

    Returns
    -------
    list of (float, float)
        (lowest, highest) of each band (Hz): VERT's, then ROLL's.
    """
    return mode_bands(cfg.sus, _REACH_BINS * resolution_hz)


def _cells(cfg: OpticConfig, param: str, resolution_hz: float) -> float:
    dof, lo, hi = MODE_SEARCH[param]
    f0 = cfg.sus.uncoupled_frequencies_hz()[dof]
    return (hi - lo) * f0 / max(resolution_hz, lo * f0 / cfg.sus.Q[dof])


def search(data: FitData, cfg: OpticConfig, values: Mapping[str, float],
           free: Sequence[str] = (), unit: float = 1.0, effect: str | None = None
           ) -> tuple[dict[str, float], float]:
    """Start values of ``bounce_roll`` for `data`, around the nominal model at `values`
    (with `effect`, already found, at its values there).

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
    effect : str, optional
        Effects already in the model (a catalogue entry or a combination).

    Returns
    -------
    start : dict
        ``vertical``, ``f_vertical_hz``, ``roll``, ``f_roll_hz``, ``roll_angle``.
    path : float
        How far the modes' signatures turn as their frequencies sweep the search ranges
        (radians summed over trials): Davies' look-elsewhere measure (:func:`p_value`).
    """
    model = ClosedLoopModel.of(cfg, data, effect).for_data(data)
    r = data.whiten(model(values))
    Q = _nominal_directions(data, model, values, free)
    sus, plant = _plant(cfg, values, effect)
    nominal = cfg.sus.uncoupled_frequencies_hz()
    signatures = {}
    for param, (dof, lo, hi) in MODE_SEARCH.items():
        patterns = [{"roll_angle": a} for a in _ANGLES] if dof == "ROLL" else [{}]
        cols, grid, red = _columns(data, cfg, plant, sus, dof, patterns,
                                   (lo * nominal[dof], hi * nominal[dof]), Q)
        q = red.to(Q.T).T
        for p in range(len(patterns)):  # the nominal parameters' part is not the mode's
            cols[:, p] -= (cols[:, p] @ q) @ q.T
        signatures[param] = (cols, grid, red)
    path = sum(_path(cols) for cols, _, _ in signatures.values())
    start: dict[str, float] = {}
    found = dict.fromkeys(signatures, np.zeros_like(r))
    for _ in range(2):  # each mode searched again in what the other one leaves
        for param, (cols, grid, red) in signatures.items():
            dof = MODE_SEARCH[param][0]
            others = red.to(r - sum(v for k, v in found.items() if k != param))
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
            found[param] = red.back(x[k] @ cols[k])
            if dof == "VERT":
                start[coupling] = float(x[k, 0])
            else:
                start[coupling], start["roll_angle"] = _rank_one(x[k])
    return start, path


def _plant(cfg: OpticConfig, values: Mapping[str, float], effect: str | None
           ) -> tuple[SOSParams, Plant]:
    """The suspension and the plant of the model at `values` (with `effect`)."""
    sus = with_params(cfg.sus, {k: v for k, v in values.items() if k in FIT_PARAMS})
    plant = cfg.plant(sus)
    if effect:
        plant = with_effect(plant, sus, effect,
                            {k: v for k, v in values.items() if k not in FIT_PARAMS})
    return sus, plant


def p_value(lr: float, dof: int, path: float) -> float:
    """Davies' (1987) bound on the chance that noise alone gives likelihood ratio `lr` at
    the best of a search: ``P(chi2_dof > lr) + path lr^((dof-1)/2) e^(-lr/2) /
    (2^(dof/2) Gamma(dof/2))``, with `path` the search's :func:`search` path. A mode seen
    only through its compliance below resonance hardly turns as its frequency sweeps, and
    is charged little for the search; one seen at its peak is charged for every width.

    Parameters
    ----------
    lr : float
        The likelihood ratio at the best trial.
    dof : int
        Directions the effect adds, less the searched parameters `path` pays for (at
        least 1 is taken).
    path : float
        The search's look-elsewhere path (rad); 0 for no search.

    Returns
    -------
    float
        At most 1.
    """
    dof, lr = max(dof, 1), max(lr, 0.0)
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
    if not np.isfinite(drop[best]):  # no trial with physical couplings
        return at_nominal
    return at_nominal if drop[best] - drop[at_nominal] < _FLAT else best


@dataclass(frozen=True)
class _Reduced:
    """Short coordinates for one mode's trial columns: their entries at the bins near the
    mode as they are, the others in an orthonormal basis of what the columns (and the
    nominal directions) span there. Far from the mode its response is smooth in the mode's
    frequency, so a few shapes make every trial's: a column's inner products with any
    vector are those of its coordinates with the vector's (:meth:`to`)."""

    near: NDArray[np.int64]  # indices into the whitened residual vector
    far: NDArray[np.int64]
    basis: NDArray[np.float64]  # (m, len(far)), orthonormal rows
    size: int  # length of the whitened residual vector

    def to(self, v: NDArray[np.float64]) -> NDArray[np.float64]:
        """Coordinates of `v` (shape (..., size))."""
        return np.concatenate([v[..., self.near], v[..., self.far] @ self.basis.T], axis=-1)

    def back(self, u: NDArray[np.float64]) -> NDArray[np.float64]:
        """The vector of coordinates `u`, when it lies in their span."""
        out = np.zeros(self.size)
        out[self.near] = u[: self.near.size]
        out[self.far] = u[self.near.size :] @ self.basis
        return out


def _columns(data: FitData, cfg: OpticConfig, plant: Plant, sus: SOSParams, dof: str,
             patterns: Sequence[dict], band: tuple[float, float], Q: NDArray[np.float64]
             ) -> tuple[NDArray[np.float64], NDArray[np.float64], _Reduced]:
    """Whitened change of the data's bins per unit coupling of each pattern, for every trial
    frequency in `band`: shape (trials, patterns, coordinates) in the returned coordinates,
    and the trial frequencies. Every used bin counts: below its resonance a mode also adds
    its static compliance. As in ClosedLoopModel, a bin within NARROW_REACH_BINS of a trial
    sees the mode through the Hann kernel itself, any other through the two-point rule (also
    near the closed loop's damped modes, which the model averages over the kernel: a screen,
    there about 1.5 % off at 0.05 Hz, for the model's own fit that follows)."""
    res = data.resolution_hz
    width = band[0] / sus.Q[dof]
    step = 0.25 * max(res, width)
    grid = np.arange(band[0], band[1] + step / 2, step)
    f = data.frequency_hz
    bins = np.flatnonzero(data.mask.any(axis=(1, 2)))
    reach = NARROW_REACH_BINS * res
    is_near = (f[bins] > band[0] - reach) & (f[bins] < band[1] + reach)
    near, far = bins[is_near], bins[~is_near]
    rows = [DOFS.index(x) for x in data.responses]
    cols = [DOFS.index(x) for x in data.excited]
    coupled = [with_effect(plant, sus, "bounce_roll", {"vertical": 1.0, "roll": 1.0, **p})
               for p in patterns]
    j = coupled[0].mechanics.index(dof)
    mode = functools.partial(_mode, mass=coupled[0].mechanics.M[j, j], q=sus.Q[dof])
    patterns_c = [np.outer(plant.input_matrix @ c.sensing[:, j],
                           c.actuation[j] @ plant.output_matrix) for c in coupled]

    def first_order(at: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        loop = _loop_at(cfg, plant, at)  # B: (bins, points, patterns x responses x excited)
        B = np.stack([_first_order(loop, c, rows, cols) for c in patterns_c], axis=2)
        # the last size written out: -1 is ambiguous when no bin is near the band
        return B.reshape(*at.shape, int(np.prod(B.shape[at.ndim:]))), loop[3]

    d2, w2 = two_point(res)
    B2, s2 = first_order(f[bins, None] + res * d2)
    red, far_coords = _far(data, near, far, B2[~is_near] * w2[:, None],
                           mode(s2[~is_near][None], grid[:, None, None]), Q, len(patterns))
    out = np.empty((grid.size, len(patterns), red.near.size + red.basis.shape[0]))
    out[..., red.near.size :] = far_coords
    fine = None
    if res > 0:
        d, w = hann_kernel(res, width)
        fine = (*first_order(f[near, None] + res * d), w)
    shape = (len(patterns), len(rows), len(cols))
    two = B2[is_near] * w2[:, None]
    for chunk in np.array_split(np.arange(grid.size), max(1, grid.size // 128)):
        dT = _near(f[near], grid[chunk], two, s2[is_near], fine, mode, reach)
        z = data.whitened_change(np.moveaxis(dT.reshape(*dT.shape[:2], *shape), 2, 1), near)
        out[chunk, :, : red.near.size] = np.concatenate([z.real, z.imag], axis=-1)
    return out, grid, red


def _mode(s: NDArray[np.complex128], f0: NDArray[np.float64], mass: float, q: float
          ) -> NDArray[np.complex128]:
    """A mode's response (per unit force) at `s` when it lies at `f0` Hz."""
    w0 = 2 * np.pi * f0
    return 1 / (mass * (s**2 + s * w0 / q + w0**2))


def _near(f: NDArray[np.float64], grid: NDArray[np.float64], B2: NDArray, s2: NDArray,
          fine: tuple[NDArray, NDArray, NDArray] | None, mode: Callable, reach: float
          ) -> NDArray[np.complex128]:
    """The change of the near bins (frequencies `f`) for each trial of `grid`: the two-point
    rule (`B2` weighted, at `s2`), then the Hann kernel itself (`fine`: B, s, weights) in
    place of it within `reach` of the trial. Shape (trials, bins, patterns x elements)."""
    dT = np.einsum("gbk,bkm->gbm", mode(s2[None], grid[:, None, None]), B2)
    if fine is None:
        return dT
    Bf, sf, wf = fine
    lo = np.searchsorted(f, grid - reach, side="right")
    hi = np.searchsorted(f, grid + reach, side="left")
    for t in range(int(np.max(hi - lo, initial=0))):
        g = np.flatnonzero(lo + t < hi)
        b = lo[g] + t
        kernel = np.einsum("gk,gkm->gm", wf * mode(sf[b], grid[g, None]), Bf[b])
        dT[g, b] += kernel - np.einsum("gk,gkm->gm", mode(s2[b], grid[g, None]), B2[b])
    return dT


def _far(data: FitData, near: NDArray[np.int64], far: NDArray[np.int64], B2: NDArray,
         h: NDArray[np.complex128], Q: NDArray[np.float64], patterns: int
         ) -> tuple[_Reduced, NDArray[np.float64]]:
    """The reduced coordinates (:class:`_Reduced`) and every trial's columns in their far
    part, from the mode's response `h` (trials, far bins, points) at the far bins' points.
    Its few shapes over the far points come from an SVD of every 8th trial: ``h`` is
    analytic in the mode's frequency, which is at least NARROW_REACH_BINS away."""
    entry = np.nonzero(data.mask)[0]
    k = entry.size
    is_near = np.isin(entry, near)
    at_near, at_far = np.flatnonzero(is_near), np.flatnonzero(~is_near)
    flat = h.reshape(h.shape[0], -1)
    shapes = np.zeros((0, flat.shape[1]))
    if flat.size:  # (a measurement may lie wholly near the mode)
        _, sv, vh = np.linalg.svd(flat[::8], full_matrices=False)
        shapes = vh[sv > _SHAPE_TOL * sv[0]]
    a = flat @ shapes.conj().T  # (trials, shapes)
    dT = np.einsum("rbk,bkm->rbm", shapes.reshape(-1, *h.shape[1:]), B2)
    z = data.whitened_change(np.moveaxis(dT.reshape(*dT.shape[:2], patterns, *data.H.shape[1:]),
                                         2, 0), far)  # (patterns, shapes, entries)
    # a complex coefficient's real and imaginary parts each have their own real column
    F = np.concatenate([np.concatenate([z.real, z.imag], -1),
                        np.concatenate([-z.imag, z.real], -1)], axis=1)
    far_idx = np.concatenate([at_far, k + at_far])
    span = np.concatenate([F.reshape(-1, far_idx.size), Q[far_idx].T])
    basis = np.linalg.qr(span.T)[0].T
    red = _Reduced(np.concatenate([at_near, k + at_near]), far_idx, basis, 2 * k)
    coef = np.concatenate([a.real, a.imag], axis=1)
    return red, np.einsum("gr,prm->gpm", coef, F @ basis.T)


def _loop_at(cfg: OpticConfig, plant: Plant, at: NDArray[np.float64]
             ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The loop at frequencies `at` (bins, points): sensitivity ``(1 - P K)^-1``, the
    controller, the drive's delay and pole, and ``s``."""
    flat = at.ravel()
    s = 2j * np.pi * flat
    k = cfg.loop().controller(flat)
    S = sensitivity(plant.response(flat), k)
    K = k[:, :, None] * np.eye(len(DOFS))
    drive = np.exp(-s * plant.delay_s) / (1 + s / (2 * np.pi * plant.drive_pole_hz))
    return S, K, drive, s.reshape(at.shape)


def _first_order(loop: tuple[NDArray, NDArray, NDArray, NDArray], c: NDArray[np.float64],
                 rows: list[int], cols: list[int]) -> NDArray[np.complex128]:
    """``B`` of ``dT = B h``: the closed loop's first-order response to a plant term ``c h``
    (c the coupling pattern in the DOF basis, (4, 4) or one per point, h the mode's
    response)."""
    S, K, drive, s = loop
    c = c if c.ndim == 3 else c[None]  # a pattern that changes with frequency, or not
    B = (S @ (c * drive[:, None, None]) @ K @ S)[:, rows][:, :, cols]
    return B.reshape(*s.shape, len(rows), len(cols))


def two_point(res: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
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


# ------------------------------------------------------------------ a mode anywhere
SEARCH_Q = (8.0, 40.0)
"""The quality factors a ``resonance`` is searched with (the fit then frees its Q): a
trial's shape correlates well with a mode's of Q within a factor of ~2.5 of it."""


@dataclass(frozen=True)
class Scan:
    """Every trial frequency of a :func:`search_resonance`, one sweep per searched Q.

    Attributes
    ----------
    f_hz : tuple of ndarray
        Each sweep's trial frequencies (Hz), ascending.
    drop : tuple of ndarray
        The chi^2 each trial's best body removes, to first order (``-inf`` where that body
        would be no small attachment).
    """

    f_hz: tuple[NDArray[np.float64], ...]
    drop: tuple[NDArray[np.float64], ...]

    def plausible(self, margin: float) -> list[tuple[float, float]]:
        """The frequency ranges (Hz) whose trials remove within `margin` (chi^2) of the
        best trial's drop: where the data cannot tell the mode from the one found.

        The likelihood over a mode's frequency has several optima when the data see the
        body's mass or spring and not its peak; the curvature at the best one then says
        nothing of the others, and these ranges do."""
        best = max(float(d.max()) for d in self.drop if d.size)
        runs: list[tuple[float, float]] = []
        for f, d in zip(self.f_hz, self.drop, strict=True):
            near = np.flatnonzero(d >= best - margin)
            # consecutive trials form one range, which ends somewhere before the trials
            # either side of it: it reaches them
            for run in np.split(near, np.flatnonzero(np.diff(near) > 1) + 1):
                if run.size:
                    runs.append((float(f[max(run[0] - 1, 0)]),
                                 float(f[min(run[-1] + 1, f.size - 1)])))
        return merged(runs)


def merged(ranges: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """`ranges` (lo, hi) as disjoint ranges, ascending."""
    out: list[tuple[float, float]] = []
    for lo, hi in sorted(ranges):
        if out and lo <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], hi))
        else:
            out.append((lo, hi))
    return out


def search_resonance(data: FitData, cfg: OpticConfig, values: Mapping[str, float],
                     free: Sequence[str] = (), effect: str | None = None
                     ) -> tuple[dict[str, float], list[float], Scan]:
    """Start values of a ``resonance`` for `data`, anywhere in its band, around the nominal
    model at `values` (`free` and `effect` as in :func:`search`).

    Parameters
    ----------
    data : FitData
        The measured bins searched.
    cfg : OpticConfig
    values : mapping of str to float
        The refitted nominal parameters (and `effect`'s).
    free : sequence of str
        Those refitted with the resonance: what they can absorb of a mode is not its
        evidence.
    effect : str, optional
        Effects already in the model (a catalogue entry or a combination).

    Returns
    -------
    start : dict
        ``f_hz``, ``q`` and the couplings ``g_POS`` ... ``g_SIDE`` (the dominant rank-one
        part of the best symmetric coupling).
    paths : list of float
        Each Q's look-elsewhere path (:func:`p_value`, one search per Q).
    scan : Scan
        Every trial's drop, for the range of frequencies the data allow.
    """
    model = ClosedLoopModel.of(cfg, data, effect).for_data(data)
    r = data.whiten(model(values))
    Q = _nominal_directions(data, model, values, free)
    plant = _plant(cfg, values, effect)[1]
    trials = _Trials(data, cfg, plant, r, Q)
    idx = [plant.mechanics.index(d) for d in BODY_DOFS]
    inertia = np.sqrt(np.diag(plant.mechanics.M)[idx])
    best = (-np.inf, 0.0, 0.0, np.zeros(len(_PAIRS)))
    paths, freqs, drops = [], [], []
    for q in SEARCH_Q:
        path, f, d = 0.0, [], []
        for f0, drop, x, angle in trials.sweep(q):
            path += angle
            # a body heavier than a tenth of the optic is no small attachment: the
            # first-order columns no longer hold, and no such thing hangs on a face
            small = _relative_mass(x, inertia) < MAX_RELATIVE_MASS
            f.append(f0)
            d.append(drop if small else -np.inf)
            if drop > best[0] and small:
                best = (drop, f0, q, x)
        paths.append(path)
        freqs.append(np.array(f))
        drops.append(np.array(d))
    drop, f0, q, x = best
    C = trials.columns(f0, q)  # the best trial's direction, refined off the grid
    CQ = C @ Q
    x = _refined(C @ C.T - CQ @ CQ.T, C @ r - CQ @ trials.Qr, x, trials.seen)
    lam, g = _dominant(x)
    start = {"f_hz": f0, "q": q, **{f"g_{d}": float(v) for d, v in zip(
        BODY_DOFS, math.sqrt(abs(lam)) * g, strict=True)}}
    return start, paths, Scan(tuple(freqs), tuple(drops))


_PAIRS = [(i, j) for i in range(len(BODY_DOFS)) for j in range(i, len(BODY_DOFS))]
MAX_RELATIVE_MASS = 0.1
"""The heaviest body a search starts from, as a fraction of the optic's inertia in the DOF
it pulls hardest (its coupling's largest eigenvalue, mass-normalised)."""


def _relative_mass(x: NDArray[np.float64], inertia: NDArray[np.float64]) -> float:
    """Largest eigenvalue (absolute) of the coupling `x` normalised by the optic's inertia
    (`inertia`: square roots of its mass and moments over BODY_DOFS)."""
    C = _coupling(x)
    return float(np.abs(np.linalg.eigvalsh(C / np.outer(inertia, inertia))).max())


def _coupling(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """The symmetric coupling over BODY_DOFS whose upper entries are `x` (:data:`_PAIRS`)."""
    C = np.zeros((len(BODY_DOFS),) * 2)
    for (i, j), v in zip(_PAIRS, x, strict=True):
        C[i, j] = C[j, i] = v
    return C


def _dominant(x: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
    """The dominant eigenpair of the symmetric coupling whose upper entries are `x`
    (:data:`_PAIRS` order): a body's ``g g^T`` has one, positive."""
    lam, vec = np.linalg.eigh(_coupling(x))
    k = int(np.argmax(np.abs(lam)))
    return float(lam[k]), vec[:, k]


def _body(s: NDArray[np.complex128], f0: float, q: float) -> NDArray[np.complex128]:
    """What a unit-mass body at `f0`, `q` adds to the optic's dynamic stiffness per unit
    ``g g^T``: ``a s^2 / (s^2 + a)``, ``a = w^2 + s w / q`` (its mass below resonance, its
    spring above)."""
    w = 2 * np.pi * f0
    a = w**2 + s * w / q
    return a * s**2 / (s**2 + a)


class _Trials:
    """The first-order columns of a ``resonance`` at every trial frequency.

    The body's response is a scalar per bin, so its whitened column is a weighted sum of
    the whitened loop responses around each coupling entry, computed once at every used
    bin (two-point rule) and, for a trial narrower than two bins, on the Hann kernel's
    points of the bins near it: a trial costs a product over the entries, and every bin
    counts (below its resonance a body adds its mass, above it its spring). Near the closed
    loop's damped modes the two-point rule screens what the model averages over the kernel
    (as in :func:`_columns`)."""

    def __init__(self, data: FitData, cfg: OpticConfig, plant: Plant,
                 r: NDArray[np.float64], Q: NDArray[np.float64]) -> None:
        self.data, self.cfg, self.plant, self.r, self.Q = data, cfg, plant, r, Q
        self.lever_m = cfg.sus.radius_m  # a face point's PIT/YAW lever at the edge
        self.seen = np.array([float(d in data.excited) for d in BODY_DOFS])
        self.bins = np.flatnonzero(data.mask.any(axis=(1, 2)))
        self.f = data.frequency_hz[self.bins]
        self.res = data.resolution_hz
        self.rows = [DOFS.index(x) for x in data.responses]
        self.cols = [DOFS.index(x) for x in data.excited]
        # each used entry's bin, and where each bin's entries start (bin-major order)
        counts = data.mask[self.bins].sum(axis=(1, 2))
        self.entry_bin = np.repeat(np.arange(self.bins.size), counts)
        self.start = np.concatenate([[0], np.cumsum(counts)])
        self.Qr = Q.T @ r
        self.d2, self.w2 = two_point(self.res)
        B2, self.s2 = self._first_order(self.f[:, None] + self.res * self.d2)
        self.Z = self._whitened(B2, self.bins)  # (points, patterns, entries)
        self._fine: dict[int, NDArray] = {}
        # the finest kernel (1/16 bin) serves every trial narrower than two bins
        self.d_fine, self.w_fine = hann_kernel(self.res, 0.0) if self.res > 0 else (None, None)

    def _whitened(self, B: NDArray, at: NDArray[np.int64]) -> NDArray[np.complex128]:
        """Whitened change per unit body response of `B` (bins, points, patterns, nr, ne)
        at data bins `at`: (points, patterns, entries)."""
        return self.data.whitened_change(np.moveaxis(B, (1, 2), (0, 1)), at)

    def _first_order(self, at: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        """``B`` at points `at` (bins, points): (bins, points, patterns, responses, excited)."""
        loop = _loop_at(self.cfg, self.plant, at)
        s = loop[3].ravel()
        H = self.plant.mechanics.admittance(s)
        idx = [self.plant.mechanics.index(d) for d in BODY_DOFS]
        left = (self.plant.input_matrix @ self.plant.sensing @ H)[:, :, idx]
        right = (H @ self.plant.actuation @ self.plant.output_matrix)[:, idx, :]
        B = []
        for i, j in _PAIRS:
            c = np.einsum("pa,pb->pab", left[:, :, i], right[:, j, :])
            if i != j:
                c = c + np.einsum("pa,pb->pab", left[:, :, j], right[:, i, :])
            B.append(_first_order(loop, -c, self.rows, self.cols))
        return np.stack(B, axis=2), loop[3]

    def _fine_at(self, b: int) -> NDArray[np.complex128]:
        """The whitened loop responses on the finest Hann kernel's points of used bin `b`:
        (points, patterns, its entries)."""
        if b not in self._fine:
            B = self._first_order(self.f[b] + self.res * self.d_fine[None])[0]
            self._fine[b] = self._whitened(B, self.bins[b : b + 1])
        return self._fine[b]

    def columns(self, f0: float, q: float) -> NDArray[np.float64]:
        """A trial's whitened columns, real then imaginary parts: (patterns, 2 x entries)."""
        h = _body(self.s2, f0, q) * self.w2  # (bins, points)
        z = np.einsum("kpe,ek->pe", self.Z, h[self.entry_bin])
        if self.res > 0 and f0 / q < 2 * self.res:  # narrower than two bins: the kernel
            lo, hi = np.searchsorted(self.f, [f0 - NARROW_REACH_BINS * self.res,
                                              f0 + NARROW_REACH_BINS * self.res])
            for b in range(int(lo), int(hi)):
                sf = 2j * np.pi * (self.f[b] + self.res * self.d_fine)
                z[:, self.start[b] : self.start[b + 1]] = np.einsum(
                    "k,kpe->pe", self.w_fine * _body(sf, f0, q), self._fine_at(b))
        return np.concatenate([z.real, z.imag], axis=-1)

    def sweep(self, q: float):  # noqa: ANN201 - a generator of tuples
        """Every trial frequency at quality factor `q`, in steps of a quarter of a bin or
        of the mode's width: ``(f0, drop, couplings, angle turned since the last)``."""
        f0, top = max(self.f[0], 1e-3), self.f[-1]
        last = None
        while f0 <= top:
            C = self.columns(f0, q)
            CQ = C @ self.Q
            A = C @ C.T - CQ @ CQ.T
            b = C @ self.r - CQ @ self.Qr
            x, drop = _body_part(A, b, self.lever_m, self.seen)
            angle = 0.0 if last is None else _turn(last, (C[0], CQ[0]))
            last = (C[0], CQ[0])
            yield f0, drop, x, angle
            f0 += 0.25 * max(self.res, f0 / q)


def _body_part(A: NDArray[np.float64], b: NDArray[np.float64], lever_m: float,
               seen: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """The best coupling a body can make (``g g^T``: rank one, positive) and the drop in
    chi^2 it makes (normal equations `A`, `b` of the ten entries), over the directions of
    :data:`_DIRECTIONS`, PIT and YAW in units of `lever_m` (a point at the face's edge
    pulls at 45 degrees), those of BODY_DOFS the data do not excite zero (`seen`, 1 or 0):
    ten free entries would fit noise no body can."""
    g = _DIRECTIONS * np.array([1.0, lever_m, lever_m, 1.0]) * seen
    Y = np.stack([g[:, i] * g[:, j] for i, j in _PAIRS], axis=1)
    A, b = np.nan_to_num(A), np.nan_to_num(b)
    yb, yAy = Y @ b, np.einsum("dk,kl,dl->d", Y, A, Y)
    drop = np.where((yb > 0) & (yAy > 0), yb**2 / np.where(yAy > 0, yAy, 1.0), 0.0)
    k = int(np.argmax(drop))
    if drop[k] <= 0:
        return np.zeros(len(_PAIRS)), 0.0
    return Y[k] * yb[k] / yAy[k], float(drop[k])


def _refined(A: NDArray[np.float64], b: NDArray[np.float64], x: NDArray[np.float64],
             seen: NDArray[np.float64]) -> NDArray[np.float64]:
    """The body coupling ``g g^T`` (upper entries) of most drop in chi^2, from `x`'s, its
    components on the DOFs not `seen` held at zero."""
    lam, vec = np.linalg.eigh(_coupling(x))
    if lam[-1] <= 0:
        return x

    def coupling(g: NDArray[np.float64]) -> tuple[NDArray[np.float64], float, float]:
        g = g * seen
        y = np.array([g[i] * g[j] for i, j in _PAIRS])
        return y, float(y @ b), float(y @ A @ y)

    def loss(g: NDArray[np.float64]) -> float:
        _, yb, yAy = coupling(g)
        return -yb**2 / yAy if yb > 0 and yAy > 0 else 0.0

    g0 = math.sqrt(lam[-1]) * vec[:, -1]
    got = optimize.minimize(loss, g0, method="Nelder-Mead",
                            options={"xatol": 1e-6 * np.abs(g0).max(), "fatol": 1e-3})
    y, yb, yAy = coupling(got.x)
    return y * yb / yAy if got.fun < loss(g0) else x


def _hemisphere(n: int, seed: int = 0) -> NDArray[np.float64]:
    """`n` directions spread over half the unit sphere of POS/PIT/YAW/SIDE (a body's
    ``g`` and ``-g`` are one), the axes and their pairs among them."""
    pts = np.random.default_rng(seed).standard_normal((n, len(BODY_DOFS)))
    eye = np.eye(len(BODY_DOFS))
    pts = np.vstack([eye, [eye[i] + s * eye[j] for i in range(4) for j in range(i + 1, 4)
                           for s in (1, -1)], pts])
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    return pts


_DIRECTIONS = _hemisphere(3000)


def _turn(a: tuple, b: tuple) -> float:
    """Angle (rad) between two trials' first columns with the nominal directions projected
    out, each given as (column, its nominal components)."""
    (ca, qa), (cb, qb) = a, b
    dot = ca @ cb - qa @ qb
    na, nb = ca @ ca - qa @ qa, cb @ cb - qb @ qb
    return float(np.arccos(np.clip(abs(dot) / math.sqrt(max(na * nb, 1e-300)), 0, 1)))
