"""Candidate physics for free-swinging modes the model cannot reach, each modelled, fitted with
the wire geometry, and weighed over the optics measured.

``twind modes`` solves the wire length, break-off height and clamp separation for an optic's
measured POS, PIT and YAW; T000134 then keeps SIDE just below POS, while the 40m measures it
12-54 mHz away. Each candidate here changes the optic's stiffness; its fit solves the geometry
again with the candidate in, and, where the candidate's size is not predicted, its parameter
too. Candidates of predicted size can fail; one free parameter per optic fits any one
frequency, so those are weighed by what else they predict: the sign of the parameter across
optics, and how far they mix POS and SIDE in the two modes near 1 Hz, which the mode shapes
of a ringdown (``twind freeswing``) measure.

| id                | physics                                              | size            |
| ----------------- | ---------------------------------------------------- | --------------- |
| wire_bending      | the wire's flexural rigidity shortens the pendulum   | predicted       |
| side_roll         | the wire loop's trapezoid rolls the optic as it      | predicted       |
|                   | swings sideways (the rigid-body model, geometric.py) |                 |
| side_spring       | a stiffness on SIDE alone (source unknown)           | k (N/m), free   |
| pos_side_coupling | a stiffness coupling POS and SIDE (an asymmetry):    | k_xy (N/m), free|
|                   | the two modes repel and mix                          |                 |
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from twind import DOFS
from twind.analysis.identification.modes import TOLERANCE_HZ, mechanics_modes, solve_geometry
from twind.config import OpticConfig
from twind.errors import TwindError
from twind.model.mechanics import Mechanics

WIRE_DIAMETER_M = 0.0017 * 0.0254
"""The SOS's steel music wire, 0.0017 inch (43 um); the configured vertical stiffness (the
measured 16 Hz bounce) asks for 46 um of steel over the nominal wire length."""
WIRE_YOUNG_PA = 2.0e11
"""Young's modulus of steel music wire."""
SIGN_NPM = 1e-4
"""A free stiffness counts as positive or negative beyond this (N/m): 1e-5 of the pendulum's."""


def bending_length(optic: OpticConfig) -> float:
    """``sqrt(E I / T)`` (m): how far from each clamped end a wire under tension ``T`` (half
    the optic's weight) bends; the pendulum is that much shorter at both ends."""
    sus = optic.sus
    inertia = math.pi * WIRE_DIAMETER_M**4 / 64
    return math.sqrt(WIRE_YOUNG_PA * inertia / (sus.mass_kg * sus.g_mps2 / 2))


def _add(mech: Mechanics, entries: Mapping[tuple[str, str], float]) -> Mechanics:
    K = mech.K.copy()
    for (a, b), value in entries.items():
        K[mech.index(a), mech.index(b)] += value
    return replace(mech, K=K)


def _bending(mech: Mechanics, optic: OpticConfig, _: float) -> Mechanics:
    sus, lam = optic.sus, bending_length(optic)
    pendulum = sus.mass_kg * sus.g_mps2 / sus.wire_length_m
    extra = pendulum * (sus.wire_length_m / (sus.wire_length_m - 2 * lam) - 1)
    return _add(mech, {("POS", "POS"): extra, ("SIDE", "SIDE"): extra})


def _side_spring(mech: Mechanics, optic: OpticConfig, k: float) -> Mechanics:
    return _add(mech, {("SIDE", "SIDE"): k})


def _coupling(mech: Mechanics, optic: OpticConfig, k: float) -> Mechanics:
    return _add(mech, {("POS", "SIDE"): k, ("SIDE", "POS"): k})


@dataclass(frozen=True)
class Candidate:
    """One candidate.

    Attributes
    ----------
    id : str
    physics : str
        One line for a report.
    free : str or None
        The parameter solved with the geometry (a stiffness, N/m), or None when the
        candidate's size is predicted.
    model : str
        The suspension model it modifies (``geometric`` is the rigid body on its wires).
    stiffen : callable
        ``(mechanics, optic, value) -> mechanics`` with the candidate in.
    """

    id: str
    physics: str
    free: str | None
    model: str
    stiffen: Callable[[Mechanics, OpticConfig, float], Mechanics]

    def mechanics(self, optic: OpticConfig, value: float = 0.0) -> Mechanics:
        """The optic's rigid-body dynamics with the candidate in.

        Parameters
        ----------
        optic : OpticConfig
        value : float
            The candidate's free parameter (a stiffness, N/m); unused when its size is
            predicted.

        Returns
        -------
        Mechanics
            Of the candidate's model (:attr:`model`), stiffened.
        """
        return self.stiffen(replace(optic, model=self.model).mechanics(), optic, value)


def _unchanged(mech: Mechanics, optic: OpticConfig, _: float) -> Mechanics:
    return mech


NOMINAL = Candidate("T000134", "the nominal model, geometry solved", None, "analytical",
                    _unchanged)
CANDIDATES = (
    Candidate("wire_bending", "the wires' flexural rigidity (0.0017 inch steel) shortens the "
              "pendulum at both clamped ends", None, "analytical", _bending),
    Candidate("side_roll", "the trapezoidal wire loop rolls the optic as it swings sideways "
              "(the rigid body on its wires)", None, "geometric", _unchanged),
    Candidate("side_spring", "a stiffness on SIDE alone, source unknown", "k_side_Npm",
              "analytical", _side_spring),
    Candidate("pos_side_coupling", "a stiffness coupling POS and SIDE (an asymmetry): the two "
              "modes repel and mix", "k_xy_Npm", "analytical", _coupling),
)
"""The candidates, by the order a report lists them."""


@dataclass(frozen=True)
class CandidateFit:
    """One candidate fitted to one optic's measured modes.

    Attributes
    ----------
    optic, candidate : str
    measured, fitted : dict of str to float
        Mode frequencies (Hz) by DOF.
    params : dict of str to float
        The solved geometry (m) and the candidate's free parameter (N/m), if any.
    mixing_deg : float
        How far the mode labelled POS leans towards SIDE (0: pure POS, 45: half each).
    reached : bool
        Whether every measured mode is within :data:`~twind.analysis.identification.modes.TOLERANCE_HZ`.
    """

    optic: str
    candidate: str
    measured: dict[str, float]
    fitted: dict[str, float]
    params: dict[str, float]
    mixing_deg: float

    @property
    def reached(self) -> bool:
        return all(abs(self.fitted.get(d, math.inf) - f) <= TOLERANCE_HZ
                   for d, f in self.measured.items())

    def chi2(self) -> float:
        """Sum over the measured modes of (miss / measurement error)^2, the error the table's
        +-5 mHz; a mode the model cannot label counts as missed by 1 Hz."""
        return sum(((self.fitted.get(d, f + 1.0) - f) / TOLERANCE_HZ) ** 2
                   for d, f in self.measured.items())


def fit_candidate(optic: OpticConfig, measured: Mapping[str, float],
                  candidate: Candidate = NOMINAL) -> CandidateFit:
    """Solve the geometry (and the candidate's free parameter, for SIDE) for the measured
    modes (:func:`twind.analysis.identification.modes.solve_geometry`) and compare every mode.

    Parameters
    ----------
    optic : OpticConfig
    measured : mapping of str to float
        The measured modes (Hz) by DOF.
    candidate : Candidate
        The physics tried (default: the model as it is).

    Returns
    -------
    CandidateFit
    """
    geometry, value, mech = solve_geometry(optic, measured, candidate.mechanics,
                                           free=bool(candidate.free) and "SIDE" in measured)
    params = dict(geometry, **({candidate.free: value} if candidate.free else {}))
    try:
        modes = mechanics_modes(mech, optic.name)
    except TwindError:
        modes = {}
    return CandidateFit(optic.name, candidate.id, dict(measured),
                        {d: f for d, (f, _) in modes.items()}, params, _mixing(mech, modes))


def _npm(value: float) -> str:
    """A stiffness (N/m), 0 within :data:`SIGN_NPM`."""
    return f"{value:+.3f}" if abs(value) > SIGN_NPM else "0"


def _span(values: list[float]) -> str:
    low, high = round(min(values)), round(max(values))
    return f"{low}" if low == high else f"{low}-{high}"


def _mixing(mech: Mechanics, modes: Mapping[str, tuple[float, np.ndarray]]) -> float:
    """The angle (deg) by which the POS mode's shape leans towards SIDE."""
    if "POS" not in modes:
        return math.nan
    shape = modes["POS"][1]
    return math.degrees(math.atan2(abs(shape[mech.index("SIDE")]),
                                   abs(shape[mech.index("POS")])))


@dataclass(frozen=True)
class Comparison:
    """Every candidate fitted to every optic of a measured table, and the verdict.

    Attributes
    ----------
    fits : dict of str to list of CandidateFit
        By candidate id (``T000134`` first), one fit per optic.
    """

    fits: dict[str, list[CandidateFit]]

    def summary(self, candidate: str) -> dict:
        """chi^2 over the optics, parameters, BIC, optics reached, the free parameter's range
        and sign, and the POS-SIDE mixing it implies."""
        fits = self.fits[candidate]
        n = sum(len(f.measured) for f in fits)
        k = sum(len(f.params) for f in fits)
        chi2 = sum(f.chi2() for f in fits)
        free = next((c.free for c in CANDIDATES if c.id == candidate), None)
        values = np.array([f.params[free] for f in fits]) if free else np.array([])
        mixing = np.array([f.mixing_deg for f in fits])
        return {"chi2": chi2, "parameters": k, "modes": n, "bic": chi2 + k * math.log(n),
                "reached": sum(f.reached for f in fits), "optics": len(fits),
                "free": free, "free_min": float(values.min()) if free else None,
                "free_max": float(values.max()) if free else None,
                "free_positive": int((values > SIGN_NPM).sum()) if free else None,
                "mixing_deg_max": float(np.nanmax(mixing)) if np.isfinite(mixing).any()
                else None}

    def verdict(self) -> list[str]:
        """What the optics say, in words: each candidate's reach and cost, then either the
        predicted candidate that explains every optic or ``unexplained``, with the free
        candidates that fit and the mixing that would tell them apart."""
        nominal = self.summary(NOMINAL.id)
        if nominal["reached"] == nominal["optics"]:
            return ["T000134 reaches every optic's measured modes: nothing to explain"]
        lines = [self._line(c, nominal) for c in CANDIDATES]
        predicted = [c.id for c in CANDIDATES if c.free is None
                     and self.summary(c.id)["reached"] == nominal["optics"]]
        if predicted:
            return lines + [f"explained by {', '.join(predicted)} (size predicted) on every "
                            "optic"]
        fitting = {c.id: [f for f in self.fits[c.id] if f.reached] for c in CANDIDATES if c.free}
        told = "; ".join(f"{i} on {', '.join(f.optic for f in fits)} (POS leans "
                         f"{_span([f.mixing_deg for f in fits])} deg to SIDE)"
                         for i, fits in fitting.items() if fits)
        return lines + [
            "unexplained: no candidate of predicted size reaches every optic's modes. One free "
            f"parameter per optic fits: {told or 'none'}. The frequencies cannot say which "
            "physics; the mode shapes can: a ringdown's OSEM amplitudes (twind freeswing) show "
            "how far the modes near 1 Hz mix POS and SIDE."]

    def _line(self, c: Candidate, nominal: dict) -> str:
        s = self.summary(c.id)
        reach = (f"reaches {s['reached']}/{s['optics']} optics, chi2 {nominal['chi2']:.0f} -> "
                 f"{s['chi2']:.0f}")
        if c.free is None:
            return f"{c.id} (size predicted): {reach}"
        return (f"{c.id} (one free {c.free} per optic, {_npm(s['free_min'])} to "
                f"{_npm(s['free_max'])}, positive on {s['free_positive']}/{s['optics']}): "
                f"{reach}, BIC {nominal['bic']:.0f} -> {s['bic']:.0f}")

    def lines(self) -> list[str]:
        """A table in mHz (SIDE and POS: measured, then each candidate's fit; a free
        parameter in N/m) and the verdict."""
        ids = list(self.fits)
        head = "optic  SIDE-POS | " + " | ".join(f"{i:>17}" for i in ids)
        sub = "       measured | " + " | ".join(f"{'POS  SIDE':>17}" for _ in ids)
        rows = [head, sub + "   (mHz)"]
        for k, fit0 in enumerate(self.fits[ids[0]]):
            cells = []
            for i in ids:
                f = self.fits[i][k]
                mark = " " if f.reached else "*"
                cells.append(f"{1e3 * f.fitted.get('POS', math.nan):7.1f} "
                             f"{1e3 * f.fitted.get('SIDE', math.nan):7.1f}{mark} ")
            m = fit0.measured
            rows.append(f"{fit0.optic:5} {1e3 * (m['SIDE'] - m['POS']):+8.0f} | "
                        + " | ".join(cells)
                        + f"   measured {1e3 * m['POS']:.0f} {1e3 * m['SIDE']:.0f}")
        for c in CANDIDATES:
            if c.free:
                rows.append(f"{c.free}: " + ", ".join(
                    f"{f.optic} {_npm(f.params[c.free])}" for f in self.fits[c.id]))
        return rows + ["* a measured mode missed by more than 5 mHz", ""] + self.verdict()

    def to_json(self) -> dict:
        """The ``twind modes --candidates --json`` object."""
        return {"candidates": {c.id: {"physics": c.physics, "free": c.free}
                               for c in (NOMINAL, *CANDIDATES)},
                "fits": {i: [{"optic": f.optic, "measured_hz": f.measured,
                              "fitted_hz": f.fitted, "params": f.params,
                              "mixing_deg": f.mixing_deg, "reached": f.reached}
                             for f in fits] for i, fits in self.fits.items()},
                "summary": {i: self.summary(i) for i in self.fits},
                "verdict": self.verdict()}


def compare(optics: Mapping[str, OpticConfig],
            table: Mapping[str, Mapping[str, float]]) -> Comparison:
    """Fit the nominal model and every candidate to every optic of `table`.

    Parameters
    ----------
    optics : mapping of str to OpticConfig
        By name.
    table : mapping of str to mapping of str to float
        Measured modes (Hz) by optic and DOF.

    Returns
    -------
    Comparison
        Every fit, by candidate, and the verdict over the optics.
    """
    missing = [d for d in DOFS if any(d not in m for m in table.values())]
    if missing:
        msg = f"candidates need every optic's {', '.join(DOFS)}; missing {', '.join(missing)}"
        raise TwindError(msg)
    return Comparison({c.id: [fit_candidate(optics[n], table[n], c) for n in table]
                       for c in (NOMINAL, *CANDIDATES)})
