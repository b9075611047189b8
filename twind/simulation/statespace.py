"""A state-space optic integrated in fixed steps, with its damping loops closed as a CDS front
end closes them.

The model is taken in its modal form (:func:`~twind.model.statespace.modal_form`), each
block discretised exactly for a held input (zero-order hold, ``expm``), so a cycle costs the
blocks' own sizes and not the square of the states (KAGRA's SRM: 112 states, ~3 k
multiply-adds a cycle). Modes above a frequency may be dropped (:meth:`ModalForm.truncated`,
their static response kept); :func:`truncation_error` states what that costs.

A cycle: every readback is read (``y = C x + D u``, with its sensor noise); each damping loop
takes ``IN1`` (its readback), ``IN2 = IN1 + EXC`` and ``OUT = K IN2`` (its filter module's
second-order sections, bilinear at the rate, and its output limiter); the drives are the TEST points' EXC plus the
loops' OUT, held over the cycle while the state advances.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from twind.errors import TwindError
from twind.loop.filtermodule import IDENTITY_SECTION, FilterModule
from twind.model.statespace import ModalForm, StateSpace, modal_form



class EngineError(TwindError):
    """A state-space optic that cannot be integrated as asked."""


@dataclass(frozen=True)
class Block:
    """Samples of every test point of one optic, by channel suffix (``IM_DAMP_L_IN1``,
    ``TM_TEST_P_EXC``, ``TM_OPLEV_PIT_DIAG``), from sample `start_sample` at `rate_hz`."""

    start_sample: int
    rate_hz: float
    channels: Mapping[str, NDArray[np.float64]]


def truncation_error(full: ModalForm, reduced: ModalForm, f_max_hz: float) -> float:
    """The largest error of `reduced`'s response against `full`'s up to `f_max_hz`, relative
    to each element's largest response there (elements zero in the model left out)."""
    f = np.geomspace(1e-2, f_max_hz, 800)
    a, b = full.response(f), reduced.response(f)
    top = np.abs(a).max(axis=0)
    seen = top > 1e-9 * top.max()
    return float((np.abs(a - b).max(axis=0)[seen] / top[seen]).max()) if seen.any() else 0.0


class StateSpaceEngine:
    """One state-space optic and its damping loops, stepped at the model rate.

    Parameters
    ----------
    name : str
        The optic.
    model : StateSpace
    drives : mapping of str to str
        A TEST point's suffix (less ``_EXC``) to the model input it drives.
    readbacks : mapping of str to str
        A readback's channel suffix to the model output it reads.
    loops : mapping of str to (str, FilterModule or None)
        A damping loop's module to the model input its OUT drives and its controller; its
        IN1 is the readback ``<module>_IN1``.
    rate_hz : float
    max_hz : float, optional
        Drop the modes above this frequency (their static response kept).
    noise : mapping of str to float, optional
        White sensor noise per readback (its suffix): one-sided ASD, in its units per rtHz.
    seed : int
    closed : sequence of str, optional
        The damping loops closed (default every loop with a controller); the others' IN1,
        IN2 and OUT are still recorded, with OUT zero.

    Attributes
    ----------
    points : list of str
        The excitation points, by channel suffix: each TEST point's EXC, then each loop's.
    modal, full : ModalForm
        The form integrated and the model's whole one.
    dropped : int
        Modes dropped.
    """

    def __init__(self, name: str, model: StateSpace, drives: Mapping[str, str],
                 readbacks: Mapping[str, str],
                 loops: Mapping[str, tuple[str, FilterModule | None]], rate_hz: float,
                 max_hz: float | None = None, noise: Mapping[str, float] | None = None,
                 seed: int = 0, closed: Sequence[str] | None = None) -> None:
        self.name, self.rate = name, float(rate_hz)
        with_filters = [m for m, (_, fm) in loops.items() if fm is not None]
        self.closed = list(with_filters if closed is None else closed)
        missing = [m for m in self.closed if m not in with_filters]
        if missing:
            msg = (f"{name}: the damping loop(s) {', '.join(missing)} have no controller "
                   "(gain, FMs) to close them with")
            raise EngineError(msg)
        self.tests, self.loops = list(drives), list(loops)
        self.points = [f"{t}_EXC" for t in self.tests] + [f"{m}_EXC" for m in self.loops]
        self._modules = {m: fm for m, (_, fm) in loops.items()}
        inputs = list(dict.fromkeys([*drives.values(), *(loops[m][0] for m in self.loops)]))
        self.readbacks = list(readbacks)
        absent = [m for m in self.loops if f"{m}_IN1" not in readbacks]
        if absent:
            msg = f"{name}: the loops {', '.join(absent)} have no IN1 among the readbacks"
            raise EngineError(msg)
        self.full = modal_form(model, inputs, [readbacks[r] for r in self.readbacks])
        self.modal, self.dropped = (self.full.truncated(max_hz) if max_hz else (self.full, 0))
        self._drive_column = {t: inputs.index(drives[t]) for t in self.tests}
        self._loop_column = np.array([inputs.index(loops[m][0]) for m in self.loops],
                                     dtype=np.int64)
        self._loop_row = np.array([self.readbacks.index(f"{m}_IN1") for m in self.loops],
                                  dtype=np.int64)
        self._discretise()
        self._filters()
        asd = dict(noise or {})
        unknown = [r for r in asd if r not in self.readbacks]
        if unknown:
            msg = f"noise on {', '.join(unknown)}: not readbacks of {name}"
            raise EngineError(msg)
        self._sigma = np.array([asd.get(r, 0.0) for r in self.readbacks]) * np.sqrt(self.rate / 2)
        self._rng = np.random.default_rng(seed)
        self.samples = 0

    def _discretise(self) -> None:
        """Each block's exact zero-order-hold step, laid out for the kernel."""
        dt = 1.0 / self.rate
        blocks = self.modal.blocks_all()
        n = sum(b.t.shape[0] for b in blocks)
        m = self.modal.d.shape[1]
        self.ad = np.zeros((n, n))
        self.bd = np.zeros((n, m))
        self.c = np.zeros((self.modal.d.shape[0], n))
        self.starts = np.zeros(len(blocks) + 1, dtype=np.int64)
        at = 0
        for i, blk in enumerate(blocks):
            k = blk.t.shape[0]
            big = np.zeros((k + m, k + m))
            big[:k, :k], big[:k, k:] = blk.t * dt, blk.b * dt
            e = scipy.linalg.expm(big)
            self.ad[at:at + k, at:at + k], self.bd[at:at + k] = e[:k, :k], e[:k, k:]
            self.c[:, at:at + k] = blk.c
            at += k
            self.starts[i + 1] = at
        self.d = self.modal.d.copy()
        self.x = np.zeros(n)
        self.u = np.zeros(m)

    def _filters(self) -> None:
        """Every loop's switched-on sections and gain (closed loops only)."""
        sos, gains, limits, first = [], [], [], [0]
        for module in self.loops:
            rows = [IDENTITY_SECTION[None, :]]
            gain = limit = 0.0
            if module in self.closed:
                fm = self._modules[module]
                layout, where = fm.section_layout(self.rate)
                rows = [layout[where[k]] for k in sorted(fm.on)] or [IDENTITY_SECTION[None, :]]
                gain, limit = fm.gain, fm.limit
            stacked = np.vstack(rows)
            sos.append(stacked)
            gains.append(gain)
            limits.append(limit)
            first.append(first[-1] + len(stacked))
        self.sos = np.vstack(sos) if sos else np.zeros((0, 6))
        self.sos_first = np.array(first, dtype=np.int64)
        self.gains, self.limits = np.array(gains), np.array(limits)
        self.zi = np.zeros((len(self.sos), 2))

    def step(self, n: int, exc: Mapping[str, NDArray[np.float64]] | None = None) -> Block:
        """Advance `n` cycles with the excitations `exc` (by EXC channel suffix: a TEST
        point's ``TM_TEST_P_EXC`` or a loop's ``IM_DAMP_L_EXC``).

        Returns
        -------
        Block
            Every test point: each TEST point's EXC, each loop's EXC, IN1, IN2, OUT, and
            every readback.
        """
        exc = dict(exc or {})
        unknown = [k for k in exc if k not in self.points]
        if unknown:
            msg = f"no excitation point {', '.join(unknown)} on {self.name}"
            raise EngineError(msg)
        m = self.d.shape[1]
        drive = np.zeros((n, m))
        tests = {f"{t}_EXC": _samples(exc[f"{t}_EXC"], n) if f"{t}_EXC" in exc else np.zeros(n)
                 for t in self.tests}
        for t in self.tests:
            drive[:, self._drive_column[t]] += tests[f"{t}_EXC"]
        loop_exc = np.zeros((n, len(self.loops)))
        for j, module in enumerate(self.loops):
            if f"{module}_EXC" in exc:
                loop_exc[:, j] = _samples(exc[f"{module}_EXC"], n)
        noise = self._rng.standard_normal((n, len(self.readbacks))) * self._sigma
        y = np.zeros((n, len(self.readbacks)))
        out = np.zeros((n, len(self.loops)))
        _run(self.ad, self.bd, self.c, self.d, self.starts, self.x, self.u, drive, noise,
             self._loop_row, self._loop_column, loop_exc, self.sos, self.sos_first, self.gains,
             self.limits, self.zi, y, out)
        start = self.samples
        self.samples += n
        channels = dict(tests)
        channels.update({r: y[:, i] for i, r in enumerate(self.readbacks)})
        for j, module in enumerate(self.loops):
            channels[f"{module}_EXC"] = loop_exc[:, j]
            channels[f"{module}_IN2"] = y[:, self._loop_row[j]] + loop_exc[:, j]
            channels[f"{module}_OUT"] = out[:, j]
        return Block(start, self.rate, channels)


def _samples(x: NDArray[np.float64] | float, n: int) -> NDArray[np.float64]:
    arr = np.asarray(x, dtype=float)
    arr = np.broadcast_to(arr, (n,)) if arr.ndim == 0 else arr
    if arr.shape != (n,):
        msg = f"an excitation of {arr.shape[0]} samples for a step of {n}"
        raise EngineError(msg)
    return arr


@nb.njit(cache=True)
def _run(ad, bd, c, d, starts, x, u, drive, noise, loop_row, loop_col, loop_exc, sos,  # noqa: ANN001, PLR0913
         sos_first, gains, limits, zi, y, out):  # pragma: no cover - numba
    """The cycles: read, close the loops, drive, advance (see the module's docstring)."""
    n, m = drive.shape
    ns, p = x.size, y.shape[1]
    nl = loop_row.size
    xn = np.empty(ns)
    for t in range(n):
        for i in range(p):
            acc = noise[t, i]
            for j in range(ns):
                acc += c[i, j] * x[j]
            for k in range(m):
                acc += d[i, k] * u[k]
            y[t, i] = acc
        for k in range(m):
            u[k] = drive[t, k]
        for l in range(nl):
            v = y[t, loop_row[l]] + loop_exc[t, l]
            for s in range(sos_first[l], sos_first[l + 1]):  # transposed direct form II
                b0, b1, b2 = sos[s, 0], sos[s, 1], sos[s, 2]
                a0, a1, a2 = sos[s, 3], sos[s, 4], sos[s, 5]
                w = (b0 * v + zi[s, 0]) / a0
                zi[s, 0] = (b1 * v - a1 * w) / a0 + zi[s, 1]
                zi[s, 1] = (b2 * v - a2 * w) / a0
                v = w
            v = gains[l] * v
            if limits[l] > 0:  # the module's output limiter
                v = min(max(v, -limits[l]), limits[l])
            out[t, l] = v
            u[loop_col[l]] += out[t, l]
        for b in range(starts.size - 1):
            lo, hi = starts[b], starts[b + 1]
            for i in range(lo, hi):
                acc = 0.0
                for j in range(lo, hi):
                    acc += ad[i, j] * x[j]
                for k in range(m):
                    acc += bd[i, k] * u[k]
                xn[i] = acc
        for i in range(ns):
            x[i] = xn[i]
