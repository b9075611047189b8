"""What ``twind diagnose`` found on a state-space optic: each chosen change (:class:`Claim`)
and the whole diagnosis (:class:`PlantDiagnosis`), in words, as tables and as JSON."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from twind.analysis.identification.data import FitData
from twind.analysis.identification.locate import Located
from twind.analysis.statespace.fit import Noise, PlantFit
from twind.analysis.statespace.measurement import PlantSet
from twind.analysis.statespace.model import Effect, PlantModel
from twind.config.statespace import StateSpaceOptic
from twind.model.statespace import ModalForm

TRADED = 0.9
"""A claim's parameter correlated this much with a calibration is shown traded against it."""
UNCALIBRATED_SIGMAS = 2.0
"""A readback whose fitted calibration lies within this many sigmas of zero is not
calibrated by the measurement."""

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
    revealed : list of Claim
        For a drive that also drives another input, the modes that input shows moved where
        the data have them, chosen with it (their likelihood ratio is in this claim's).
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
    revealed: list[Claim] = field(default_factory=list, repr=False)
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
    stopped : str
        Why the choice of changes stopped before it was done (``""``: it was done).
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
    stopped: str = ""

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
        """A change in words, with its values and sigmas from `fit` (default its own), and
        the calibrations it trades against (:meth:`traded`)."""
        fit = fit or claim.fit
        traded = self.traded(claim, fit)
        return self._reading(claim, fit) + "".join(
            f"; its {p} trades against the {name} (correlation {rho:+.2f}): the data fix "
            "their product" for p, (name, rho) in traded.items())

    def traded(self, claim: Claim, fit: PlantFit) -> dict[str, tuple[str, float]]:
        """Each parameter of `claim` correlated by :data:`TRADED` or more with a readback's
        calibration in `fit`, with the calibration most correlated and the correlation: the
        data fix their product, not each, and the claim's value is read only as far as the
        calibration is known."""
        key, out = claim.effect.key(), {}
        if not fit.cov.size:
            return out
        sigma = np.sqrt(np.abs(np.diag(fit.cov)))
        gains = [j for j, name in enumerate(fit.names) if name.startswith("g_")]
        for p in fit.own(claim.effect):
            if claim.effect.family == "resonance" and p.startswith("b"):
                continue  # its residue in one element: a shape, not a reading
            i = fit.names.index(f"{key}.{p}")
            rho = {j: fit.cov[i, j] / (sigma[i] * sigma[j]) for j in gains
                   if sigma[i] * sigma[j] > 0 and np.isfinite(fit.cov[i, j])}
            j = max(rho, key=lambda j: abs(rho[j]), default=None)
            if j is not None and abs(rho[j]) >= TRADED:
                out[p] = (self._nuisance_name(fit.names[j]), float(rho[j]))
        return out

    def _reading(self, claim: Claim, fit: PlantFit) -> str:
        """A change in words, with its values and sigmas from `fit`."""
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
        if e.family == "drive_coupling":
            d, u = self.plant.drives[e.target[0]], self.model.extra.inputs[e.target[1]]
            named = [n for n in self.optic.drives if self.optic.drives[n] == u]
            what = f"{named[0]} ({u})" if named else u
            return f"{d} also drives what {what} drives, {self._shares(own, err)}"
        if e.family == "drive_crosstalk":
            r, d = self.plant.readbacks[e.target[0]], self.plant.drives[e.target[1]]
            return (f"{r} picks up {d} directly: a flat {_pm(own['c'], err('c') or math.nan, 2)}"
                    " counts/count in phase with the drive (electronic crosstalk)")
        r = self.plant.readbacks[e.target[0]]
        ip, iz = own["inv_pole_hz"], own["inv_zero_hz"]
        lo, hi = self.data.frequency_hz[0], self.data.frequency_hz[-1]
        pole, zero = (f"{1 / x:.3g} Hz" if lo / 3 < 1 / max(x, 1e-300) < 3 * hi else "none"
                      for x in (ip, iz))
        lag = 1e3 * (ip - iz) / (2 * math.pi)
        return (f"{r} has a stage of its own: pole {pole}, zero {zero}; "
                f"{'a delay' if lag >= 0 else 'an advance'} of {abs(lag):.3g} ms below them")

    def _shares(self, own: dict[str, float], err: Callable[[str], float | None]) -> str:
        """A drive coupling's share per readback, in words: a number only where the data
        determine it; where they do not (the readback's calibration takes it up, or too
        few coherent bins), the readback named without one."""
        known = [(p, v) for p, v in own.items() if err(p) is not None]
        unknown = [self.plant.readbacks[int(p[1:])] for p in own if err(p) is None]
        words = []
        if known:
            words.append("seen as that share of its response in " + ", ".join(
                f"{self.plant.readbacks[int(p[1:])]} {_pm(100 * v, 100 * err(p), 2)} %"
                for p, v in known))
        if unknown:
            words.append(f"{'also ' if known else ''}in {', '.join(unknown)}, by a share the "
                         "data do not determine")
        return "; ".join(words)

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

    def uncalibrated(self) -> dict[str, str]:
        """The readbacks this measurement cannot calibrate, each with why: the fit leaves
        its calibration undetermined, or consistent with zero within
        :data:`UNCALIBRATED_SIGMAS` sigmas. What the model has them read is then only
        their shape, and a claim in them is read against a scale the data do not fix."""
        out = {}
        for name, value in self.final.nuisance.items():
            if not name.startswith("g_") or name.startswith("g_d") or name not in self.final.names:
                continue  # a readback the model does not reach is not calibrated at all
            sigma = self.final.error(name)
            readback = self.plant.readbacks[int(name[2:])]
            if sigma is None:
                out[readback] = "its calibration is not determined by the fit"
            elif abs(value) < UNCALIBRATED_SIGMAS * sigma:
                out[readback] = (f"its calibration {_pm(value, sigma, 2)} is consistent with "
                                 "zero: the drive reaches it too weakly in the model's terms")
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
                "nuisance": self.nuisance(), "uncalibrated": self.uncalibrated(),
                "stopped": self.stopped,
                "modes": self.modes_table(),
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
               "p_given_others": c.p_given_others, "reading": self.describe(c),
               "traded": {p: {"against": name, "correlation": rho}
                          for p, (name, rho) in self.traded(c, fit).items()}}
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
        out += [f"  cannot be calibrated: {r}: {why}" for r, why in self.uncalibrated().items()]
        out += [f"  stopped: {self.stopped}"] if self.stopped else []
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
