"""``twind diagnose`` of a plant given as a state-space model: where the model misses the
measurement, which of its modes moved or vanished, what it lacks, and how much better the fit
becomes.

The diagnosis of an SOS (:mod:`twind.analysis.diagnose`), for a model known by its matrices
alone:

1. What any real measurement adds to a model is fitted first, with a loss that grossly wrong
   bins cannot drag (a narrow mode off its frequency): each readback's calibration, a delay
   and a low-pass (:mod:`~twind.analysis.statespace.fit`). Its residuals are searched band
   by band (:func:`~twind.analysis.identification.locate.band_tests`, Holm over all).
2. Changes are chosen one at a time (forward selection) from the families of
   :data:`~twind.analysis.statespace.model.FAMILIES`: each of the model's modes in reach of
   the data moved (its frequency and Q, searched over a factor 1.5 either side) or scaled
   (0: missing), a mode in no model (searched over the band), a readback that also reads
   another, a readback's own first-order stage. The members of a family are screened on
   the residuals (:mod:`~twind.analysis.statespace.search`), the best fitted in full with
   the calibrations, the delay and the changes chosen before. The evidence is the drop in
   deviance under the errors' own distribution (Student's t,
   :class:`~twind.analysis.statespace.fit.Noise`), over the bins' correlation: a likelihood
   ratio whose p-value pays for the searches (Davies) and for every member and family tried
   (Bonferroni). The claimed change of highest delta BIC joins, up to :data:`MAX_EFFECTS`;
   those the later ones made redundant leave. In a closed loop whose other damping loops
   are closed too, a mode's change is screened and fitted through the whole closed loop:
   the other loops answer the suspension as changed, and damp and move the mode they see.
3. What the final model still misses is searched again: ``unexplained``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from twind import progress
from twind.analysis.identification import narrow
from twind.analysis.identification.data import FitData
from twind.analysis.identification.fit import bin_correlation
from twind.analysis.identification.model import NARROW_REACH_BINS
from twind.analysis.identification.narrow import SEARCH_Q
from twind.analysis.identification.locate import Located, band_tests, significant
from twind.analysis.identification.params import FitError
from twind.analysis.statespace.fit import ROBUST_SCALE, Noise, PlantFit, fit_baseline, fit_plant
from twind.analysis.statespace.measurement import PlantSet
from twind.analysis.statespace.model import Effect, PlantModel, other_loops
from twind.analysis.statespace.search import Residuals, grid
from twind.config.statespace import StateSpaceOptic
from twind.model.statespace import ModalForm

ALPHA = 0.01
"""False-alarm probability of claiming a change."""
EQUIVALENT_LR = 6.0
"""Claimed changes whose likelihood ratios lie within this of the best one's are its rivals
(as for an SOS, :data:`twind.analysis.diagnosis.EQUIVALENT_LR`)."""
MAX_EFFECTS = 6
"""Changes a diagnosis chooses at most: a real suspension may differ from its model in
several modes."""
FAMILY_FITS = 2
"""Members of a family fitted in full at a step (the others ranked out on the residuals)."""
VISIBLE = 1.0
"""A model mode is tried only where its response adds at least this to the data's chi^2 in
the noise's units: one the data cannot see can be neither moved nor missing."""
_STAGES = [(p, z) for p in (0.3, 1.0, 3.0, 10.0, 30.0, 100.0) for z in (math.inf, 0.5 * p, 2 * p)]
"""A readback's stage's starts: poles across and above the band, zeros none or near."""
HOPELESS = 0.25
"""A member whose screen drops the chi^2 by less than this part of what a claim needs is not
fitted: its full fit (the calibrations refitted with it) seldom gains that much more."""


@dataclass
class Claim:
    """One change fitted with the calibrations and the changes chosen before it.

    Attributes
    ----------
    effect : Effect
    fit : PlantFit
        The fit holding it (once chosen: the final fit).
    lr, k, p_value, delta_bic
        Its likelihood ratio over the model without it, the directions it adds, its p-value
        (searches, members and families paid for) and ``lr - k ln(n)``.
    members : int
        Of its family at its step.
    seen_in : str
        The element whose chi^2 it lowers most.
    """

    effect: Effect
    fit: PlantFit
    lr: float
    k: int
    p_value: float
    delta_bic: float
    members: int = 1
    seen_in: str = ""
    equivalent: list[str] = field(default_factory=list)
    rival_of: str | None = None
    partial: bool = False
    p_given_others: float | None = None
    paths: tuple[float, ...] = field(default=(), repr=False)
    local: tuple[float, float, int] | None = None
    """chi2/nu of the model and of the final fit over the bins this change moves by more than
    their error, and how many: where it acts (the whole band's chi2/nu dilutes a change
    seen in a few bins)."""


@dataclass
class PlantDiagnosis:
    """What ``twind diagnose`` found on a state-space optic.

    Attributes
    ----------
    optic : StateSpaceOptic
    plant : PlantSet
        The measurement.
    data : FitData
        Its bins fitted.
    model : PlantModel
    nominal : PlantFit
        The model with its calibrations, delay and low-pass fitted.
    noise : Noise
        The errors' distribution the likelihood takes.
    located, unexplained : list of Located
    effects : list of Claim
        Chosen (best first), then their rivals.
    final : PlantFit
    first_step : dict of str to float
        Every member fitted at the first step, and its p-value.
    """

    optic: StateSpaceOptic
    plant: PlantSet
    data: FitData
    model: PlantModel
    nominal: PlantFit
    noise: Noise
    located: list[Located]
    effects: list[Claim]
    final: PlantFit
    unexplained: list[Located]
    first_step: dict[str, float] = field(default_factory=dict)

    @property
    def modal(self) -> ModalForm:
        """The model's modal form between the measured drives and readbacks."""
        return self.model.modal

    @property
    def chosen(self) -> list[Claim]:
        """The changes of the final model, best first."""
        return [e for e in self.effects if e.rival_of is None]

    @property
    def consistent(self) -> bool:
        """True when nothing was located and nothing claimed."""
        return not self.located and not self.effects

    def describe(self, claim: Claim, fit: PlantFit | None = None) -> str:
        """A change in words, with its values and sigmas from `fit` (default its own)."""
        fit = fit or claim.fit
        e, key = claim.effect, claim.effect.key()
        own, err = fit.own(e), (lambda p: fit.error(f"{key}.{p}"))
        if e.family == "mode_frequency":
            mode = self.modal.modes[e.target[0]]
            f = mode.f_hz * math.exp(own["log_f"])
            q = mode.q * math.exp(own["log_q"])
            sf, sq = (err("log_f") or math.nan) * f, (err("log_q") or math.nan) * q
            resolved = math.isfinite(sq) and q < f / self.data.resolution_hz
            qtext = (f"Q {_pm(q, sq, 3)}" if resolved else
                     f"narrower than the {self.data.resolution_hz:.3g} Hz bins (Q not resolved)")
            return (f"the model's mode at {mode.describe()} is at {_pm(f, sf, 4)} Hz, {qtext}, "
                    f"{_pm(own['amplitude'], err('amplitude') or math.nan, 2)} of its amplitude, "
                    f"in the measurement (seen in {claim.seen_in})")
        if e.family == "mode_amplitude":
            mode = self.modal.modes[e.target[0]]
            a, sa = own["amplitude"], err("amplitude")
            missing = abs(a) < 2 * (sa or math.inf) and abs(a) < 0.5
            what = ("is missing from the measurement" if missing
                    else "has another amplitude in the measurement")
            return (f"the model's mode at {mode.describe()} {what}: {_pm(a, sa or math.nan, 2)} "
                    f"of the model's (seen in {claim.seen_in})")
        if e.family == "resonance":
            return (f"a mode the model lacks at {_pm(own['f_hz'], err('f_hz') or math.nan, 4)} "
                    f"Hz, Q {_pm(own['q'], err('q') or math.nan, 3)} (seen in {claim.seen_in})")
        if e.family == "cross_coupling":
            r, r2 = (self.plant.readbacks[i] for i in e.target)
            eps, se = own["epsilon"], err("epsilon")
            return (f"{r} also reads {_pm(100 * eps, 100 * (se or math.nan), 2)} % of what "
                    f"{r2} reads")
        r = self.plant.readbacks[e.target[0]]
        ip, iz = own["inv_pole_hz"], own["inv_zero_hz"]
        pole, zero = (f"{1 / x:.3g} Hz" if x > 0 else "none" for x in (ip, iz))
        lag = 1e3 * (ip - iz) / (2 * math.pi)
        return (f"{r} has a stage of its own: pole {pole}, zero {zero}; "
                f"{'a delay' if lag >= 0 else 'an advance'} of {abs(lag):.3g} ms below them")

    def summary(self) -> str:
        """One line for a person."""
        chi2 = f"chi2/nu {self.nominal.chi2_nu:.3g} -> {self.final.chi2_nu:.3g}"
        rest = "; ".join(f"{x.element} near {math.sqrt(x.band_hz[0] * x.band_hz[1]):.3g} Hz"
                         for x in self.unexplained[:3])
        if self.consistent:
            return (f"consistent with the model (chi2/nu {self.nominal.chi2_nu:.3g}, the "
                    "calibrations, delay and low-pass fitted)")
        if not self.chosen:
            return f"no change explains the misfit; it lies in {rest}"
        names = "; ".join(self.describe(c, self.final) for c in self.chosen)
        if rest:
            return f"{names} ({chi2}); a residual remains in {rest}"
        return f"{names} ({chi2}); nothing remains"

    def modes_table(self) -> list[dict]:
        """Every model mode within the measured band: the model's frequency, Q and label,
        and the measurement's where a change was claimed."""
        f = self.data.frequency_hz[self.data.mask.any(axis=(1, 2))]
        out = []
        changed = {c.effect.target[0]: c for c in self.chosen
                   if c.effect.family in ("mode_frequency", "mode_amplitude")}
        for m in self.modal.modes:
            if not f[0] / 1.2 <= m.f_hz <= f[-1] * 1.2:
                continue
            row = {"mode": m.index, "f_hz": m.f_hz, "q": m.q, "label": m.label,
                   "share": m.share, "measured": None}
            c = changed.get(m.index)
            if c is not None and c.effect.family == "mode_frequency":
                own, key = self.final.own(c.effect), c.effect.key()
                fm, qm = m.f_hz * math.exp(own["log_f"]), m.q * math.exp(own["log_q"])
                sf, sq = self.final.error(f"{key}.log_f"), self.final.error(f"{key}.log_q")
                row["measured"] = {"f_hz": fm, "f_hz_sigma": sf and sf * fm, "q": qm,
                                   "q_sigma": sq and sq * qm, "q_resolved": bool(
                                       sq and qm < fm / self.data.resolution_hz)}
            elif c is not None:
                own = self.final.own(c.effect)
                row["measured"] = {"amplitude": own["amplitude"], "amplitude_sigma":
                                   self.final.error(f"{c.effect.key()}.amplitude")}
            out.append(row)
        return out

    def nuisance(self) -> dict[str, dict]:
        """The final fit's calibrations, delay and low-pass, each with its sigma (None: not
        determined, or held)."""
        out = {}
        for name, value in self.final.nuisance.items():
            out[self._nuisance_name(name)] = {"value": value, "sigma": self.final.error(name)}
        return out

    def _nuisance_name(self, name: str) -> str:
        if name.startswith("g_d"):
            return f"calibration {self.plant.drives[int(name[3:])]}"
        if name.startswith("g_"):
            return f"calibration {self.plant.readbacks[int(name[2:])]}"
        return {"tau_s": "delay_s", "inv_lp_hz": "inv_lowpass_hz",
                "loops": "other loops' gain (1: as configured)"}.get(name, name)

    def to_json(self) -> dict:
        """``twind diagnose --json`` of a state-space optic."""
        return {"optic": self.optic.name, "plant": "statespace",
                "consistent": self.consistent,
                "chi2_nu_nominal": self.nominal.chi2_nu, "chi2_nu_final": self.final.chi2_nu,
                "coherent": self.plant.coherent_bands(),
                "located": [x.to_json() for x in self.located],
                "effects": [self._claim_json(c) for c in self.effects],
                "unexplained": [{"element": x.element, "band_hz": list(x.band_hz)}
                                for x in self.unexplained],
                "p_values": self.first_step,
                "nuisance": self.nuisance(), "modes": self.modes_table(),
                "summary": self.summary()}

    def _claim_json(self, c: Claim) -> dict:
        fit = c.fit
        key = c.effect.key()
        params = {p: fit.own(c.effect)[p] for p in fit.own(c.effect)}
        sigma = {p: fit.error(f"{key}.{p}") for p in params}
        out = {"effect": key, "family": c.effect.family, "params": params, "sigma": sigma,
               "delta_bic": c.delta_bic, "p_value": c.p_value, "lr": c.lr, "k": c.k,
               "members": c.members, "seen_in": c.seen_in, "equivalent": c.equivalent,
               "chi2_nu_where_it_acts": None if c.local is None else
               {"model": c.local[0], "refitted": c.local[1], "bins": c.local[2]},
               "rival_of": c.rival_of, "partial": c.partial,
               "p_given_others": c.p_given_others, "reading": self.describe(c)}
        if c.effect.family in ("mode_frequency", "mode_amplitude"):
            m = self.modal.modes[c.effect.target[0]]
            out["mode"] = {"f_hz": m.f_hz, "q": m.q, "label": m.label, "share": m.share}
        if c.effect.family == "mode_frequency":
            own = fit.own(c.effect)
            out["f_hz"] = self.modal.modes[c.effect.target[0]].f_hz * math.exp(own["log_f"])
            s = fit.error(f"{key}.log_f")
            out["f_hz_sigma"] = None if s is None else s * out["f_hz"]
        return out

    def lines(self) -> list[str]:
        """A summary for a person."""
        out = [self.summary(),
               f"{self.optic.name}: the model with its calibrations, delay and low-pass "
               f"fitted: chi2/nu {self.nominal.chi2_nu:.3g}; "
               + ("consistent with the data" if self.consistent else
                  f"misses in {len(self.located)} band(s)")]
        out += [x.line(34) for x in self.located[:8]]
        for c in self.effects:
            role = f"rival of {c.rival_of}" if c.rival_of else "change" + (
                " (partial)" if c.partial else "")
            given = ("" if c.p_given_others is None
                     else f", p {c.p_given_others:.2g} given the others")
            where = "" if c.local is None else (
                f"; chi2/nu {c.local[0]:.3g} -> {c.local[1]:.3g} over the {c.local[2]} bins it "
                "moves")
            out.append(f"  {role} {c.effect.key()}: delta BIC {c.delta_bic:.1f}, p "
                       f"{c.p_value:.2g}{given}{where}")
            out.append(f"    {self.describe(c)}")
        nuis = self.nuisance()
        out.append("  what the measurement adds: " + ", ".join(
            f"{k} {_pm(v['value'], v['sigma'] or math.nan, 3)}" for k, v in nuis.items()))
        for x in self.unexplained[:8]:
            out.append(f"  unexplained: {x.element} {x.band_hz[0]:.3g}-{x.band_hz[1]:.3g} Hz")
        if not self.consistent:
            out.append(f"  chi2/nu {self.nominal.chi2_nu:.3g} -> {self.final.chi2_nu:.3g}")
        return out


def _pm(x: float, s: float, digits: int) -> str:
    """``x +- s`` (``x`` alone when ``s`` is NaN)."""
    if s is None or not math.isfinite(s):
        return f"{x:.{digits}g}"
    return f"{x:.{digits}g} +- {s:.2g}"


# ------------------------------------------------------------------------------ the diagnosis
def diagnose_plant(plant: PlantSet, optic: StateSpaceOptic, max_effects: int = MAX_EFFECTS
                   ) -> PlantDiagnosis:
    """Diagnose a measured plant against `optic`'s state-space model.

    Parameters
    ----------
    plant : PlantSet
        The measurement (:func:`~twind.analysis.statespace.measurement.read_plant`).
    optic : StateSpaceOptic
    max_effects : int
        Changes chosen at most.

    Returns
    -------
    PlantDiagnosis

    Raises
    ------
    FitError
        If no bin of the measurement is coherent.
    """
    base = fit_baseline(plant, optic)
    data, model, free, noise, nominal = base.data, base.model, base.free, base.noise, base.fit
    unit = _unit(nominal, data, noise)
    located = _located(data, model, nominal)
    model, chosen, rivals, first = _select(data, model, optic, plant, free, nominal, noise,
                                           unit, max_effects)
    if not chosen:
        return PlantDiagnosis(optic, plant, data, model, nominal, noise, located, [], nominal,
                              located, first)
    final_model, final = _prune(data, model, optic, plant, free, chosen, noise, unit)
    unexplained = _located(data, final_model, final)
    for c in chosen:
        c.fit, c.partial = final, bool(unexplained)
        c.local = _local(data, base.model, final_model, nominal, final, c.effect)
    rivals = [r for r in rivals if any(c.effect.key() == r.rival_of for c in chosen)]
    return PlantDiagnosis(optic, plant, data, final_model, nominal, noise, located,
                          chosen + rivals, final, unexplained, first)


def _local(data: FitData, nominal_model: PlantModel, model: PlantModel, nominal: PlantFit,
           final: PlantFit, effect: Effect) -> tuple[float, float, int] | None:
    """chi2/nu of `nominal` (on `nominal_model`) and of `final` (on `model`) over the bins
    where `effect` (at its final values) moves the final prediction by more than the error,
    and their number."""
    without = [(e, e.start(len(v) - 2) if e.key() == effect.key() else v)
               for e, v in final.effects]
    with_it = model(final.nuisance, final.effects)
    moved = np.abs(with_it - model(final.nuisance, without)) > data.sigma
    moved &= data.mask
    if not moved.any():
        return None
    n = int(moved.sum())

    def chi2_nu(prediction: NDArray[np.complex128]) -> float:
        z = (data.H - prediction)[moved] / data.sigma[moved]
        return float(np.sum(np.abs(z) ** 2) / (2 * n))

    return chi2_nu(nominal_model(nominal.nuisance, nominal.effects)), chi2_nu(with_it), n


def _unit(fit: PlantFit, data: FitData, noise: Noise) -> float:
    """The drop in deviance one fitted parameter makes in pure noise: one, inflated by the
    correlation of neighbouring bins (a Hann window's, taken from the residuals with those
    beyond :data:`ROBUST_SCALE` scales clipped: a grossly wrong mode is no noise). A change
    is smooth over the bins it moves, so its projection on the noise is inflated by the
    correlations themselves, ``1 + 2 sum rho_k``, not by their squares (which inflate a sum
    of squares, :func:`~twind.analysis.identification.locate.band_tests`)."""
    r = np.clip(fit.residual, -ROBUST_SCALE * noise.scale, ROBUST_SCALE * noise.scale)
    rho = bin_correlation(r, [data])
    return max(1.0, 1.0 + 2.0 * sum(rho))


def _located(data: FitData, model: PlantModel, fit: PlantFit) -> list[Located]:
    """Bands of elements where `fit` misses the data (Holm over all)."""
    pred = model(fit.nuisance, fit.effects)
    z = np.zeros(data.H.shape, dtype=complex)
    z[data.mask] = (data.H - pred)[data.mask] / data.sigma[data.mask]
    inflation = 1.0 + 2.0 * sum(x * x for x in fit.bin_correlation)
    return significant(band_tests(data, z, fit.noise_scale**2, inflation))


# ------------------------------------------------------------------------------ selection
def _select(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
            free: list[str], nominal: PlantFit, noise: Noise, unit: float, most: int
            ) -> tuple[PlantModel, list[Claim], list[Claim], dict[str, float]]:
    """Forward selection: the model as the chosen changes leave it (its other loops'
    feedback), the chosen changes (best first), their rivals, and the p-value of every member
    fitted at the first step."""
    chosen: list[Claim] = []
    rivals: list[Claim] = []
    first: dict[str, float] = {}
    current = nominal
    for step in range(most):
        claims = _step(data, model, optic, plant, free, chosen, current, noise, unit)
        if step == 0:
            first = {c.effect.key(): c.p_value for c in claims}
        claimed = sorted((c for c in claims if c.p_value < ALPHA), key=lambda c: -c.delta_bic)
        if not claimed:
            break
        best = claimed[0]
        best.equivalent = [c.effect.key() for c in claimed[1:] if best.lr - c.lr < EQUIVALENT_LR]
        chosen.append(best)
        rivals += [replace(c, rival_of=best.effect.key()) for c in claimed[1:]
                   if c.effect.key() in best.equivalent]
        model, current = _relooped(data, model, optic, plant, free, best.fit, noise)
        best.fit = current
    return model, chosen, rivals, first


def _relooped(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
              free: list[str], fit: PlantFit, noise: Noise, new: Effect | None = None
              ) -> tuple[PlantModel, PlantFit]:
    """`model` with the other loops' feedback of the model as `fit` changes it
    (:func:`_looped`), and `fit` refitted with it."""
    looped = _looped(data, model, optic, plant, fit.effects)
    if looped is model:
        return model, fit
    return looped, fit_plant(data, looped, fit.nuisance, free, fit.effects, noise=noise,
                             new=new, limits=_limits(looped, data, fit.effects))


def _looped(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
            effects: Sequence[tuple[Effect, dict]]) -> PlantModel:
    """`model` with what the other damping loops feed back made from the model as `effects`
    change it (its modes moved or scaled): a closed loop's other loops answer the suspension
    there is, not the one modelled. `model` itself when no other loop is closed or its
    feedback was made with these changes of its modes already."""
    modes = tuple((e.key(), tuple(sorted(v.items()))) for e, v in effects
                  if e.family.startswith("mode_"))
    if model.loops is None or modes == model.loops_made_with:
        return model
    looped = copy.copy(model)
    looped.loops = other_loops(optic, plant.drives, plant.readbacks, data.frequency_hz,
                               data.resolution_hz, effects)
    looped.loops_made_with = modes
    return looped


@dataclass(frozen=True)
class _Member:
    """A family's member as a screen found it: its drop in chi^2 (noise units), where its
    fit starts, and its searches' paths."""

    effect: Effect
    drop: float
    start: dict[str, float]
    paths: tuple[float, ...] = ()


def _step(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
          free: list[str], chosen: list[Claim], current: PlantFit, noise: Noise, unit: float
          ) -> list[Claim]:
    """Every family's likeliest members, each fitted with the changes `chosen`; their
    p-values paid for the members and the families screened."""
    res = Residuals(data, model, model(current.nuisance, current.effects),
                    model.gain(current.nuisance, current.effects),
                    {r: current.nuisance[f"g_{r}"] for r in range(data.H.shape[1])
                     if f"g_{r}" in free})
    # a screen's drop in chi^2 is, for residuals within the noise, (dof + 1) / dof / scale^2
    # of deviance
    screen_unit = noise.scale**2 * noise.dof / (noise.dof + 1) * unit
    families = {name: members for name, members in _screen(res, model, chosen, current,
                                                            screen_unit).items() if members}
    claims: list[Claim] = []
    for family, members in families.items():
        ranked = sorted(members, key=lambda x: -x.drop)
        for m in ranked[:FAMILY_FITS]:
            if m is not ranked[0] and m.drop < 0.5 * ranked[0].drop:
                continue  # far behind its family's best: a rival at most, not worth a fit
            if m.drop < HOPELESS * _needed(len(members) * len(families), len(m.start)):
                continue
            progress.note(f"step {len(chosen) + 1}: {m.effect.key()}")
            if family == "channel_response":
                m = replace(m, start=_stage_start(data, model, current, m.effect))
            claim = _try(data, model, optic, plant, free, chosen, m, current, noise, unit)
            if claim is None:
                continue
            if family == "resonance":
                claim = _narrower(claim, res, model)
            claim.members = len(members)
            claim.p_value = min(1.0, claim.p_value * len(members) * len(families))
            claims.append(claim)
    return claims


def _narrower(claim: Claim, res: Residuals, model: PlantModel) -> Claim:
    """`claim` (a resonance) paying also for the search it would have needed at its own
    fitted Q, when that is narrower than the searched ones: a narrow mode has more places
    to hide in the noise than a broad one. Trials a quarter of a width (or bin) apart turn
    the signature through about the same angle, so that search's path is the broadest
    sweep's scaled by the trials each takes."""
    q = claim.fit.own(claim.effect)["q"]
    if q <= max(SEARCH_Q) * 1.5:
        return claim
    f = res.data.frequency_hz[res.data.mask.any(axis=(1, 2))]
    lo, hi = max(float(f[0]), 1e-3), float(f[-1])
    trials = [grid(lo, hi, x, model.res).size for x in (SEARCH_Q[-1], q)]
    paths = (*claim.paths, claim.paths[-1] * trials[1] / trials[0])
    return replace(claim, paths=paths, p_value=min(1.0, _p_value(claim.lr, claim.k, paths)))


def _needed(tried: int, k: int) -> float:
    """The likelihood ratio `k` directions must reach to be claimed among `tried`."""
    return float(stats.chi2.isf(ALPHA / tried, k))


def _screen(res: Residuals, model: PlantModel, chosen: list[Claim],
            base: PlantFit, unit: float) -> dict[str, list[_Member]]:
    """Each family's members, screened on the residuals of `base`."""
    modal = model.modal
    taken = {c.effect.target[0] for c in chosen
             if c.effect.family in ("mode_frequency", "mode_amplitude")}
    f = res.data.frequency_hz[res.data.mask.any(axis=(1, 2))]
    terms = {k: model.closed_term(k) for k, m in enumerate(modal.modes)
             if k not in taken and f[0] / 1.5 <= m.f_hz <= 1.5 * f[-1]}
    out: dict[str, list[_Member]] = {"mode_frequency": [], "mode_amplitude": []}
    for k, term in terms.items():
        if res.power(term) < VISIBLE * unit:
            continue
        progress.tick()
        sweep = res.moved(k, unit)
        out["mode_frequency"].append(_Member(
            Effect("mode_frequency", (k,)), sweep.drop,
            {"log_f": math.log(2 * math.pi * sweep.f_hz / modal.w[k]),
             "log_q": math.log(sweep.q / modal.q[k]), "amplitude": 1.0}, sweep.paths))
        drop, coef = res.linear(res.G * term)
        out["mode_amplitude"].append(_Member(Effect("mode_amplitude", (k,)), drop / unit,
                                             {"amplitude": 1.0 + coef}))
    repeat = sum(c.effect.family == "resonance" for c in chosen)
    sweep = res.resonance(unit, _moved_to(model, base.effects))
    nr, nd = res.z.shape[1:]
    out["resonance"] = []
    if sweep.coefficients is not None:  # None: no trial left outside the moved modes
        start = {"f_hz": sweep.f_hz, "q": sweep.q,
                 **{f"b{i}": float(b) for i, b in enumerate(sweep.coefficients)}}
        out["resonance"].append(_Member(Effect("resonance", (repeat,)), sweep.drop, start,
                                        sweep.paths))
    read = [i for i in range(nr) if res.data.mask[:, i].any()]
    gains = [i for i in range(nr) if f"g_{i}" in base.names]
    out["cross_coupling"] = []
    for r in read:
        for r2 in gains:
            if r2 == r:
                continue
            column = np.zeros_like(res.z)
            column[:, r] = res.predicted[:, r2] * res.whitener[:, r]
            drop, coef = res.linear(column)
            out["cross_coupling"].append(_Member(Effect("cross_coupling", (r, r2)), drop / unit,
                                                 {"epsilon": coef}))
    out["channel_response"] = []
    for r in gains:
        column = np.zeros_like(res.z)
        column[:, r] = (1j * res.data.frequency_hz[:, None] * res.predicted[:, r]
                        * res.whitener[:, r])
        drop, _ = res.linear(column)
        out["channel_response"].append(_Member(Effect("channel_response", (r,)), drop / unit,
                                               {"inv_pole_hz": 0.0, "inv_zero_hz": 0.0}))
    return out


def _moved_to(model: PlantModel, effects: Sequence[tuple[Effect, dict]]
              ) -> list[tuple[float, float]]:
    """Where the modes that `effects` move now lie, each widened to three widths or
    :data:`~twind.analysis.identification.model.NARROW_REACH_BINS` bins, whichever is more:
    a mode in no model found there would be the moved one again."""
    out = []
    for effect, own in effects:
        if effect.family == "mode_frequency":
            k = effect.target[0]
            f = model.modal.modes[k].f_hz * math.exp(own["log_f"])
            q = model.modal.q[k] * math.exp(own["log_q"])
            reach = max(3 * f / q, NARROW_REACH_BINS * model.res)
            out.append((f - reach, f + reach))
    return out


def _limits(model: PlantModel, data: FitData, effects: Sequence[tuple[Effect, dict]]
            ) -> dict[str, tuple[float, float]]:
    """Each resonance's frequency range: the data's band (a factor 2 beyond), less where a
    moved mode lies (:func:`_moved_to`), the stretch that holds it."""
    f = data.frequency_hz[data.mask.any(axis=(1, 2))]
    avoid = _moved_to(model, effects)
    out = {}
    for effect, own in effects:
        if effect.family != "resonance":
            continue
        lo, hi = max(f[0] / 2, 1e-3), 2 * f[-1]
        at = own["f_hz"]
        for a, b in avoid:
            if b <= at:
                lo = max(lo, b)
            elif a >= at:
                hi = min(hi, a)
        out[f"{effect.key()}.f_hz"] = (lo, hi)
    return out


def _stage_start(data: FitData, model: PlantModel, base: PlantFit, effect: Effect
                 ) -> dict[str, float]:
    """The stage of :data:`_STAGES` (and its mirror) that fits the residuals of `base` best."""
    best, start = math.inf, {"inv_pole_hz": 0.0, "inv_zero_hz": 0.0}
    for pole, zero in _STAGES:
        for a, b in ((pole, zero), (zero, pole)):
            own = {"inv_pole_hz": 1 / a, "inv_zero_hz": 1 / b}
            r = data.whiten(model(base.nuisance, [*base.effects, (effect, own)]))
            chi2 = float(r @ r)
            if chi2 < best:
                best, start = chi2, own
    return start


def _try(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
         free: list[str], chosen: list[Claim], member: _Member, current: PlantFit, noise: Noise,
         unit: float) -> Claim | None:
    """`member` fitted with the changes `chosen` and every nuisance parameter, against
    `current` (the model without it); None when the fit fails or adds no direction. A
    change of a mode is fitted with the other damping loops' feedback made from the model it
    changes (at its start, then at its fit); other changes, with the feedback of the changes
    `chosen`."""
    effects = [*((c.effect, current.own(c.effect)) for c in chosen), (member.effect, member.start)]
    try:
        looped = _looped(data, model, optic, plant, effects) \
            if member.effect.family.startswith("mode_") else model
        fit = fit_plant(data, looped, current.nuisance, free, effects, noise=noise,
                        new=member.effect, limits=_limits(model, data, effects))
        if looped is not model:
            _, fit = _relooped(data, model, optic, plant, free, fit, noise, member.effect)
    except FitError:
        return None
    k = fit.rank - current.rank
    if k <= 0:
        return None
    lr = max(current.deviance - fit.deviance, 0.0) / unit
    p = _p_value(lr, k, member.paths)
    return Claim(member.effect, fit, lr, k, min(1.0, p), lr - k * math.log(max(2 * data.bins, 1)),
                 seen_in=_seen_in(data, current, fit), paths=member.paths)


def _p_value(lr: float, k: int, paths: Sequence[float]) -> float:
    """A likelihood ratio's p-value: chi^2 with `k` directions, or for a change searched in
    frequency Davies' bound over each search (the frequency paid by the path), and never
    less than the chi^2's."""
    regular = float(stats.chi2.sf(lr, k))
    if not paths:
        return regular
    return max(regular, sum(narrow.p_value(lr, k - 1, path) for path in paths))


def _seen_in(data: FitData, before: PlantFit, after: PlantFit) -> str:
    """The element whose chi^2 the change lowers most."""
    n = before.residual.size // 2
    drop = np.zeros(data.mask.shape)
    for fit, sign in ((before, 1.0), (after, -1.0)):
        z2 = np.zeros(data.mask.shape)
        z2[data.mask] = fit.residual[:n] ** 2 + fit.residual[n:] ** 2
        drop += sign * z2
    per = drop.sum(axis=0)
    i, j = np.unravel_index(int(np.argmax(per)), per.shape)
    return data.responses[i] if len(data.excited) == 1 else f"{data.responses[i]}/{data.excited[j]}"


def _prune(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
           free: list[str], chosen: list[Claim], noise: Noise, unit: float
           ) -> tuple[PlantModel, PlantFit]:
    """Each chosen change's p-value given the others; the most redundant leaves while its
    p-value is at least :data:`ALPHA`. Returns the final model (its other loops' feedback
    made with the changes that stay) and fit."""
    final = chosen[-1].fit
    while len(chosen) > 1:
        without = {}
        for c in chosen:
            rest = [(e, v) for e, v in final.effects if e.key() != c.effect.key()]
            looped = _looped(data, model, optic, plant, rest)
            try:
                fit = fit_plant(data, looped, final.nuisance, free, rest, noise=noise,
                                limits=_limits(looped, data, rest))
            except FitError:
                c.p_given_others = None
                continue
            without[c.effect.key()] = looped, fit
            k = final.rank - fit.rank
            lr = max(fit.deviance - final.deviance, 0.0) / unit
            c.p_given_others = min(1.0, _p_value(lr, k, c.paths)) if k > 0 else 1.0
        worst = max(chosen, key=lambda c: c.p_given_others or 0.0)
        if (worst.p_given_others or 0.0) < ALPHA:
            break
        chosen.remove(worst)
        model, final = without[worst.effect.key()]
    return model, final
