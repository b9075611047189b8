"""A state-space plant as a measurement sees it: the model's modes and other blocks, what a real
measurement adds to any model (calibrations, a delay, a low-pass), and the changes a diagnosis
tries (a mode moved, a mode missing, a mode in no model, a readback reading another, a channel
with its own frequency response).

The measured element ``readback r / drive d`` is modelled as

    g_r g_d L(f) C_r(f) [ sum_k S_k(f) + O(f) ] + sum_{r'} e_{r r'} g_{r'} g_d L(f) P_{r' d}(f)

with ``S_k = (num_s s + num_1) / (s^2 + w_k s / Q_k + w_k^2)`` the model's modes
(:class:`~twind.model.statespace.ModalForm`), ``O`` its other blocks and feedthrough,
``g`` real calibration factors (sign included) per readback and per drive,
``L = exp(-s tau) / (1 + s / (2 pi f_lp))`` the delay and low-pass every channel shares, and
``C_r`` a readback's own stage. A Welch estimate averages the response over its window's
kernel: every term is taken by the two-point rule (``f +- res / sqrt 3``), and a mode
narrower than two bins by the Hann kernel itself within a few bins of it
(:func:`~twind.analysis.identification.model.hann_kernel`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from twind.analysis.identification.model import NARROW_REACH_BINS, hann_kernel
from twind.analysis.identification.narrow import two_point
from twind.config.statespace import StateSpaceOptic
from twind.model.statespace import ModalForm

FAMILIES = ("mode_frequency", "mode_amplitude", "resonance", "cross_coupling",
            "channel_response", "drive_coupling", "drive_crosstalk")
"""What a state-space diagnosis tries: a model mode's frequency and Q changed; its amplitude
changed (0: missing); a mode the model lacks; a readback that also reads another; one
readback with its own first-order stage; a drive that also drives another input of its
stage (a coil driver's imbalance: what that input moves, seen in each readback); a drive's
electronic crosstalk into one readback (a flat term in phase with the drive)."""

_D2, _W2 = two_point(1.0)  # the two-point rule's offsets (bins) and weights
_KERNEL_SAMPLES = 8  # a mode narrower than 1/8 bin is widened to it on the kernel's points


STRUCTURAL = 1e-9
"""An element whose model response stays below this share of its readback's largest response
to any of the optic's drives is not part of the model: a model's couplings between DOFs that
its symmetry forbids come out of the matrices as numerical noise (KAGRA's: 1e-14 to 1e-18 of
the readback's largest, against 1e-6 and more for the weakest coupling the physics makes),
which a free calibration would blow up into anything."""


def modelled(optic: StateSpaceOptic, drives: Sequence[str], readbacks: Sequence[str],
             f_hz: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which elements (readbacks, drives) the model has (:data:`STRUCTURAL`), over a log grid
    spanning `f_hz`.

    Returns
    -------
    ndarray of bool, shape (readbacks, drives)
    """
    f = np.asarray(f_hz, dtype=float)
    grid = np.geomspace(max(float(f[f > 0].min()), 1e-3), float(f.max()), 64)
    outputs = [optic.readbacks[r] for r in readbacks]
    inputs = sorted({optic.input_of(d) for d in [*optic.drives, *optic.loops]})
    reach = np.abs(optic.model.response(grid, inputs, outputs)).max(axis=(0, 2))
    own = np.abs(optic.model.response(grid, [optic.input_of(d) for d in drives], outputs))
    return own.max(axis=0) >= STRUCTURAL * reach[:, None]


def stage_inputs(optic: StateSpaceOptic, drives: Sequence[str]) -> tuple[str, ...]:
    """The optic's other drives of the stages `drives` drive, one per model input none of
    `drives` drives: a drive's stage is its name's first part (``TM`` of ``TM_LOCK_P``), as
    the site's configuration names it."""
    own = {optic.input_of(d) for d in drives}
    stages = {d.split("_")[0] for d in drives}
    out: dict[str, str] = {}
    for d in [*optic.drives, *optic.loops]:
        u = optic.input_of(d)
        if d.split("_")[0] in stages and u not in own and u not in out:
            out[u] = d
    return tuple(out.values())


@dataclass(frozen=True)
class Effect:
    """One member of a family (:data:`FAMILIES`), applied to a :class:`PlantModel`.

    Attributes
    ----------
    family : str
    target : tuple of int
        ``(k,)`` the model's mode k; ``(r, r2)`` readback r also reads readback r2; ``(r,)``
        readback r's own stage; ``(n,)`` the n-th resonance (from 0); ``(d, u)`` drive d
        also drives the model's extra input u (:attr:`PlantModel.extra`); ``(r, d)`` drive
        d's crosstalk into readback r.
    anchor : (float, float) or None
        A moved mode's stretch of the band (Hz): where the data's peak it was found at lies,
        which its fits refine and do not leave.
    """

    family: str
    target: tuple[int, ...] = ()
    anchor: tuple[float, float] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            msg = f"no family {self.family!r}; expected one of {', '.join(FAMILIES)}"
            raise ValueError(msg)

    def null(self, own: Mapping[str, float]) -> dict[str, float]:
        """Its parameters `own` where the model is unchanged (a resonance: its numerators 0,
        its f and Q as they are)."""
        out = {p: 0.0 for p in own}
        if "amplitude" in out and self.family.startswith("mode_"):
            out["amplitude"] = 1.0
        if self.family == "resonance":
            out.update({p: own[p] for p in ("f_hz", "q") if p in own})
        return out

    def key(self) -> str:
        """A unique name: ``mode_frequency[12]``, ``cross_coupling[3<4]``, ``resonance[0]``."""
        if not self.target:
            return self.family
        sep = {"cross_coupling": "<", "drive_coupling": ">"}.get(self.family, ",")
        return f"{self.family}[{sep.join(map(str, self.target))}]"


@dataclass
class Parts:
    """A model evaluation in its stages: the plant, the calibrations (readback times drive),
    the shared lag, each readback's own stage, the cross-couplings, each resonance's kernel
    and each moved mode's section."""

    plant: NDArray[np.complex128]
    gains: NDArray[np.float64]
    stage: NDArray[np.complex128]
    cross: list
    resonances: dict
    moved: dict
    lag: NDArray[np.complex128] | None = None
    g: NDArray[np.float64] | None = None
    gd: NDArray[np.float64] | None = None
    inv_lp: float = 0.0
    calibrated: NDArray[np.complex128] | None = None
    out: NDArray[np.complex128] | None = None
    extra: NDArray[np.complex128] | None = None
    """The extra inputs' responses as the effects leave them (nf, readbacks, extra)."""

    def propagate(self, calibrated: NDArray[np.complex128]) -> NDArray[np.complex128]:
        """What a calibrated plant (or a change of it) becomes after each readback's stage
        and the cross-couplings; the first call keeps it as :attr:`calibrated`."""
        if self.calibrated is None:
            self.calibrated = calibrated
        out = calibrated * self.stage[:, :, None]
        for (r, r2), eps in self.cross:
            out[:, r] += eps * calibrated[:, r2]
        return out


class PlantModel:
    """The modal form at a measurement's bins, with nuisance parameters and effects.

    Parameters
    ----------
    modal : ModalForm
        Between the measurement's drives (columns) and readbacks (rows).
    f_hz : ndarray
        The bins' frequencies.
    resolution_hz : float
        Their Hann resolution (0: no window, the response at the bin itself).
    loops : ndarray, shape (nf, readbacks, drives), optional
        What the other damping loops, closed, add to a closed-loop column
        (:func:`other_loops`); scaled by the nuisance parameter ``loops``.
    feedback : dict of int to Feedback, optional
        Per closed-loop column, how a change of a mode reaches it through the other loops
        (:func:`loop_feedback`), for the searches.
    extra : ModalForm, optional
        From other inputs of the drives' stages to the readbacks (:func:`stage_inputs`):
        what a drive that also drives one of them adds (``drive_coupling``).

    Attributes
    ----------
    bounds : dict of str to (float, float)
        The range each nuisance parameter may take in a fit of this model (set by
        :func:`~twind.analysis.statespace.fit.fit_baseline` from the data's band).
    """

    def __init__(self, modal: ModalForm, f_hz: NDArray[np.float64], resolution_hz: float,
                 loops: NDArray[np.complex128] | None = None,
                 feedback: dict[int, Feedback] | None = None,
                 extra: ModalForm | None = None) -> None:
        self.modal, self.f, self.res = modal, np.asarray(f_hz, dtype=float), resolution_hz
        self.extra = extra
        self.loops, self.feedback = loops, feedback or {}
        self.loops_made_with: tuple = ()  # the mode changes `loops` was made with
        self.bounds: dict[str, tuple[float, float]] = {}  # the nuisance's physical ranges
        self.s = 2j * np.pi * self.f
        points = self.f[:, None] + resolution_hz * _D2 if resolution_hz > 0 else self.f[:, None]
        weights = _W2 if resolution_hz > 0 else np.ones(1)
        s2 = 2j * np.pi * points
        others = sum(w * modal.others(s2[:, i]) for i, w in enumerate(weights))
        self.terms = np.array([self.section(modal.num_s[k], modal.num_1[k], modal.w[k],
                                            modal.q[k]) for k in range(len(modal.modes))])
        self.plant = (self.terms.sum(axis=0) if len(modal.modes) else 0) + others
        self._cache: dict[tuple, NDArray] = {}
        self._extras: dict[tuple, NDArray] = {}  # the last few: each is extra-columns wide
        self.extra_plant = None if extra is None else sum(
            (self.section(extra.num_s[k], extra.num_1[k], extra.w[k], extra.q[k])
             for k in range(len(extra.modes))),
            sum(w * extra.others(s2[:, i]) for i, w in enumerate(weights)))

    def _cached(self, key: tuple, make):  # noqa: ANN001, ANN202 - a memo of the last few
        """`make()` remembered under `key` (a fit's Jacobian moves one parameter at a time:
        every other effect's section is the same as the last evaluation's)."""
        if key not in self._cache:
            if len(self._cache) > 256:
                self._cache.clear()
            self._cache[key] = make()
        return self._cache[key]

    # -------------------------------------------------------------- a mode at the bins
    def kernels(self, w: float, q: float) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """``1 / den`` and ``s / den`` of a mode at `w` (rad/s), `q`, as the estimate sees
        them at every bin."""
        q0, q1 = self.kernels_many(np.array([w]), q)
        return q0[0], q1[0]

    def kernels_many(self, w: NDArray[np.float64], q: float, at: slice = slice(None)
                     ) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """:meth:`kernels` of modes at each of `w` (rad/s), all at `q`, at the bins `at`
        (default all): (len(w), bins)."""
        w = np.asarray(w, dtype=float)[:, None]
        f = self.f[at]
        if self.res <= 0:
            s = self.s[at]
            den = 1.0 / (s * s + s * w / q + w * w)
            return den, s * den
        q0 = np.zeros((w.shape[0], f.size), dtype=complex)
        q1 = np.zeros_like(q0)
        for d2, w2 in zip(_D2, _W2, strict=True):  # the two-point rule
            s = 2j * np.pi * (f + self.res * d2)
            den = 1.0 / (s * s + s * w / q + w * w)
            q0 += w2 * den
            q1 += w2 * s * den
        f0 = w[:, 0] / (2 * np.pi)
        narrow = np.flatnonzero(f0 / q < 2 * self.res)  # these: the kernel itself near them
        if narrow.size:
            reach = NARROW_REACH_BINS
            d, wk = hann_kernel(self.res, 0.0)  # the finest kernel serves every narrow trial
            centre = np.searchsorted(f, f0[narrow])
            near = centre[:, None] + np.arange(-reach, reach + 1)[None, :]  # (T, bins)
            inside = (near >= 0) & (near < f.size)
            near = np.clip(near, 0, f.size - 1)
            q_k = np.minimum(q, _KERNEL_SAMPLES * f0[narrow] / self.res)[:, None, None]
            wn = w[narrow, 0][:, None, None]
            sk = 2j * np.pi * (f[near][:, :, None] + self.res * d)
            den = 1.0 / (sk * sk + sk * wn / q_k + wn * wn)
            rows = np.repeat(narrow[:, None], near.shape[1], axis=1)
            q0[rows[inside], near[inside]] = (den @ wk)[inside]
            q1[rows[inside], near[inside]] = ((sk * den) @ wk)[inside]
        return q0, q1

    def numerators(self, k: int) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """Mode `k`'s numerators ``num_s``, ``num_1`` as a change of its section reaches each
        element, (nf, readbacks, drives): the model's own, and in a closed-loop column what
        the other loops feed back of it too (to first order, :class:`Feedback`)."""
        nf = self.f.size
        A = np.broadcast_to(self.modal.num_s[k], (nf, *self.modal.num_s[k].shape)).astype(complex)
        B = np.broadcast_to(self.modal.num_1[k], (nf, *self.modal.num_1[k].shape)).astype(complex)
        for j, fb in self.feedback.items():
            A[:, :, j], B[:, :, j] = fb.reach(fb.modal.num_s[k]), fb.reach(fb.modal.num_1[k])
        return A, B

    def closed_term(self, k: int) -> NDArray[np.complex128]:
        """Mode `k`'s section as :meth:`numerators` carry it to each element."""
        A, B = self.numerators(k)
        q0, q1 = self.kernels(self.modal.w[k], self.modal.q[k])
        return q1[:, None, None] * A + q0[:, None, None] * B

    def section(self, num_s: NDArray, num_1: NDArray, w: float, q: float) -> NDArray[np.complex128]:
        """A mode's response at every bin, (nf, readbacks, drives)."""
        q0, q1 = self.kernels(w, q)
        return q1[:, None, None] * num_s + q0[:, None, None] * num_1

    # -------------------------------------------------------------- the whole model
    def __call__(self, nuisance: Mapping[str, float],
                 effects: Sequence[tuple[Effect, Mapping[str, float]]] = ()
                 ) -> NDArray[np.complex128]:
        """The modelled measurement, (nf, readbacks, drives).

        Parameters
        ----------
        nuisance : mapping of str to float
            ``g_<r>`` per readback index, ``g_d<j>`` per drive index (default 1), ``tau_s``,
            ``inv_lp_hz`` (``1 / f_lp``; 0 for none).
        effects : sequence of (Effect, mapping)
            Each with its own parameters' values.
        """
        return self.parts(nuisance, effects).out

    def parts(self, nuisance: Mapping[str, float],
              effects: Sequence[tuple[Effect, Mapping[str, float]]] = ()) -> Parts:
        """The model and the stages it is made in (for its derivatives)."""
        nr, nd = self.plant.shape[1:]
        P = self.plant.copy()
        parts = Parts(P, np.ones((nr, nd)), np.ones((self.f.size, nr), dtype=complex), [], {}, {})
        for effect, v in effects:
            fam, t = effect.family, effect.target
            if fam == "mode_frequency":
                k = t[0]
                moved = self._moved(k, v)
                parts.moved[effect.key()] = moved
                P += v["amplitude"] * moved - self.terms[k]
            elif fam == "mode_amplitude":
                P += (v["amplitude"] - 1.0) * self.terms[t[0]]
            elif fam == "resonance":
                b = np.array([v[f"b{i}"] for i in range(nr * nd)]).reshape(nr, nd)
                q0 = self._cached(("q0", v["f_hz"], v["q"]), lambda v=v: self.kernels(
                    2 * np.pi * v["f_hz"], v["q"])[0])
                parts.resonances[effect.key()] = q0
                P += q0[:, None, None] * b
            elif fam == "cross_coupling":
                parts.cross.append((t, v["epsilon"]))
            elif fam == "channel_response":
                parts.stage[:, t[0]] *= self.stage(v["inv_pole_hz"], v["inv_zero_hz"])
        if self.loops is not None:
            P += nuisance.get("loops", 1.0) * self.loops
        couplings = [(e.target, v) for e, v in effects if e.family == "drive_coupling"]
        if couplings:
            parts.extra = self.extra_response(effects)
            for (d, u), v in couplings:
                for name, eps in v.items():
                    P[:, int(name[1:]), d] += eps * parts.extra[:, int(name[1:]), u]
        g = np.array([nuisance.get(f"g_{i}", 1.0) for i in range(nr)])
        gd = np.array([nuisance.get(f"g_d{j}", 1.0) for j in range(nd)])
        parts.g, parts.gd, parts.gains = g, gd, g[:, None] * gd[None, :]
        parts.lag = self.lag(nuisance)
        parts.inv_lp = nuisance.get("inv_lp_hz", 0.0)
        parts.out = parts.propagate(P * parts.gains[None] * parts.lag[:, None, None])
        for e, v in effects:
            if e.family == "drive_crosstalk":
                parts.out[:, e.target[0], e.target[1]] += v["c"] * parts.lag
        return parts

    def extra_response(self, effects: Sequence[tuple[Effect, Mapping[str, float]]]
               ) -> NDArray[np.complex128]:
        """The extra inputs' responses with the modes `effects` move or scale changed
        (remembered)."""
        changes = tuple((e.key(), tuple(sorted(v.items()))) for e, v in effects
                        if e.family in ("mode_frequency", "mode_amplitude"))

        def make() -> NDArray[np.complex128]:
            X, m = self.extra_plant.copy(), self.extra
            for e, v in effects:
                k = e.target[0] if e.family in ("mode_frequency", "mode_amplitude") else None
                if k is None:
                    continue
                old = self.section(m.num_s[k], m.num_1[k], m.w[k], m.q[k])
                if e.family == "mode_amplitude":
                    X += (v["amplitude"] - 1.0) * old
                    continue
                w, q = m.w[k] * math.exp(v["log_f"]), m.q[k] * math.exp(v["log_q"])
                X += v["amplitude"] * self.section(m.num_s[k], m.num_1[k], w, q) - old
            return X

        if changes not in self._extras:
            if len(self._extras) > 3:
                self._extras.clear()
            self._extras[changes] = make()
        return self._extras[changes]

    def seen_through(self, drive: int, extra_input: int, shares: Mapping[str, float]
                     ) -> PlantModel:
        """This model with its modes reaching column `drive` also through `extra_input`, by
        each readback's share (``e<r>``, a ``drive_coupling``'s parameters): how the modes
        that input moves show in the measurement once the coupling is fitted, for the
        screens (its sections and its fits are this model's)."""
        num_s, num_1 = self.modal.num_s.copy(), self.modal.num_1.copy()
        for name, eps in shares.items():
            r = int(name[1:])
            num_s[:, r, drive] += eps * self.extra.num_s[:, r, extra_input]
            num_1[:, r, drive] += eps * self.extra.num_1[:, r, extra_input]
        view = copy.copy(self)
        view.modal = replace(self.modal, num_s=num_s, num_1=num_1)
        view._cache, view._extras = {}, {}
        return view

    def _moved(self, k: int, v: Mapping[str, float]) -> NDArray[np.complex128]:
        """Mode `k`'s section at its moved frequency and Q (remembered)."""
        w, q = self.modal.w[k] * math.exp(v["log_f"]), self.modal.q[k] * math.exp(v["log_q"])
        return self._cached(("mode", k, w, q), lambda: self.section(
            self.modal.num_s[k], self.modal.num_1[k], w, q))

    def stage(self, inv_pole_hz: float, inv_zero_hz: float) -> NDArray[np.complex128]:
        """A readback's own stage at the bins, ``(1 + s/2 pi z) / (1 + s/2 pi p)``, its
        corners kept within a factor 3 of the band (beyond, a stage is a gain, which the
        readback's calibration already is)."""
        ip, iz, _ = self._corners(inv_pole_hz, inv_zero_hz)
        return (1 + 1j * self.f * iz) / (1 + 1j * self.f * ip)

    def _corners(self, inv_pole_hz: float, inv_zero_hz: float) -> tuple[float, float, dict]:
        """A stage's corners (1/Hz) within a factor 3 of the band, and whether each was."""
        lo, hi = 1.0 / (3.0 * self.f[-1]), 3.0 / max(self.f[0], 1e-3)
        ip, iz = min(max(inv_pole_hz, lo), hi), min(max(inv_zero_hz, lo), hi)
        return ip, iz, {"inv_pole_hz": ip == inv_pole_hz, "inv_zero_hz": iz == inv_zero_hz}

    def derivative(self, parts: Parts, name: str, effects: Sequence[tuple[Effect, Mapping]]
                   ) -> NDArray[np.complex128] | None:
        """The model's derivative by a parameter: analytic for all but a moved mode's or a
        resonance's frequency and Q, and a mode's amplitude where a drive also drives
        another input (None: take differences).

        Parameters
        ----------
        parts : Parts
            The model where the derivative is taken.
        name : str
            ``g_<r>``, ``g_d<j>`` or ``<effect key>.<param>``.
        effects : sequence of (Effect, mapping)
            The effects `parts` was made with.
        """
        nf, nr, nd = parts.plant.shape
        if name.startswith("g_"):
            unit = np.zeros((nr, nd))
            if name.startswith("g_d"):
                j = int(name[3:])
                unit[:, j] = parts.g
            else:
                r = int(name[2:])
                unit[r] = parts.gd
            return parts.propagate(parts.plant * unit[None] * parts.lag[:, None, None])
        if name == "loops":
            return parts.propagate(self.loops * parts.gains[None] * parts.lag[:, None, None])
        if name in ("tau_s", "inv_lp_hz"):
            dlag = (-self.s if name == "tau_s" else
                    -1j * self.f / (1 + 1j * self.f * parts.inv_lp)) * parts.lag
            return parts.propagate(parts.plant * parts.gains[None] * dlag[:, None, None])
        key, _, param = name.rpartition(".")
        effect, own = next(((e, v) for e, v in effects if e.key() == key), (None, None))
        if effect is None:
            return None
        if effect.family == "channel_response":
            r = effect.target[0]
            ip, iz, inside = self._corners(own["inv_pole_hz"], own["inv_zero_hz"])
            d = np.zeros_like(parts.plant)
            jf = 1j * self.f
            factor = -jf / (1 + jf * ip) if param == "inv_pole_hz" else jf / (1 + jf * iz)
            if inside[param]:
                d[:, r] = parts.out[:, r] * factor[:, None]
            for (rr, r2), eps in parts.cross:  # what the cross-coupling added is not staged
                if rr == r and inside[param]:
                    d[:, r] -= eps * parts.calibrated[:, r2] * factor[:, None]
            return d
        if effect.family.startswith("mode_") and any(e.family == "drive_coupling"
                                                      for e, _ in effects):
            return None  # the mode reaches the drives also through a coupled input
        if effect.family == "mode_amplitude":
            return parts.propagate(self.terms[effect.target[0]] * parts.gains[None]
                                   * parts.lag[:, None, None])
        if effect.family == "mode_frequency" and param == "amplitude":
            return parts.propagate(parts.moved[key] * parts.gains[None]
                                   * parts.lag[:, None, None])
        if effect.family == "resonance" and param.startswith("b"):
            i = int(param[1:])
            d = np.zeros_like(parts.plant)
            d[:, i // nd, i % nd] = parts.resonances[key]
            return parts.propagate(d * parts.gains[None] * parts.lag[:, None, None])
        if effect.family == "cross_coupling":
            r, r2 = effect.target
            d = np.zeros_like(parts.plant)
            d[:, r] = parts.calibrated[:, r2]
            return d
        if effect.family == "drive_coupling":
            (j, u), r = effect.target, int(param[1:])
            d = np.zeros_like(parts.plant)
            d[:, r, j] = parts.extra[:, r, u]
            return parts.propagate(d * parts.gains[None] * parts.lag[:, None, None])
        if effect.family == "drive_crosstalk":
            d = np.zeros_like(parts.plant)
            d[:, effect.target[0], effect.target[1]] = parts.lag
            return d
        return None

    def gain(self, nuisance: Mapping[str, float],
             effects: Sequence[tuple[Effect, Mapping[str, float]]] = ()) -> NDArray[np.complex128]:
        """``g_r g_d L C_r``: what turns a change of the plant into one of the modelled
        measurement, (nf, readbacks, drives) (cross-couplings left out)."""
        parts = self.parts(nuisance, effects)
        return parts.gains[None] * parts.lag[:, None, None] * parts.stage[:, :, None]

    def lag(self, nuisance: Mapping[str, float]) -> NDArray[np.complex128]:
        """``L(f)``: the delay and low-pass every channel shares."""
        tau, inv_lp = nuisance.get("tau_s", 0.0), nuisance.get("inv_lp_hz", 0.0)
        return self._cached(("lag", tau, inv_lp), lambda: np.exp(-self.s * tau)
                            / (1 + 1j * self.f * inv_lp))


@dataclass(frozen=True)
class Feedback:
    """How a change of the plant reaches a closed-loop column, to first order.

    With loop ``d`` excited and the others closed, the column is ``T = P_R a`` per unit of
    ``d``'s OUT, ``a`` the loops' drives per unit of it. A change ``dP`` of the plant changes
    it by ``dP_R a + W dP_in a``, ``W = (P_R - T e_d^T) (1 - K P_in)^-1 K``, with ``P_in`` the
    loops' IN1 rows and ``K`` their controllers.

    Attributes
    ----------
    modal : ModalForm
        From the loops (``d`` first) to the readbacks, then the loops' IN1 (as
        :func:`other_loops` makes it; its modes are the plant's, in the same order).
    P : ndarray, shape (nf, rows, loops)
        `modal`'s response at the bins.
    K : ndarray, shape (nf, loops)
        The loops' controllers at the bins.
    a : ndarray, shape (nf, loops)
    W : ndarray, shape (nf, readbacks, loops)
    inner : tuple of int
        The rows of `modal` that are the loops' IN1.
    """

    modal: ModalForm
    P: NDArray[np.complex128]
    K: NDArray[np.complex128]
    a: NDArray[np.complex128]
    W: NDArray[np.complex128]
    inner: tuple[int, ...]

    def reach(self, num: NDArray[np.float64]) -> NDArray[np.complex128]:
        """What a mode's numerator `num` (a row of `modal` per output, a column per loop)
        becomes in the column: ``num_R a + W num_in a``, (nf, readbacks)."""
        nr = self.W.shape[1]
        drive = np.einsum("il,fl->fi", num[list(self.inner)], self.a)
        return np.einsum("rl,fl->fr", num[:nr], self.a) + np.einsum("frl,fl->fr", self.W, drive)


def loop_feedback(optic: StateSpaceOptic, drives: Sequence[str], readbacks: Sequence[str],
                  f_hz: NDArray[np.float64]) -> dict[int, Feedback]:
    """:class:`Feedback` of each closed-loop column with other loops closed, from the model
    at the bins' centres."""
    out = {}
    for j, (loops, rows) in _closed_columns(optic, drives, readbacks).items():
        modal = optic.modal(tuple(loops), rows)
        inner = tuple(rows.index(f"{m}_IN1") for m in loops)
        P = modal.response(np.asarray(f_hz, dtype=float))
        K = controllers(optic, loops, f_hz)
        M = closed(P[:, inner], K)
        a = M[:, :, 0] / M[:, :1, 0]
        PR = P[:, : len(readbacks)]
        T = np.einsum("frl,fl->fr", PR, a)
        W = np.einsum("frl,flm->frm", PR - T[:, :, None] * np.eye(len(loops))[0], M)
        out[j] = Feedback(modal, P, K, a, W, inner)
    return out


def controllers(optic: StateSpaceOptic, loops: Sequence[str], f_hz: NDArray[np.float64]
                ) -> NDArray[np.complex128]:
    """The configured controllers of `loops` at `f_hz`, (nf, loops)."""
    return np.stack([optic.loops[m].filters.build().response(f_hz) for m in loops], axis=1)


def closed(p_in: NDArray[np.complex128], k: NDArray[np.complex128]) -> NDArray[np.complex128]:
    """``(1 - K P_in)^-1 K``: each loop's OUT per unit of each loop's EXC with every loop
    closed, from the plant between the loops' drives and their IN1 (``P_in``, (..., loops,
    loops)) and their controllers (``K``, (..., loops))."""
    n = k.shape[-1]
    return np.linalg.solve(np.eye(n) - k[..., :, None] * p_in, k[..., :, None] * np.eye(n))


def closed_first(p_in: NDArray[np.complex128], k: NDArray[np.complex128]
                 ) -> NDArray[np.complex128]:
    """The first column of :func:`closed` (each loop's OUT per unit of the first loop's
    EXC), solved for that column alone: a search solves it at every trial and bin."""
    n = k.shape[-1]
    rhs = np.zeros((*k.shape, 1), dtype=complex)
    rhs[..., 0, 0] = k[..., 0]
    return np.linalg.solve(np.eye(n) - k[..., :, None] * p_in, rhs)[..., 0]


def _closed_columns(optic: StateSpaceOptic, drives: Sequence[str], readbacks: Sequence[str]
                    ) -> dict[int, tuple[list[str], tuple[str, ...]]]:
    """Each column that is a damping loop with other loops closed: its loops (its own first)
    and the rows its model needs (the readbacks, then the loops' IN1)."""
    closed = [m for m, spec in optic.loops.items() if spec.filters is not None]
    out = {}
    for j, d in enumerate(drives):
        others = [m for m in closed if m != d]
        if d in optic.loops and others:
            loops = [d, *others]
            out[j] = loops, tuple(dict.fromkeys([*readbacks, *(f"{m}_IN1" for m in loops)]))
    return out


def other_loops(optic: StateSpaceOptic, drives: Sequence[str], readbacks: Sequence[str],
                f_hz: NDArray[np.float64], resolution_hz: float,
                effects: Sequence[tuple[Effect, Mapping[str, float]]] = ()
                ) -> NDArray[np.complex128] | None:
    """What the optic's other damping loops, closed with the configuration's controllers, add
    to each closed-loop column.

    A readback ``R`` per unit of loop ``d``'s OUT is ``P_Rd`` with loop ``d`` alone closed;
    with the others closed too it is ``R/EXC`` over ``OUT/EXC`` of the whole closed loop,
    each estimated (Hann-averaged) on its own, as diaggui does. This returns that less the
    Hann-averaged ``P_Rd``, averaged as :class:`PlantModel` averages (the two-point rule, the
    kernel near a mode narrower than two bins, such a mode widened to an eighth of a bin).
    None when no column is a closed loop with other loops configured.

    Parameters
    ----------
    optic : StateSpaceOptic
    drives, readbacks : sequence of str
        The measurement's columns and rows.
    f_hz : ndarray
    resolution_hz : float
    effects : sequence of (Effect, mapping)
        Changes of the model's modes (moved, scaled) to make first.

    Returns
    -------
    ndarray of complex, shape (nf, readbacks, drives), or None
    """
    f_hz = np.asarray(f_hz, dtype=float)
    out = np.zeros((f_hz.size, len(readbacks), len(drives)), dtype=complex)
    for j, (loops, rows) in _closed_columns(optic, drives, readbacks).items():
        modal = changed(optic.modal(tuple(loops), rows), effects)
        if resolution_hz > 0:  # as the model's kernels: none narrower than an eighth of a bin
            modal = replace(modal, q=np.minimum(modal.q, _KERNEL_SAMPLES * modal.w
                                                / (2 * np.pi * resolution_hz)))
        points, weights, owner = _kernel_points(f_hz, resolution_hz, modal)
        others, K = _unchanged(optic, loops, modal, points)
        P = modal.modes_response(points) + others
        inner = [rows.index(f"{m}_IN1") for m in loops]
        u = closed_first(P[:, inner], K)
        R = np.einsum("prl,pl->pr", P[:, : len(readbacks)], u)
        out[:, :, j] = _averaged(R, owner, weights, f_hz.size) / \
            _averaged(u[:, :1], owner, weights, f_hz.size) - \
            _averaged(P[:, : len(readbacks), 0], owner, weights, f_hz.size)
    return out if np.any(out) else None


_UNCHANGED: dict[tuple, tuple[NDArray[np.complex128], NDArray[np.complex128]]] = {}


def _unchanged(optic: StateSpaceOptic, loops: Sequence[str], modal: ModalForm,
               points: NDArray[np.float64]
               ) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """What no change of a mode alters at `points`: the non-mode blocks' response and the
    loops' controllers (remembered: a diagnosis asks for them at every change it tries)."""
    key = (id(optic), tuple(loops), id(modal.d), points.size, hash(points.tobytes()))
    if key not in _UNCHANGED:
        if len(_UNCHANGED) > 8:
            _UNCHANGED.clear()
        _UNCHANGED[key] = (modal.others(2j * np.pi * points),
                           controllers(optic, loops, points))
    return _UNCHANGED[key]


def changed(modal: ModalForm, effects: Sequence[tuple[Effect, Mapping[str, float]]]) -> ModalForm:
    """`modal` with the modes `effects` move or scale changed as :class:`PlantModel` changes
    them (the same modes, in the same order, whatever the inputs and outputs)."""
    w, q = modal.w.copy(), modal.q.copy()
    scale = np.ones(len(modal.modes))
    for effect, v in effects:
        k = effect.target[0] if effect.family in ("mode_frequency", "mode_amplitude") else None
        if k is None:
            continue
        scale[k] *= v["amplitude"]
        if effect.family == "mode_frequency":
            w[k] *= math.exp(v["log_f"])
            q[k] *= math.exp(v["log_q"])
    return replace(modal, w=w, q=q, num_s=modal.num_s * scale[:, None, None],
                   num_1=modal.num_1 * scale[:, None, None])


def _averaged(x: NDArray[np.complex128], owner: NDArray[np.intp], weights: NDArray[np.float64],
              bins: int) -> NDArray[np.complex128]:
    """Each bin's weighted sum of the rows of `x` that belong to it: (bins, columns)."""
    out = np.zeros((bins, x.shape[1]), dtype=complex)
    np.add.at(out, owner, weights[:, None] * x)
    return out


def _kernel_points(f_hz: NDArray[np.float64], res: float, modal: ModalForm
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
    """The frequencies a Welch estimate at each bin averages over, their weights and their
    bins: the two-point rule, the Hann kernel itself within reach of a narrow mode."""
    if res <= 0:
        return f_hz, np.ones(f_hz.size), np.arange(f_hz.size)
    f_modes = modal.w / (2 * np.pi)  # as moved (`changed` keeps the modes' own records)
    narrow = f_modes[f_modes / modal.q < 2 * res]
    near = np.zeros(f_hz.size, dtype=bool)
    for f0 in narrow:
        near |= np.abs(f_hz - f0) < NARROW_REACH_BINS * res
    d, wk = hann_kernel(res, 0.0)
    far, close = np.flatnonzero(~near), np.flatnonzero(near)
    points = np.concatenate([(f_hz[far, None] + res * _D2).ravel(),
                             (f_hz[close, None] + res * d).ravel()])
    weights = np.concatenate([np.tile(_W2, far.size), np.tile(wk, close.size)])
    owner = np.concatenate([np.repeat(far, _D2.size), np.repeat(close, d.size)])
    return points, weights, owner
