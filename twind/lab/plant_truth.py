"""A real suspension as the published model's own matrices perturbed: masses, stiffnesses
and damping changed together, several modes moved at once in shapes of their own, and which
model mode became which true mode, tracked along the way.

The models KAGRA publishes (``twind/configs/kagra/*_safe.mat``) hold a second-order block:
rows of ``A`` with a single 1 are positions whose derivative is a velocity state
(``dp_i/dt = v_i``), and each velocity's row is ``-K' p - C' v + B u`` with ``K' = M^-1 K``
the mass-normalised stiffness and ``C'`` the damping. :func:`suspension` finds that block in
any model (and refuses a model without one); :class:`Perturbation` changes it as real
suspensions differ from their models: each DOF's mass (its rows of ``K'``, ``C'`` and ``B``
divided by ``1 + dm``), its stiffness (``K' -> S K' S``, ``S`` diagonal: its own term and
its couplings scaled), the couplings between DOFs (the springs and dampers of two coupled
DOFs turned: ``K' -> T^-1 K' T``, ``C' -> T^-1 C' T`` with ``T`` a rotation in
mass-normalised coordinates: mode shapes change and modes mix) and the damping
(``C' -> G C' G``: Qs change). Each keeps a suspension of masses, springs and dampers one:
a term added to one side of ``K'`` alone (``K' (I + D)`` with ``D`` off-diagonal) is a
circulatory force, which makes the models' modes of Q 1e4-5e5 unstable at a thousandth of
their stiffness. Nothing here uses the modal form the diagnosis fits.

:func:`track` follows every pole from the model (``t = 0``) to the truth (``t = 1``) in small
steps, each step's poles matched to the last by nearness and eigenvector overlap (the step
halved where that is ambiguous), so that the model mode each true mode came from is known.
:func:`correspondence` states it per model mode, with the shapes' MAC over the measured
elements and whether the true mode is visible above the sensors' noise;
:func:`draw_truth` scales a random perturbation until the wanted number of visible modes
moved.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from twind.errors import TwindError
from twind.model.statespace import StateSpace

MOVED = 0.02
"""A true mode this far (relative) from its model mode has moved."""
VISIBLE = 3.0
"""A mode is visible where its peak exceeds the sensor's noise floor this many times in an
element coherent there."""
DEGENERATE = 1e-6
"""Poles closer than this (relative) are one degenerate mode: their eigenvectors are any
basis of a shared space."""
Q_LIMIT = 1e7
"""No true mode is narrower than this Q (the models' narrowest are 5e5): a perturbation that
makes one is unstable or undamped, and is scaled down."""
STEPS = 64
"""Steps from the model to the truth (each halved where the matching is ambiguous)."""
MAX_HALVINGS = 10


class SuspensionError(TwindError):
    """A model without the second-order block a perturbation changes."""


@dataclass(frozen=True, eq=False)
class Suspension:
    """The second-order block of a state-space model.

    Attributes
    ----------
    model : StateSpace
    position, velocity : ndarray of int
        Each DOF's position state and velocity state (``dp/dt = v``).
    body : ndarray of bool
        The DOFs whose velocity row is not zero (the others are free: the ground's
        displacements, driven by accelerations alone).
    """

    model: StateSpace
    position: NDArray[np.int64]
    velocity: NDArray[np.int64]
    body: NDArray[np.bool_]

    @property
    def dofs(self) -> int:
        """The number of position-velocity pairs."""
        return self.position.size

    @property
    def stiffness(self) -> NDArray[np.float64]:
        """``K'``: the velocity rows' terms in the positions, negated."""
        return -self.model.a[np.ix_(self.velocity, self.position)]

    @property
    def damping(self) -> NDArray[np.float64]:
        """``C'``: the velocity rows' terms in the velocities, negated."""
        return -self.model.a[np.ix_(self.velocity, self.velocity)]

    @property
    def states(self) -> NDArray[np.int64]:
        """The body DOFs' states: positions, then velocities."""
        return np.concatenate([self.position[self.body], self.velocity[self.body]])

    def perturbed(self, p: Perturbation) -> StateSpace:
        """The model with `p` applied to its second-order block (every other state, input
        and output as they were)."""
        t = self.rotation(p.coupling)
        s = np.sqrt(1.0 + p.stiffness)
        e = np.exp(p.damping / 2)
        inv_m = 1.0 / (1.0 + p.mass)
        k = inv_m[:, None] * s[:, None] * self._rotated(self.stiffness, t) * s[None, :]
        c = inv_m[:, None] * e[:, None] * self._rotated(self.damping, t) * e[None, :]
        a = self.model.a.copy()
        a[np.ix_(self.velocity, self.position)] = -k
        a[np.ix_(self.velocity, self.velocity)] = -c
        b = self.model.b.copy()
        b[self.velocity] *= inv_m[:, None]
        return replace(self.model, a=a, b=b, source=f"{self.model.source} (perturbed)")

    def rotation(self, angles: NDArray[np.float64]) -> NDArray[np.float64]:
        """The product of a rotation by ``angles[i, j]`` (radians) between DOFs ``i`` and
        ``j`` for every nonzero term: a rotation in mass-normalised coordinates, the masses'
        ratio ``m_j / m_i = K'_ij / K'_ji`` read from the pair's own coupling (``M K'``
        is symmetric), so that ``T^T M T = M``."""
        k = self.stiffness
        out = np.eye(self.dofs)
        for i, j in zip(*np.nonzero(angles), strict=True):
            r = math.sqrt(k[i, j] / k[j, i])
            g = np.eye(self.dofs)
            g[i, i] = g[j, j] = math.cos(angles[i, j])
            g[i, j], g[j, i] = r * math.sin(angles[i, j]), -math.sin(angles[i, j]) / r
            out = out @ g
        return out

    def _rotated(self, m: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.float64]:
        """``T^-1 m T`` over the DOFs, the free DOFs' columns (the ground's) ``T^-1 m``:
        the body's springs or dampers turned by ``T``, its sensors and actuators not."""
        return np.linalg.solve(t, m) @ t

    def shares(self) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """The model's poles and how much each DOF's mass moves each: ``|w_i v_i|`` over
        the DOF's velocity state, with ``w`` and ``v`` the pole's left and right
        eigenvectors (``w v = 1``), the pole's relative change per relative change of that
        mass."""
        s = self.states
        lam, v = np.linalg.eig(self.model.a[np.ix_(s, s)])
        w = np.linalg.inv(v)
        share = np.zeros((lam.size, self.dofs))
        rows = np.flatnonzero(self.body)
        m = rows.size
        share[:, rows] = np.abs(w[:, m:] * v[m:].T)
        return lam, share

    def poles(self, p: Perturbation) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """The perturbed block's poles and unit eigenvectors (columns): every pole of the
        model but the free DOFs' zeros and the other states' own."""
        s = self.states
        w, v = np.linalg.eig(self.perturbed(p).a[np.ix_(s, s)])
        return w, v / np.linalg.norm(v, axis=0)


def suspension(model: StateSpace) -> Suspension:
    """The second-order block of `model`.

    A position is a state whose row of ``A`` holds a single 1 (in the column of its
    velocity) and no input; a pair is kept while its velocity's row depends on the kept
    pairs' states alone (so that no other state, a filter's or a servo's, drives the block).

    Raises
    ------
    SuspensionError
        If no such pair has a stiffness or a damping: a model that is not masses, springs
        and dampers cannot be perturbed as a suspension.
    """
    a, b = model.a, model.b
    pos, vel = [], []
    for i in range(a.shape[0]):
        nz = np.flatnonzero(a[i])
        if nz.size == 1 and a[i, nz[0]] == 1.0 and nz[0] != i and not b[i].any():
            pos.append(i)
            vel.append(int(nz[0]))
    pairs = [(p, v) for p, v in zip(pos, vel, strict=True)
             if v not in pos and vel.count(v) == 1]
    while True:
        states = {s for pair in pairs for s in pair}
        kept = [(p, v) for p, v in pairs if set(np.flatnonzero(a[v]).tolist()) <= states]
        if len(kept) == len(pairs):
            break
        pairs = kept
    position = np.array([p for p, _ in pairs], dtype=np.int64)
    velocity = np.array([v for _, v in pairs], dtype=np.int64)
    body = np.array([a[v].any() for v in velocity], dtype=bool)
    if not body.any():
        msg = (f"{model.source}: no second-order block (positions whose derivative is a "
               "velocity state, velocities driven by -K' p - C' v + B u alone): only a model "
               "of masses, springs and dampers can be perturbed as a suspension")
        raise SuspensionError(msg)
    return Suspension(model, position, velocity, body)


@dataclass(frozen=True)
class Perturbation:
    """How a real suspension differs from its model, per DOF of the second-order block.

    Attributes
    ----------
    mass : ndarray, shape (dofs,)
        Each DOF's relative mass change ``dm`` (rows of ``K'``, ``C'``, ``B`` over
        ``1 + dm``).
    stiffness : ndarray, shape (dofs,)
        ``d``: ``K' -> S K' S``, ``S = diag(sqrt(1 + d))`` (each DOF's own stiffness times
        ``1 + d``, its couplings by the geometric mean of its and its partner's).
    coupling : ndarray, shape (dofs, dofs)
        Angles (radians) of the rotations between coupled DOFs that turn the springs and
        dampers (:meth:`Suspension.rotation`): ``K' -> T^-1 K' T``, ``C' -> T^-1 C' T``.
    damping : ndarray, shape (dofs,)
        ``g``: ``C' -> G C' G``, ``G = diag(exp(g / 2))``.
    """

    mass: NDArray[np.float64]
    stiffness: NDArray[np.float64]
    coupling: NDArray[np.float64]
    damping: NDArray[np.float64]

    def scaled(self, t: float) -> Perturbation:
        """`t` times this perturbation: its path from the model (0) to it (1)."""
        return Perturbation(t * self.mass, t * self.stiffness, t * self.coupling,
                            t * self.damping)

    @staticmethod
    def none(dofs: int) -> Perturbation:
        """No change."""
        return Perturbation(np.zeros(dofs), np.zeros(dofs), np.zeros((dofs, dofs)),
                            np.zeros(dofs))

    def to_json(self) -> dict:
        """Its nonzero terms, by DOF (the pair's index in :class:`Suspension`)."""
        i, j = np.nonzero(self.coupling)
        return {"mass": {str(k): float(x) for k, x in enumerate(self.mass) if x},
                "stiffness": {str(k): float(x) for k, x in enumerate(self.stiffness) if x},
                "coupling": [[int(a), int(b), float(self.coupling[a, b])]
                             for a, b in zip(i, j, strict=True)],
                "damping": {str(k): float(x) for k, x in enumerate(self.damping) if x}}


def draw(sus: Suspension, rng: np.random.Generator, active: int = 4, couplings: int = 6,
         weights: NDArray[np.float64] | None = None) -> Perturbation:
    """A random perturbation of `sus`: a few DOFs changed much, the others a little.

    Every body DOF's mass and stiffness change by about 1 % (damping 20 %); `active` of
    them by -40 to +80 % (mass), -50 to +50 % (stiffness) and a factor 0.3-3 (damping).
    `couplings` random pairs of coupled DOFs (``K'_ij`` and ``K'_ji`` of one sign), and
    every such pair an active DOF belongs to, are turned by about 0.1 rad. The active DOFs
    are drawn in proportion to `weights` (per DOF; default uniform).
    """
    m = sus.dofs
    body = np.flatnonzero(sus.body & (np.diag(sus.stiffness) > 0))
    odds = np.ones(body.size) if weights is None else weights[body] + 1e-3 * weights.max()
    chosen = rng.choice(body, size=min(active, body.size), replace=False, p=odds / odds.sum())
    on = np.zeros(m, dtype=bool)
    on[body] = True
    mass = np.where(on, rng.normal(0, 0.01, m), 0.0)
    mass[chosen] = rng.uniform(-0.4, 0.8, chosen.size)
    diag = np.where(on, rng.normal(0, 0.01, m), 0.0)
    diag[chosen] = rng.uniform(-0.5, 0.5, chosen.size)
    damping = np.where(on, rng.normal(0, 0.2, m), 0.0)
    damping[chosen] = rng.uniform(math.log(0.3), math.log(3.0), chosen.size)
    k = sus.stiffness
    pairs = np.argwhere(np.triu(k * k.T > 0, 1) & on[:, None] & on[None, :])
    e = np.zeros((m, m))
    for i, j in pairs[rng.choice(len(pairs), size=min(couplings, len(pairs)), replace=False)]:
        e[i, j] = rng.normal(0, 0.1)
    for i, j in pairs[np.isin(pairs, chosen).any(axis=1)]:
        e[i, j] = rng.normal(0, 0.1)
    return Perturbation(mass, diag, e, damping)


# ----------------------------------------------------------------------------- tracking
@dataclass(frozen=True)
class Tracked:
    """Every pole of the block followed from the model (``t = 0``) along a perturbation.

    Attributes
    ----------
    t : ndarray, shape (steps,)
    poles : ndarray, shape (steps, poles)
        Column k: the model's pole k along the path.
    ambiguous : ndarray of bool, shape (poles,)
        Poles whose matching stayed ambiguous at the smallest step (not a degenerate
        partner's).
    """

    t: NDArray[np.float64]
    poles: NDArray[np.complex128]
    ambiguous: NDArray[np.bool_]


def track(sus: Suspension, p: Perturbation, steps: int = STEPS) -> Tracked:
    """Follow each pole of `sus` from the model to `p` applied (see the module's
    docstring).

    Parameters
    ----------
    sus : Suspension
    p : Perturbation
    steps : int
        Uniform steps in t, each halved (up to :data:`MAX_HALVINGS` times) while the
        matching is ambiguous.

    Returns
    -------
    Tracked
    """
    lam, vec = sus.poles(p.scaled(0.0))
    ts, out = [0.0], [lam]
    ambiguous = np.zeros(lam.size, dtype=bool)
    for k in range(steps):
        t0, t1 = k / steps, (k + 1) / steps
        lam, vec, flagged = _advance(sus, p, t0, t1, lam, vec, ts, out, 0)
        ambiguous |= flagged
    return Tracked(np.array(ts), np.array(out), ambiguous)


def _advance(sus: Suspension, p: Perturbation, t0: float, t1: float,
             lam: NDArray, vec: NDArray, ts: list, out: list, depth: int
             ) -> tuple[NDArray, NDArray, NDArray]:
    """One step of :func:`track` (halved while ambiguous): the poles at `t1` in the order
    of those at `t0`, appended to `ts` and `out`."""
    new, new_vec = sus.poles(p.scaled(t1))
    order, unsure = _matched(lam, vec, new, new_vec)
    if unsure.any() and depth < MAX_HALVINGS:
        mid = (t0 + t1) / 2
        lam, vec, a = _advance(sus, p, t0, mid, lam, vec, ts, out, depth + 1)
        lam, vec, b = _advance(sus, p, mid, t1, lam, vec, ts, out, depth + 1)
        return lam, vec, a | b
    ts.append(t1)
    out.append(new[order])
    return new[order], new_vec[:, order], unsure


def _matched(lam: NDArray, vec: NDArray, new: NDArray, new_vec: NDArray
             ) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """The new pole each old one became (nearest and most overlapping, jointly), and
    which old poles had a rival nearly as good that is not a degenerate partner."""
    scale = np.maximum(np.abs(lam), 1e-12)[:, None]
    cost = np.abs(lam[:, None] - new[None, :]) / scale + 1 - np.abs(vec.conj().T @ new_vec)
    rows, cols = linear_sum_assignment(cost)
    order = np.empty(lam.size, dtype=np.int64)
    order[rows] = cols
    partner = np.abs(lam[:, None] - lam[None, :]) <= DEGENERATE * scale
    taken = np.zeros_like(partner)
    taken[np.arange(lam.size), order] = True
    rivals = np.where(partner.astype(int) @ taken.astype(int) > 0, np.inf, cost).min(axis=1)
    unsure = rivals < 3 * cost[np.arange(lam.size), order]
    return order, unsure


# ----------------------------------------------------------------------------- the truth
@dataclass(frozen=True)
class View:
    """What a measurement sees of a model: its elements and its noise.

    Attributes
    ----------
    inputs, outputs : tuple of str
        The model inputs driven and outputs read.
    floor : ndarray, shape (outputs, inputs)
        Each output's sensor noise over each input's excitation (ASD ratio: the element's
        noise floor).
    band : (float, float)
        The measured band (Hz).
    resolution_hz : float
    holes : tuple of (int, float, float)
        An output made incoherent over a band (lo, hi Hz).
    """

    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    floor: NDArray[np.float64]
    band: tuple[float, float]
    resolution_hz: float
    holes: tuple[tuple[int, float, float], ...] = ()

    def in_band(self, f_hz: float) -> bool:
        """Whether `f_hz` lies in the measured band."""
        return self.band[0] <= f_hz <= self.band[1]

    def visible(self, model: StateSpace, poles: NDArray[np.complex128],
                residues: NDArray[np.complex128]) -> NDArray[np.bool_]:
        """Whether each mode of `model` (its pole and its residues over the elements) stands
        :data:`VISIBLE` times above the noise floor in an element coherent at its frequency
        (the response there above the floor, out of every hole): its peak taken as the
        residue over the larger of its half-width and a bin."""
        f = np.abs(poles) / (2 * math.pi)
        h = np.abs(model.response(f, self.inputs, self.outputs))
        width = np.maximum(-poles.real, 2 * math.pi * self.resolution_hz)
        peak = np.abs(residues) / width[:, None, None]
        ok = (h >= self.floor) & (peak >= VISIBLE * self.floor)
        for row, lo, hi in self.holes:
            ok[(f >= lo) & (f <= hi), row] = False
        return ok.any(axis=(1, 2)) & (f >= self.band[0]) & (f <= self.band[1])


@dataclass(frozen=True)
class ModeTruth:
    """A model mode and the true mode it became.

    Attributes
    ----------
    model_f_hz, model_q, true_f_hz, true_q : float
    mac : float
        Of the model's and the truth's residues over the measured elements (a degenerate
        model mode's: of its group's summed residues).
    visible : bool
        The true mode stands above the noise in a coherent element.
    in_band : bool
        Its true frequency lies in the measured band.
    degenerate : int
        How many model poles share its frequency (1: none but itself).
    """

    model_f_hz: float
    model_q: float
    true_f_hz: float
    true_q: float
    mac: float
    visible: bool
    in_band: bool
    degenerate: int = 1
    ambiguous: bool = False

    @property
    def shift(self) -> float:
        """``true / model - 1``."""
        return self.true_f_hz / self.model_f_hz - 1

    @property
    def moved(self) -> bool:
        """It moved by :data:`MOVED` or more and is visible."""
        return bool(abs(self.shift) >= MOVED and self.visible)

    def to_json(self) -> dict:
        """Its fields and its shift (%)."""
        return {"model_f_hz": self.model_f_hz, "model_q": self.model_q,
                "true_f_hz": self.true_f_hz, "true_q": self.true_q,
                "shift_percent": 100 * self.shift, "mac": self.mac, "visible": self.visible,
                "in_band": self.in_band, "degenerate": self.degenerate,
                "ambiguous": self.ambiguous, "moved": self.moved}


def residues(sus: Suspension, p: Perturbation, inputs: Sequence[str],
             outputs: Sequence[str]) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """Every pole of the perturbed block and its residue over `outputs` x `inputs`.

    The block is fed by the free DOFs and feeds the other states, and neither feeds it back,
    so a pole's right eigenvector of the whole model is the block's, zero on the free DOFs
    and ``(pole - A_rr)^-1 A_rb v`` on the others, and its left one the block's, zero on the
    others and ``w A_bf (pole - A_ff)^-1`` on the free DOFs. The block's left eigenvectors
    are the rows of the inverse of its right ones: a degenerate group's residues sum to the
    group's (each alone is one choice of basis).

    Returns
    -------
    poles : ndarray, shape (n,)
    residues : ndarray, shape (n, outputs, inputs)
    """
    model = sus.perturbed(p)
    a = model.a
    b_ = sus.states
    f_ = np.concatenate([sus.position[~sus.body], sus.velocity[~sus.body]])
    r_ = np.setdiff1d(np.arange(a.shape[0]), np.concatenate([b_, f_]))
    cols = [model.input_index(x) for x in inputs]
    rows = [model.output_index(x) for x in outputs]
    lam, v = np.linalg.eig(a[np.ix_(b_, b_)])
    w = np.linalg.inv(v)
    c, bb = model.c[rows], model.b[:, cols]
    out = np.empty((lam.size, len(rows), len(cols)), dtype=complex)
    for k, pole in enumerate(lam):
        x_r = np.linalg.solve(pole * np.eye(r_.size) - a[np.ix_(r_, r_)],
                              a[np.ix_(r_, b_)] @ v[:, k])
        w_f = np.linalg.solve((pole * np.eye(f_.size) - a[np.ix_(f_, f_)]).T,
                              (w[k] @ a[np.ix_(b_, f_)]))
        out[k] = np.outer(c[:, b_] @ v[:, k] + c[:, r_] @ x_r, w[k] @ bb[b_] + w_f @ bb[f_])
    return lam, out


def mac(a: NDArray, b: NDArray) -> float:
    """The modal assurance criterion of two shapes (flattened): 1 for the same shape."""
    a, b = np.ravel(a), np.ravel(b)
    den = np.vdot(a, a).real * np.vdot(b, b).real
    return float(abs(np.vdot(a, b)) ** 2 / den) if den > 0 else math.nan


def correspondence(sus: Suspension, p: Perturbation, view: View,
                   tracked: Tracked | None = None, up_to_hz: float | None = None
                   ) -> list[ModeTruth]:
    """Each model mode (complex pole, positive frequency) up to `up_to_hz` (default: twice
    the band's top, for a mode moved into it), the true mode it became along `p`'s path,
    their MAC and the true mode's visibility in `view`. Ascending in the model's
    frequency."""
    tracked = tracked if tracked is not None else track(sus, p)
    start, r0 = _aligned(tracked.poles[0], *residues(sus, p.scaled(0.0), view.inputs,
                                                      view.outputs))
    end, r1 = _aligned(tracked.poles[-1], *residues(sus, p, view.inputs, view.outputs))
    top = 2 * view.band[1] if up_to_hz is None else up_to_hz
    keep = [i for i in np.argsort(np.abs(start))
            if start[i].imag > 0 and _f(start[i]) <= top]
    group0 = {i: _group(start, i) for i in keep}
    own = np.array([r1[_group(end, i)].sum(axis=0) for i in keep])
    seen = view.visible(sus.perturbed(p), end[keep], own)
    return [ModeTruth(_f(start[i]), _q(start[i]), _f(end[i]), _q(end[i]),
                      mac(r0[group0[i]].sum(axis=0), r1[group0[i]].sum(axis=0)), bool(v),
                      bool(view.in_band(_f(end[i]))), int(group0[i].size),
                      bool(tracked.ambiguous[i]))
            for i, v in zip(keep, seen, strict=True)]


def _aligned(poles: NDArray, lam: NDArray, res: NDArray) -> tuple[NDArray, NDArray]:
    """`lam` and `res` in the order of `poles` (the same eigenvalues, tracked)."""
    order = linear_sum_assignment(np.abs(poles[:, None] - lam[None, :]))[1]
    return lam[order], res[order]


def _group(poles: NDArray, i: int) -> NDArray[np.int64]:
    """The poles degenerate with pole `i` (itself included)."""
    return np.flatnonzero(np.abs(poles - poles[i]) <= DEGENERATE * max(abs(poles[i]), 1e-12))


def _f(pole: complex) -> float:
    return float(abs(pole) / (2 * math.pi))


def _q(pole: complex) -> float:
    return float(abs(pole) / max(-2 * pole.real, 1e-300))


# ----------------------------------------------------------------------------- drawing
@dataclass(frozen=True)
class Drawn:
    """A perturbation scaled to move the wanted modes, and its correspondence."""

    perturbation: Perturbation
    modes: list[ModeTruth]
    tries: int
    scale: float

    @property
    def moved(self) -> list[ModeTruth]:
        """The visible modes that moved 2 % or more."""
        return [m for m in self.modes if m.moved]


def draw_truth(sus: Suspension, view: View, rng: np.random.Generator,
               moved: tuple[int, int] = (5, 8), largest: float = 0.6, tries: int = 40
               ) -> Drawn:
    """A random perturbation of `sus` scaled along its path so that `moved` (at least,
    at most) of the model's modes visible in `view` move by :data:`MOVED` to `largest`,
    some by less than 10 % and some by more, no mode in the band by more than `largest`.

    Raises
    ------
    SuspensionError
        If `tries` draws do not give one.
    """
    start, res = _aligned(sus.poles(Perturbation.none(sus.dofs))[0],
                          *residues(sus, Perturbation.none(sus.dofs), view.inputs, view.outputs))
    band = [i for i in range(start.size) if start[i].imag > 0 and view.in_band(_f(start[i]))]
    groups = np.array([res[_group(start, i)].sum(axis=0) for i in band])
    seen = [i for i, v in zip(band, view.visible(sus.model, start[band], groups), strict=True)
            if v]
    weights = _aligned(start, *sus.shares())[1][seen].sum(axis=0)
    for n in range(1, tries + 1):
        raw = draw(sus, rng, active=int(rng.integers(3, 7)), weights=weights)
        tracked = track(sus, raw)
        ok = _scales(tracked, seen, band, moved, largest)
        rng.shuffle(ok)
        for k in ok[:3]:
            t = float(tracked.t[k])
            part = Tracked(tracked.t[:k + 1] / t, tracked.poles[:k + 1], tracked.ambiguous)
            p = raw.scaled(t)
            modes = correspondence(sus, p, view, part)
            if moved[0] <= sum(m.moved for m in modes) <= moved[1]:
                return Drawn(p, modes, n, t)
    msg = (f"{sus.model.source}: no perturbation in {tries} draws moved {moved[0]}-{moved[1]} "
           "visible modes")
    raise SuspensionError(msg)


def _scales(tracked: Tracked, seen: Sequence[int], band: Sequence[int],
            moved: tuple[int, int], largest: float) -> list[int]:
    """The steps of `tracked` at which `moved` of the `seen` poles shifted by
    :data:`MOVED` to `largest`, one under 10 % and one over 15 %, and none of the `band`'s
    poles by more than `largest`; every pole damped (Q at most :data:`Q_LIMIT`)."""
    f = np.abs(tracked.poles)
    shift = np.abs(f / f[0] - 1)
    damped = np.all(-2 * Q_LIMIT * tracked.poles.real > f, axis=1)
    out = []
    for k in range(1, int(np.argmin(damped)) if not damped.all() else tracked.t.size):
        s = shift[k, list(seen)]
        hit = s[s >= MOVED]
        if moved[0] <= hit.size <= moved[1] and shift[k, list(band)].max() <= largest \
                and hit.min() < 0.1 and hit.max() > 0.15:
            out.append(k)
    return out
