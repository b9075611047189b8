"""A plant given as a continuous state-space model: ``x' = A x + B u``, ``y = C x + D u``.

Another lab's suspension model arrives as ABCD matrices: Simulink's ``linmod``, MATLAB's
``ss``, or a Simscape export, saved to a ``.mat`` file either as one struct (``a, b, c, d``
with ``InputName`` and ``OutputName``, as KAGRA's tools save it) or as bare ``A, B, C, D``
variables. :func:`read_mat` reads both (scipy.io); :class:`StateSpace` holds the matrices with
their signal names, and :func:`modal_form` turns them into what twind fits and integrates:

* a **real block-diagonal (modal) form**, ``W^-1 A W = blkdiag(T_1, ..., T_m)``, each block
  one real pole, one complex pair (a *mode*), or a cluster of poles closer than
  :data:`MERGE` that cannot be told apart numerically (a Jordan block such as a free mass's
  double integrator, or several identical filters). The eigenvector matrix of such a model
  is singular to working precision (KAGRA's SRM: condition 1e20), so the blocks are split
  off one cluster at a time from the real Schur form by Sylvester equations (Bavely and
  Stewart 1979), each transformation well conditioned;
* each mode as a second-order section per input/output pair, ``(a s + b) / (s^2 + w s / Q
  + w^2)``: a mode whose stiffness changes keeps its numerator (its modal mass and shape)
  and moves its denominator, which is how twind refits it
  (:class:`~twind.analysis.statespace.model.PlantModel`);
* each mode's **label**: the degree of freedom that carries the largest share of it. For a
  collocated drive and sensor (a force on a body and its displacement, KAGRA's ``f_TMP`` and
  ``dispTMP``) the sections' ``b`` are the squares of the mass-normalised mode shape, so
  ``b_k / sum_k b`` is the share of that DOF's inverse mass that mode ``k`` carries: a
  number from 0 to 1 whatever the units, compared across DOFs.

:meth:`ModalForm.truncated` drops the modes above a frequency (their static part kept, so
the response below them is unchanged to first order) for an engine that integrates the model
at the model rate; the relative error it costs is measured on a grid and stated.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.io
import scipy.linalg
from numpy.typing import NDArray

from twind.errors import TwindError

MERGE = 1e-3
"""Poles closer than this (relative to their magnitude) share one block of the modal form."""

ZERO_TOL = 1e-9
"""Poles smaller than this times ``|A|`` are taken as zero (free masses, integrators)."""

CONDITION_LIMIT = 1e8
"""A modal transformation worse conditioned than this is refused: the model's poles are too
close to be separated, and its responses would not be trustworthy."""


class StateSpaceError(TwindError):
    """A state-space model that cannot be read or used."""


@dataclass(frozen=True, eq=False)
class StateSpace:
    """A continuous linear time-invariant model with named inputs and outputs.

    Attributes
    ----------
    a, b, c, d : ndarray
        ``(n, n)``, ``(n, m)``, ``(p, n)``, ``(p, m)``.
    inputs, outputs : tuple of str
        The names of the ``m`` inputs and ``p`` outputs, as the file gives them.
    source : str
        Where the matrices came from.
    """

    a: NDArray[np.float64]
    b: NDArray[np.float64]
    c: NDArray[np.float64]
    d: NDArray[np.float64]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    source: str = ""

    def __post_init__(self) -> None:
        n, m, p = self.a.shape[0], len(self.inputs), len(self.outputs)
        shapes = {"a": (n, n), "b": (n, m), "c": (p, n), "d": (p, m)}
        for name, shape in shapes.items():
            got = getattr(self, name).shape
            if got != shape:
                msg = (f"{self.source}: {name} is {got[0]}x{got[1]}, expected {shape[0]}x"
                       f"{shape[1]} ({n} states, {m} inputs, {p} outputs)")
                raise StateSpaceError(msg)
            if not np.all(np.isfinite(getattr(self, name))):
                msg = f"{self.source}: {name} holds NaN or inf"
                raise StateSpaceError(msg)
        for kind, names in (("input", self.inputs), ("output", self.outputs)):
            twice = sorted({x for x in names if names.count(x) > 1})
            if twice:
                msg = f"{self.source}: {kind}s named twice: {', '.join(twice[:5])}"
                raise StateSpaceError(msg)

    @property
    def states(self) -> int:
        """The number of states."""
        return self.a.shape[0]

    def input_index(self, name: str) -> int:
        """The index of input `name`, given whole or as its last path component (Simulink
        names signals ``model/block``)."""
        return _index(name, self.inputs, "input", self.source)

    def output_index(self, name: str) -> int:
        """The index of output `name` (whole, or its last path component)."""
        return _index(name, self.outputs, "output", self.source)

    def response(self, f_hz: NDArray[np.float64], inputs: Sequence[str],
                 outputs: Sequence[str]) -> NDArray[np.complex128]:
        """``C (sI - A)^-1 B + D`` at `f_hz`, solved directly at each frequency.

        Parameters
        ----------
        f_hz : ndarray
            Frequencies (Hz).
        inputs, outputs : sequence of str
            The columns and rows wanted.

        Returns
        -------
        ndarray of complex, shape (nf, len(outputs), len(inputs))
        """
        cols = [self.input_index(x) for x in inputs]
        rows = [self.output_index(x) for x in outputs]
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        n = self.states
        shifted = s[:, None, None] * np.eye(n) - self.a
        x = np.linalg.solve(shifted, np.broadcast_to(self.b[:, cols], (s.size, n, len(cols))))
        return self.c[rows] @ x + self.d[np.ix_(rows, cols)]


def _index(name: str, names: Sequence[str], kind: str, source: str) -> int:
    """The position of `name` among `names`, matched whole or by last path component."""
    if name in names:
        return names.index(name)
    tails = [i for i, x in enumerate(names) if x.rsplit("/", 1)[-1] == name]
    if len(tails) == 1:
        return tails[0]
    if len(tails) > 1:
        msg = f"{source}: {kind} {name!r} is ambiguous: {', '.join(names[i] for i in tails)}"
        raise StateSpaceError(msg)
    short = [x.rsplit("/", 1)[-1] for x in names]
    msg = f"{source}: no {kind} {name!r}; the model's {kind}s are {', '.join(short)}"
    raise StateSpaceError(msg)


# ------------------------------------------------------------------------------ .mat files
def read_mat(path: str | Path, variable: str | None = None) -> StateSpace:
    """A state-space model from a MATLAB ``.mat`` file (v4 to v7.2; scipy.io).

    The file holds either a struct with fields ``a, b, c, d`` (any case) and optionally
    ``InputName``, ``OutputName`` and ``Ts``, as Simulink's ``linmod`` and KAGRA's tools
    save it, or bare variables ``A, B, C, D`` (any case) with optional ``InputName`` and
    ``OutputName``. Signals without names are called ``u1 ...`` and ``y1 ...``.

    Parameters
    ----------
    path : str or Path
        The file.
    variable : str, optional
        The struct to read, when the file holds several.

    Returns
    -------
    StateSpace

    Raises
    ------
    StateSpaceError
        If the file cannot be read, holds no model, a discrete one (``Ts`` not 0), or
        matrices whose shapes do not agree.
    """
    source = str(path)
    try:
        raw = scipy.io.loadmat(source, squeeze_me=True, struct_as_record=False)
    except FileNotFoundError:
        raise StateSpaceError(f"{source}: no such file") from None
    except NotImplementedError:
        msg = (f"{source}: a MATLAB v7.3 (HDF5) file; save it with save(..., '-v7') for "
               "twind to read it")
        raise StateSpaceError(msg) from None
    except Exception as err:  # noqa: BLE001 - scipy raises several kinds on a bad file
        msg = f"{source}: not a readable .mat file ({type(err).__name__}: {err})"
        raise StateSpaceError(msg) from None
    values = {k: v for k, v in raw.items() if not k.startswith("__")}
    fields = _model_fields(values, variable, source)
    ts = fields.get("ts", 0)
    if np.size(ts) and float(np.ravel(ts)[0]) != 0:
        msg = (f"{source}: a discrete model (Ts = {float(np.ravel(ts)[0]):g} s); twind "
               "takes continuous models (Ts = 0)")
        raise StateSpaceError(msg)
    a = _matrix(fields, "a", source)
    n = a.shape[0] if a.ndim == 2 else 0
    b, c = _matrix(fields, "b", source, (n, -1)), _matrix(fields, "c", source, (-1, n))
    d = _matrix(fields, "d", source, (c.shape[0], b.shape[1]))
    inputs = _names(fields.get("inputname"), b.shape[1], "u")
    outputs = _names(fields.get("outputname"), c.shape[0], "y")
    return StateSpace(a, b, c, d, inputs, outputs, source)


def _model_fields(values: Mapping, variable: str | None, source: str) -> dict:
    """The model's fields, keyed in lower case: from struct `variable`, the one struct
    holding a, b, c and d, or the file's bare variables."""
    def lower(d: Mapping) -> dict:
        return {k.lower(): v for k, v in d.items()}

    structs = {k: v for k, v in values.items() if hasattr(v, "_fieldnames")}
    if variable is not None:
        if variable not in values:
            msg = f"{source}: no variable {variable!r}; it holds {', '.join(values)}"
            raise StateSpaceError(msg)
        v = values[variable]
        return lower({f: getattr(v, f) for f in v._fieldnames}) if hasattr(v, "_fieldnames") \
            else lower(values)
    models = [k for k, v in structs.items()
              if {"a", "b", "c", "d"} <= {f.lower() for f in v._fieldnames}]
    if len(models) == 1:
        v = structs[models[0]]
        return lower({f: getattr(v, f) for f in v._fieldnames})
    if len(models) > 1:
        msg = f"{source}: several models ({', '.join(models)}); name one (variable = ...)"
        raise StateSpaceError(msg)
    bare = lower(values)
    if {"a", "b", "c", "d"} <= set(bare):
        return bare
    msg = (f"{source}: no state-space model in it: expected a struct with fields a, b, c, d "
           f"or variables A, B, C, D; it holds {', '.join(values) or 'nothing'}")
    raise StateSpaceError(msg)


def _matrix(fields: Mapping, name: str, source: str,
            shape: tuple[int, int] | None = None) -> NDArray[np.float64]:
    """Field `name` as a 2-D real array, reshaped from what squeeze_me flattened."""
    if name not in fields:
        raise StateSpaceError(f"{source}: the model has no {name.upper()}")
    try:
        m = np.asarray(fields[name], dtype=float)
    except (TypeError, ValueError):
        raise StateSpaceError(f"{source}: {name.upper()} is not a real matrix") from None
    if shape is None:
        if m.ndim == 0:
            m = m.reshape(1, 1)
        if m.ndim != 2 or m.shape[0] != m.shape[1]:
            raise StateSpaceError(f"{source}: A is {m.shape}, not square")
        return m
    if m.ndim < 2:  # squeeze_me flattened a row or a column
        rows, cols = shape
        if not m.size:
            return np.zeros((max(rows, 0), max(cols, 0)))
        if m.size % max(rows if rows >= 0 else cols, 1):
            want = f"{rows} rows" if rows >= 0 else f"{cols} columns"
            msg = f"{source}: {name.upper()} has {m.size} entries; the model needs {want}"
            raise StateSpaceError(msg)
        m = m.reshape((rows, -1) if rows >= 0 else (-1, cols))
    return m


def _names(raw, count: int, stem: str) -> tuple[str, ...]:  # noqa: ANN001 - what scipy read
    """Signal names from a MATLAB cell array (or one string), else ``u1 ...``."""
    if raw is None:
        return tuple(f"{stem}{i + 1}" for i in range(count))
    names = [str(x) for x in np.atleast_1d(raw)]
    if len(names) != count:
        return tuple(f"{stem}{i + 1}" for i in range(count))
    return tuple(names)


# ------------------------------------------------------------------------------ modal form
@dataclass(frozen=True)
class Mode:
    """A complex pair of poles of the model: ``s^2 + w s / Q + w^2``.

    Attributes
    ----------
    index : int
        Its position among the model's modes (ascending frequency).
    f_hz : float
        Undamped natural frequency ``w / 2 pi`` (Hz).
    q : float
        Quality factor.
    label : str
        The DOF carrying the largest share of it (``""`` without shapes).
    share : float
        That share (0 to 1).
    """

    index: int
    f_hz: float
    q: float
    label: str = ""
    share: float = 0.0

    def describe(self) -> str:
        """E.g. ``4.92 Hz (Q 2015, TM P)``."""
        tag = f", {self.label}" if self.label else ""
        return f"{self.f_hz:.4g} Hz (Q {self.q:.3g}{tag})"


@dataclass(frozen=True)
class _Block:
    """A block of the modal form and its realisation ``x' = T x + B u``, ``y = C x``: a mode's
    2x2 block, a real pole, or a cluster of poles (evaluated by solving ``(sI - T) x = B``)."""

    t: NDArray[np.float64]
    b: NDArray[np.float64]
    c: NDArray[np.float64]


@dataclass(frozen=True)
class ModalForm:
    """A state-space model's responses between chosen inputs and outputs as a sum of modes
    (second-order sections) and other blocks, plus its feedthrough.

    Attributes
    ----------
    inputs, outputs : tuple of str
        Its columns and rows (names as the configuration gives them).
    modes : tuple of Mode
        The complex pairs, ascending in frequency.
    num_s, num_1 : ndarray, shape (modes, outputs, inputs)
        Each mode's numerator ``num_s s + num_1``.
    w, q : ndarray, shape (modes,)
        Each mode's ``w`` (rad/s) and Q.
    blocks : tuple
        The other blocks (real poles, clusters).
    d : ndarray, shape (outputs, inputs)
    condition : float
        The modal transformation's condition number.
    """

    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    modes: tuple[Mode, ...]
    num_s: NDArray[np.float64]
    num_1: NDArray[np.float64]
    w: NDArray[np.float64]
    q: NDArray[np.float64]
    blocks: tuple[_Block, ...]
    d: NDArray[np.float64]
    condition: float
    source: str = ""
    realisation: tuple[_Block, ...] = field(default=(), repr=False)
    """Each mode's own 2x2 block, in the order of :attr:`modes`."""

    def blocks_all(self) -> tuple[_Block, ...]:
        """Every block of the form (modes first): a realisation ``x' = T x + B u``,
        ``y = C x`` of the response but for the feedthrough :attr:`d`."""
        return (*self.realisation, *self.blocks)

    def others(self, s: NDArray[np.complex128]) -> NDArray[np.complex128]:
        """What the non-mode blocks and the feedthrough add at `s` (nf, outputs, inputs)."""
        out = np.broadcast_to(self.d, (s.size, *self.d.shape)).astype(complex)
        for blk in self.blocks:
            n = blk.t.shape[0]
            x = np.linalg.solve(s[:, None, None] * np.eye(n) - blk.t,
                                np.broadcast_to(blk.b, (s.size, *blk.b.shape)))
            out = out + blk.c @ x
        return out

    def response(self, f_hz: NDArray[np.float64]) -> NDArray[np.complex128]:
        """The model's response at `f_hz` (nf, outputs, inputs)."""
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        return self.modes_response(f_hz) + self.others(s)

    def modes_response(self, f_hz: NDArray[np.float64]) -> NDArray[np.complex128]:
        """What the modes alone answer at `f_hz` (nf, outputs, inputs)."""
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        den = 1.0 / (s[None] ** 2 + s[None] * (self.w / self.q)[:, None] + self.w[:, None] ** 2)
        return (np.einsum("kf,koi->foi", s[None] * den, self.num_s, optimize=True)
                + np.einsum("kf,koi->foi", den, self.num_1, optimize=True))

    def truncated(self, f_max_hz: float) -> tuple[ModalForm, int]:
        """The modes at or below `f_max_hz`; those above leave their static response
        (``num_1 / w^2``) in the feedthrough, so the response well below them is unchanged
        to first order in ``(f / f_mode)^2``.

        Returns
        -------
        ModalForm
        int
            The modes dropped.
        """
        keep = np.array([m.f_hz <= f_max_hz for m in self.modes], dtype=bool)
        static = np.einsum("k,koi->oi", 1.0 / self.w[~keep] ** 2, self.num_1[~keep])
        kept = (m for m, k in zip(self.modes, keep, strict=True) if k)
        modes = tuple(Mode(i, m.f_hz, m.q, m.label, m.share) for i, m in enumerate(kept))
        real = tuple(b for b, k in zip(self.realisation, keep, strict=True) if k)
        return (ModalForm(self.inputs, self.outputs, modes, self.num_s[keep], self.num_1[keep],
                          self.w[keep], self.q[keep], self.blocks, self.d + static,
                          self.condition, self.source, real),
                int((~keep).sum()))


def modal_form(ss: StateSpace, inputs: Sequence[str], outputs: Sequence[str],
               shapes: Mapping[str, tuple[str, str]] | None = None) -> ModalForm:
    """The modal form of `ss` between `inputs` and `outputs`, each mode labelled by
    `shapes`.

    Parameters
    ----------
    ss : StateSpace
    inputs, outputs : sequence of str
        Names of the model's inputs and outputs kept (whole, or last path component).
    shapes : mapping of str to (str, str), optional
        A DOF's label (``"TM P"``) to a collocated input and output of the model (``f_TMP``,
        ``dispTMP``) whose response tells how much of each mode the DOF carries.

    Returns
    -------
    ModalForm

    Raises
    ------
    StateSpaceError
        If the model's poles cannot be separated into well-conditioned blocks, or it is
        unstable (a pole with a positive real part).
    """
    shapes = dict(shapes or {})
    cols = [ss.input_index(x) for x in inputs]
    rows = [ss.output_index(x) for x in outputs]
    t_blocks, W, Wi, condition = block_diagonal(ss.a)
    eigenvalues = [np.linalg.eigvals(t) for _, _, t in t_blocks]
    unstable = [ev for evs in eigenvalues for ev in evs if ev.real > 1e-9 * max(1.0, abs(ev))]
    if unstable:
        worst = max(unstable, key=lambda e: e.real)
        msg = (f"{ss.source}: the model is unstable (a pole at {worst.real:.3g} "
               f"{worst.imag:+.3g}j rad/s); twind takes stable open-loop plants")
        raise StateSpaceError(msg)
    Bm, Cm = Wi @ ss.b, ss.c @ W
    shape_cols = {k: ss.input_index(i) for k, (i, _) in shapes.items()}
    shape_rows = {k: ss.output_index(o) for k, (_, o) in shapes.items()}
    modes, num_s, num_1, w, q, blocks, shape_b, real = [], [], [], [], [], [], [], []
    for (lo, hi, t), ev in zip(t_blocks, eigenvalues, strict=True):
        b, c = Bm[lo:hi][:, cols], Cm[rows][:, lo:hi]
        if t.shape[0] == 2 and abs(ev[0].imag) > 0:
            real.append(_Block(t, b, c))
            ns, n1 = _section(t, b, c)
            num_s.append(ns)
            num_1.append(n1)
            wk = math.sqrt(t[0, 0] * t[1, 1] - t[0, 1] * t[1, 0])
            w.append(wk)
            q.append(wk / max(-(t[0, 0] + t[1, 1]), 1e-300))
            shape_b.append({k: _section(t, Bm[lo:hi][:, [shape_cols[k]]],
                                        Cm[[shape_rows[k]]][:, lo:hi])[1][0, 0]
                            for k in shapes})
        else:
            blocks.append(_Block(t, b, c))
    order = np.argsort(w)
    labels = _labels([shape_b[k] for k in order], list(shapes))
    modes = tuple(Mode(i, w[k] / (2 * math.pi), q[k], *labels[i])
                  for i, k in enumerate(order))
    empty = np.zeros((0, len(rows), len(cols)))
    return ModalForm(tuple(inputs), tuple(outputs), modes,
                     np.array([num_s[k] for k in order]) if modes else empty,
                     np.array([num_1[k] for k in order]) if modes else empty,
                     np.array([w[k] for k in order]), np.array([q[k] for k in order]),
                     tuple(blocks), ss.d[np.ix_(rows, cols)], condition, ss.source,
                     tuple(real[k] for k in order))


def _section(t: NDArray, b: NDArray, c: NDArray) -> tuple[NDArray, NDArray]:
    """Numerator ``(num_s, num_1)`` of ``c (sI - t)^-1 b`` for a 2x2 block: ``c adj(sI - t)
    b = s c b + c [[-t22, t12], [t21, -t11]] b``."""
    adj = np.array([[-t[1, 1], t[0, 1]], [t[1, 0], -t[0, 0]]])
    return c @ b, c @ adj @ b


def _labels(shape_b: list[dict[str, float]], dofs: list[str]) -> list[tuple[str, float]]:
    """Each mode's label and share: the DOF whose collocated inverse mass it carries the
    largest share of (``b_k / sum_k b_k``, mass-normalised shapes squared)."""
    if not dofs or not shape_b:
        return [("", 0.0)] * len(shape_b)
    b = np.array([[max(m[d], 0.0) for d in dofs] for m in shape_b])  # (modes, dofs)
    total = b.sum(axis=0)
    share = np.divide(b, total, out=np.zeros_like(b), where=total > 0)
    best = share.argmax(axis=1)
    return [(dofs[j], float(share[i, j])) if share[i, j] > 0 else ("", 0.0)
            for i, j in enumerate(best)]


def block_diagonal(a: NDArray[np.float64], merge: float = MERGE
                   ) -> tuple[list[tuple[int, int, NDArray]], NDArray, NDArray, float]:
    """Real block-diagonal form of `a`: ``W^-1 a W = blkdiag(T_k)``.

    Poles within `merge` (relative) of each other, and all poles below :data:`ZERO_TOL`
    of ``|a|``, form one cluster; each cluster is moved to the top of the remaining real
    Schur form and split off by a Sylvester equation, one at a time.

    Parameters
    ----------
    a : ndarray, shape (n, n)
    merge : float

    Returns
    -------
    blocks : list of (int, int, ndarray)
        Each block's first and last-plus-one index and its matrix.
    W, W_inv : ndarray
    condition : float
        Of ``W``.

    Raises
    ------
    StateSpaceError
        If ``W`` is worse conditioned than :data:`CONDITION_LIMIT`.
    """
    n = a.shape[0]
    if n == 0:
        return [], np.zeros((0, 0)), np.zeros((0, 0)), 1.0
    scale = max(np.linalg.norm(a, 1), 1e-300)
    clusters = _clusters(np.linalg.eigvals(a), merge, ZERO_TOL * scale)
    t, z = scipy.linalg.schur(a, output="real")
    W = z.copy()
    blocks, start, rest = [], 0, t
    for members in clusters[:-1]:
        tol = _cluster_tol(members, merge, ZERO_TOL * scale)

        def chosen(re: float, im: float, members: NDArray = members, tol: float = tol) -> bool:
            return bool(np.min(np.abs(members - complex(re, im))) <= tol)

        tr, zr, k = scipy.linalg.schur(rest, output="real", sort=chosen)
        if k != len(members):  # the ordering failed (poles too close): merge onwards
            break
        x = scipy.linalg.solve_sylvester(tr[:k, :k], -tr[k:, k:], -tr[:k, k:])
        s = np.eye(rest.shape[0])
        s[:k, k:] = x
        W[:, start:] = W[:, start:] @ zr @ s
        blocks.append((start, start + k, tr[:k, :k].copy()))
        start, rest = start + k, tr[k:, k:]
    blocks.append((start, n, rest.copy()))
    condition = float(np.linalg.cond(W))
    if not condition < CONDITION_LIMIT:
        msg = (f"the model's poles cannot be separated into modes (the transformation's "
               f"condition number is {condition:.3g})")
        raise StateSpaceError(msg)
    return blocks, W, np.linalg.inv(W), condition


def _cluster_tol(members: NDArray[np.complex128], merge: float, zero: float) -> float:
    """How near a Schur form's eigenvalue must lie to a cluster's to be one of it."""
    return max(zero, merge * float(np.max(np.abs(members)))) + 1e-12


def _clusters(ev: NDArray[np.complex128], merge: float, zero: float
              ) -> list[NDArray[np.complex128]]:
    """The poles grouped: near-zero ones together, then any within `merge` (relative) of
    another chained together; conjugates stay together. Ascending in magnitude."""
    order = np.argsort(np.abs(ev))
    ev = ev[order]
    parent = list(range(ev.size))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    small = np.flatnonzero(np.abs(ev) <= zero)
    for i in small[1:]:
        parent[root(i)] = root(small[0])
    for i in range(ev.size):
        for j in range(i + 1, ev.size):
            if abs(ev[j]) - abs(ev[i]) > merge * abs(ev[j]) + zero:
                break
            if abs(ev[i] - ev[j]) <= merge * max(abs(ev[i]), abs(ev[j])) or \
                    abs(ev[i] - np.conj(ev[j])) <= merge * max(abs(ev[i]), abs(ev[j])):
                parent[root(j)] = root(i)
    groups: dict[int, list[complex]] = {}
    for i in range(ev.size):
        groups.setdefault(root(i), []).append(ev[i])
    return sorted((np.array(g) for g in groups.values()), key=lambda g: float(np.abs(g).max()))
