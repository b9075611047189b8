"""What a diagnosis says (:func:`twind.analysis.diagnose.diagnose` finds it): each effect
fitted with its evidence (:class:`EffectFit`), the hypotheses that gave none to weigh
(:class:`NotFitted`), and the whole :class:`Diagnosis` with its report, its JSON and the
model it leaves; a ``resonance`` read as a body (:func:`body_reading`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from twind.analysis.estimation.tfset import TFSet
from twind.analysis.identification import locate as search
from twind.analysis.identification import narrow
from twind.analysis.identification.controller import ControllerCheck
from twind.analysis.identification.inmatrix import InputMatrixCheck
from twind.analysis.identification.locate import Located
from twind.analysis.identification.params import FIT_PARAMS
from twind.analysis.identification.result import FitResult
from twind.analysis.prediction import FitCurves, fit_curves
from twind.analysis.separation import Separation
from twind.config import OpticConfig
from twind.errors import TwindError
from twind.model.effects import (
    BODY_DOFS,
    entry,
    model_names,
    own_values,
)

ALPHA = 0.01
"""False-alarm probability of claiming an effect (over the whole catalogue): an effect is
claimed on its likelihood ratio's calibrated p-value (Bonferroni over the catalogue). BIC's
ln(n) per parameter (~9 for the ~5000 residuals of a 0.05 Hz measurement) would ask a
concealed coil imbalance for far more evidence than its p-value needs; delta BIC still ranks
the claimed effects."""
EQUIVALENT_LR = 6.0
"""Claimed effects whose likelihood ratio (``2 ln L``) is within this of the best one's are
not told apart by the data: less than "strong" evidence (a likelihood ratio of 20) against
them. Parameters are not charged here: an OSEM imbalance (three gain directions) that fits
as well as a one-parameter wire asymmetry is a rival the data leave standing, however BIC
ranks the two."""


FEW_AVERAGES = 10
"""Below this many averages the band search and the claims are not held to their level:
at 5 averages the rates bench located bands on 12 of 60 nulls and claimed on 2
(docs/limits.md); ``diagnose`` warns."""


class DiagnoseError(TwindError):
    """A diagnosis cannot be made or written."""


@dataclass
class EffectFit:
    """One hypothesis fitted with the nominal parameters and the effects chosen before it.

    Attributes
    ----------
    effect : str
        The catalogue entry.
    result : FitResult
        The fit that holds it: with the effects chosen before it, or once all are chosen
        the final joint fit (its parameters named ``effect.param`` in a combination).
    lr, k, p_value, delta_bic
        Its evidence over the model without it when it was tried: likelihood ratio, the
        directions it adds, p-value (look-elsewhere and the hypotheses tried paid for)
        and ``lr - k ln(n)``.
    equivalent : list of str
        Claimed rivals the data do not tell apart from it.
    rival_of : str or None
        For a rival listed beside a chosen effect: that effect.
    partial : bool
        Chosen, but the final model still leaves structure (in ``unexplained``).
    p_given_others : float or None
        With two or more chosen: its p-value against the final model without it.
    """

    effect: str
    result: FitResult
    lr: float
    k: int
    p_value: float
    delta_bic: float
    equivalent: list[str] = field(default_factory=list)
    rival_of: str | None = None
    partial: bool = False
    p_given_others: float | None = None
    whole: tuple[tuple[float, float], ...] = field(default=(), repr=False)
    """Bands its fit took bin by bin, whatever their coherence (``bounce_roll``'s)."""
    searched: list[float] = field(default_factory=list, repr=False)
    """Its search's look-elsewhere paths (a mode searched for), one per search."""
    step_result: FitResult | None = field(default=None, repr=False)
    """Its fit when it was chosen (before later effects joined)."""
    radius_m: float | None = field(default=None, repr=False)
    """The optic's radius (a ``resonance``'s reading asks whether its point is on it)."""
    f_ranges: list[tuple[float, float]] = field(default_factory=list)
    """A searched ``resonance``: the frequency ranges (Hz) its search could not tell from
    the best trial (:data:`F_MARGIN`)."""

    def values(self) -> tuple[dict[str, float], dict[str, float | None]]:
        """Its parameters and their sigmas (None: undetermined), by its own names."""
        got = self.result.as_dict()
        sig = dict(zip(self.result.names, self.result.sigma.tolist(), strict=True))
        combo = self.result.effect or self.effect
        values = own_values(combo, self.effect, got)
        sigma = {n: None if math.isnan(x) else float(x)
                 for n, x in own_values(combo, self.effect, sig).items()}
        for n in entry(self.effect).params:  # held at zero (unfitted), not determined
            values.setdefault(n, 0.0)
            sigma.setdefault(n, None)
        return values, sigma

    def to_json(self) -> dict:
        """One entry of ``effects`` in ``twind diagnose --json``."""
        values, sigmas = self.values()
        params, sigma = model_names(entry(self.effect).id, values, sigmas)
        out = {"effect": self.effect, "params": params, "sigma": sigma,
               "delta_bic": self.delta_bic, "p_value": self.p_value,
               "equivalent": self.equivalent, "rival_of": self.rival_of,
               "partial": self.partial, "p_given_others": self.p_given_others}
        if entry(self.effect).family:
            out["family"] = entry(self.effect).family
        if entry(self.effect).body:
            out["reading"] = body_reading(values, sigmas, self.radius_m)
            out["reading"]["f_hz_ranges"] = [list(r) for r in self._f_ranges(values, sigmas)]
        return out

    def _f_ranges(self, values: dict[str, float], sigma: dict[str, float | None]
                  ) -> list[tuple[float, float]]:
        """The search's ranges with the fitted frequency's own (2 sigma) joined: the fit
        may have moved off the trials."""
        if not self.f_ranges:
            return []
        f, s = values["f_hz"], sigma["f_hz"] or 0.0
        return narrow.merged([*self.f_ranges, (f - 2 * s, f + 2 * s)])


def body_reading(values: dict[str, float], sigma: dict[str, float | None],
                 radius_m: float | None = None) -> dict:
    """A ``resonance``'s physical reading: a body of mass m2 (kg) pulling along the beam at
    face point (y0, z0) (m) when its POS coupling leads, sideways when SIDE does; the DOFs
    it couples (at least a third of the largest coupling, angles taken at the face's
    edge); sigmas to first order (``None`` where undetermined); ``on_face`` when the point
    lies within `radius_m` of the centre (a point off the face is no body on it: another
    mode, read by its pattern).

    Parameters
    ----------
    values : dict of str to float
        The ``resonance``'s fitted parameters by its own names (``f_hz``, ``q``, ``g_POS``
        ... ``g_SIDE``).
    sigma : dict of str to float or None
        Their sigmas, None where undetermined.
    radius_m : float, optional
        The optic's radius (m); default 0.0375, the SOS's.

    Returns
    -------
    dict
        ``coupled`` (DOFs), ``along`` (``"beam"`` or ``"side"``), ``mass_kg`` and its sigma;
        when POS leads, also ``y0_m``, ``z0_m``, their sigmas and ``on_face``.
    """
    g = {d: values[f"g_{d}"] for d in BODY_DOFS}
    s = {d: sigma.get(f"g_{d}") for d in BODY_DOFS}
    edge = radius_m or 0.0375
    size = {d: abs(g[d]) / (edge if d in ("PIT", "YAW") else 1.0) for d in BODY_DOFS}
    top = max(size.values()) or 1.0
    lead = "POS" if abs(g["POS"]) >= abs(g["SIDE"]) else "SIDE"
    # the products g_i g_j are what the data fix, not each g_i (a body's sign and its
    # mass against its lever trade off): a DOF is coupled by its share of the largest
    coupled = [d for d in BODY_DOFS if size[d] >= top / 3]
    out: dict = {"coupled": coupled, "along": "beam" if lead == "POS" else "side",
                 "mass_kg": g[lead] ** 2,
                 "mass_kg_sigma": None if s[lead] is None else 2 * abs(g[lead]) * s[lead]}
    if lead == "POS" and g["POS"] != 0:
        for name, d in (("z0_m", "PIT"), ("y0_m", "YAW")):
            out[name] = g[d] / g["POS"]
            out[f"{name}_sigma"] = (None if s[d] is None or s["POS"] is None else
                                    math.hypot(s[d], abs(out[name]) * s["POS"]) / abs(g["POS"]))
        out["on_face"] = math.hypot(out["y0_m"], out["z0_m"]) <= edge
    return out


def _reading_line(r: dict) -> str:
    """A ``resonance``'s reading in words."""
    def pm(name: str, unit: float, fmt: str) -> str:
        sig = r.get(f"{name}_sigma")
        return format(r[name] * unit, fmt) + ("" if sig is None else
                                              " +- " + format(sig * unit, fmt))

    text = f"couples {'/'.join(r['coupled'])}; as a body: {pm('mass_kg', 1e3, '.2g')} g"
    if "z0_m" in r:
        text += (f" at y0 {pm('y0_m', 1e3, '.2g')} mm, z0 {pm('z0_m', 1e3, '.2g')} mm"
                 + ("" if r["on_face"] else " (off the face: not a body on it)"))
    text += f", pulling along the {r['along']}"
    if r.get("f_hz_ranges"):
        text += "; the data allow f in " + ", ".join(
            f"{lo:.3g}-{hi:.3g}" if hi > lo else f"{lo:.3g}" for lo, hi in r["f_hz_ranges"]
        ) + " Hz"
    return text


@dataclass(frozen=True)
class NotFitted:
    """A hypothesis a step tried that gave no fit to weigh, and why: reported, never dropped.

    Attributes
    ----------
    effect : str
        The catalogue entry (a family's member by its own name).
    step : int
        The step of the forward selection that tried it (1 for the first).
    reason : str
        Why: its fit failed (the fit's own words), or it adds no direction the data determine.
    """

    effect: str
    step: int
    reason: str

    def to_json(self) -> dict:
        """One entry of ``not_fitted`` in ``twind diagnose --json``."""
        return {"effect": self.effect, "step": self.step, "reason": self.reason}


@dataclass
class Diagnosis:
    """What ``twind diagnose`` found.

    Attributes
    ----------
    nominal : FitResult
        The nominal model refitted.
    located : list of Located
        Where it misses, element by element and band by band.
    effects : list of EffectFit
        The effects chosen, best first, then their rivals (``rival_of`` set).
    final : FitResult
        The model with the effects chosen.
    unexplained : list of Located
        Where the final model still misses.
    separations : dict
        For each (effect, rival): the measurement that tells them apart and its cost.
    not_fitted : list of NotFitted
        The hypotheses tried that gave no fit to weigh, with the reason.
    controller : ControllerCheck or None
        The damping loop's measured controller against the configured one; the plant was
        read through the measured one.
    input_matrix : InputMatrixCheck or None
        The input matrix the recorded IN1 and OSEM readings imply against the configured
        one; the plant was read through the measured one.
    p_band : float
        The band search's smallest Holm-corrected p-value on the refitted nominal model.
    bands : int
        Bands that search tested.
    hypotheses : int
        Hypotheses the first step tried (each family one): its Bonferroni factor.
    """

    nominal: FitResult
    located: list[Located]
    effects: list[EffectFit]
    final: FitResult
    unexplained: list[Located]
    separations: dict[tuple[str, str], Separation] = field(default_factory=dict)
    first_step: list[EffectFit] = field(default_factory=list, repr=False)
    """Every hypothesis fitted at the first step (its search's paths among them)."""
    not_fitted: list[NotFitted] = field(default_factory=list)
    controller: ControllerCheck | None = None
    input_matrix: InputMatrixCheck | None = None
    p_band: float = 1.0
    bands: int = 0
    hypotheses: int = 0

    def read_through(self, cfg: OpticConfig) -> OpticConfig:
        """`cfg` with the input matrix and the controllers measured, as the plant was read
        (`cfg` itself when they were not checked)."""
        if self.controller:
            return self.controller.config
        return self.input_matrix.config(cfg) if self.input_matrix else cfg

    def curves(self, tfs: TFSet, cfg: OpticConfig) -> dict[str, FitCurves]:
        """The models the diagnosis leaves on `tfs`'s grid, as a report draws them: the
        nominal model refitted against the configuration (``"nominal"``) and, once an
        effect is chosen, the final model against the nominal refitted (``"augmented"``).

        Parameters
        ----------
        tfs : TFSet
            The measurement diagnosed.
        cfg : OpticConfig
            The configuration as the plant was read (:meth:`read_through`).
        """
        fits = {"nominal": fit_curves(tfs, cfg, self.nominal)}
        if self.effects:
            fits["augmented"] = fit_curves(tfs, cfg, self.final, self.nominal)
        return fits

    @property
    def p_values(self) -> dict[str, float]:
        """Every hypothesis fitted at the first step and its p-value, claimed or not: how
        near the data came to each explanation."""
        return {c.effect: c.p_value for c in self.first_step}

    @property
    def chosen(self) -> list[EffectFit]:
        """The effects of the final model, best first (without their rivals)."""
        return [e for e in self.effects if e.rival_of is None]

    @property
    def consistent(self) -> bool:
        """True when the refitted nominal model explains the data: no band stands out and
        no effect earns its parameters."""
        return not self.located and not self.effects

    def summary(self) -> str:
        """One line for a person: what explains the data and what remains."""
        names = " + ".join(e.effect for e in self.chosen)
        chi2 = f"chi2/nu {self.nominal.chi2_nu:.3f} -> {self.final.chi2_nu:.3f}"
        rest = "; ".join(f"{x.element} near {math.sqrt(x.band_hz[0] * x.band_hz[1]):.3g} Hz"
                         for x in self.unexplained[:3])
        return self._controller_said() + self._plant_summary(names, chi2, rest)

    def _controller_said(self) -> str:
        """The input matrix rows and controllers that differ, as the summary opens with
        them."""
        said = ""
        if self.input_matrix is not None and not self.input_matrix.same:
            said = (f"the input matrix differs from the configuration in "
                    f"{', '.join(self.input_matrix.rows)}; read through the measured one: ")
        if self.controller is None or self.controller.same:
            return said
        filters = ", ".join(f"{c.dof}: {c.short()}" for c in self.controller.corrections)
        return (f"{said}the damping filters differ from the configuration ({filters}); read "
                "through the measured ones: ")

    def consistency(self) -> str:
        """What "consistent" was tested against: both searches, levels and p-values."""
        n = self.hypotheses
        p_effect = min(self.p_values.values(), default=1.0)
        return (f"no band located (smallest Holm-corrected p {self.p_band:.2g} over "
                f"{self.bands} bands, level {search.ALPHA:g}) and no effect claimed "
                f"(smallest p {p_effect:.2g} over {n} hypotheses, Bonferroni, level "
                f"{ALPHA:g}); chi2/nu {self.nominal.chi2_nu:.3f} over {self.nominal.bins} "
                f"bins (coherence >= {self.nominal.min_coherence:g})")

    def _plant_summary(self, names: str, chi2: str, rest: str) -> str:
        if self.consistent:
            return f"consistent with the nominal model: {self.consistency()}"
        if not self.chosen:
            return f"no hypothesis explains the misfit; it lies in {rest}"
        rivals = "".join(f"; {r.effect} fits nearly as well as {r.rival_of}: these data "
                         "cannot tell them apart" for r in self.effects if r.rival_of)
        if rest:
            return (f"{names} explain(s) part of the misfit ({chi2}); a residual remains in "
                    f"{rest}{rivals}")
        return f"explained by {names} ({chi2}); nothing remains{rivals}"

    def fitted(self, effect: str, param: str) -> tuple[float, float | None] | None:
        """`effect`'s `param` and its standard error (None: undetermined): from the final
        model when the effect was chosen, else from its fit at the first step (what the
        measurement allows of it); None when it was not fitted."""
        for fit_ in [*self.chosen, *self.first_step]:
            if fit_.effect == effect:
                values, sigma = fit_.values()
                return values[param], sigma[param]
        return None

    def final_model(self) -> tuple[dict[str, float], dict | None]:
        """The final model as a running twin takes it (:meth:`twind.client.TwinClient.params`):
        the refitted nominal parameters, and the best effect when one was claimed."""
        nominal = {n: v for n, v in self.final.identified().items() if n in FIT_PARAMS}
        best = self.effects[0] if self.effects else None
        return nominal, best and {"id": best.effect, "values": best.values()[0]}

    def to_json(self) -> dict:
        """The object of the issue, exactly."""
        nominal = {n: {"value": p["value"], "sigma": p["sigma"]}
                   for n, p in self.nominal.to_json()["params"].items()}
        return {"consistent": self.consistent,
                "consistency": {
                    "bands": {"test": "residual power band by band, Holm over the bands",
                              "alpha": search.ALPHA, "p_value": self.p_band,
                              "tested": self.bands},
                    "effects": {"test": "likelihood ratio of each hypothesis, Bonferroni "
                                        "over the hypotheses", "alpha": ALPHA,
                                "p_value": min(self.p_values.values(), default=1.0),
                                "tested": self.hypotheses},
                    "bins": self.nominal.bins,
                    "min_coherence": self.nominal.min_coherence},
                "controller": None if self.controller is None else self.controller.to_json(),
                "input_matrix": (None if self.input_matrix is None
                                 else self.input_matrix.to_json()),
                "chi2_nu_nominal": self.nominal.chi2_nu,
                "chi2_nu_final": self.final.chi2_nu,
                "located": [x.to_json() for x in self.located],
                "effects": [e.to_json() for e in self.effects],
                "unexplained": [{"element": x.element, "band_hz": list(x.band_hz)}
                                for x in self.unexplained],
                "p_values": self.p_values,
                "separations": [m.to_json(a, b) for (a, b), m in self.separations.items()],
                "not_fitted": [x.to_json() for x in self.not_fitted],
                "nominal_params": nominal, "summary": self.summary()}

    def lines(self) -> list[str]:
        """A summary for a person."""
        out = [self.summary(), *(self.input_matrix.lines() if self.input_matrix else []),
               *(self.controller.lines() if self.controller else []),
               f"{self.nominal.optic}: nominal model refitted, chi2/nu "
               f"{self.nominal.chi2_nu:.3f} over {self.nominal.bins} bins (coherence >= "
               f"{self.nominal.min_coherence:g}): "
               + ("consistent with the data" if self.consistent else
                  f"misses in {len(self.located)} band(s)")]
        out += [x.line() for x in self.located[:8]]
        for e in self.effects:
            entry_json = e.to_json()
            params = ", ".join(
                f"{n} {{{', '.join(f'{k} {x:.3g}' for k, x in v.items())}}}"
                if isinstance(v, dict) else f"{n} {v:.4g}"
                for n, v in entry_json["params"].items())
            role = f"rival of {e.rival_of}" if e.rival_of else (
                "effect" + (" (partial)" if e.partial else ""))
            given = ("" if e.p_given_others is None else
                     f", p {e.p_given_others:.2g} given the others")
            out.append(f"  {role} {e.effect}: delta BIC {e.delta_bic:.1f}, p {e.p_value:.2g}"
                       f"{given} ({params})" + (f"; not told apart from "
                                                f"{', '.join(e.equivalent)}"
                                                if e.equivalent else ""))
            if "reading" in entry_json:
                out.append("    " + _reading_line(entry_json["reading"]))
        out += [f"  {m.line(a, b)}" for (a, b), m in self.separations.items()]
        if not self.consistent and not self.effects:
            out.append("  no hypothesis explains it")
        shown = {e.effect for e in self.effects}
        rest = sorted((p, e) for e, p in self.p_values.items() if e not in shown and p < 1)[:3]
        if rest:
            out.append("  nearest unclaimed: " + ", ".join(f"{e} p {p:.2g}" for p, e in rest))
        for x in self.unexplained[:8]:
            out.append(f"  unexplained: {x.element} {x.band_hz[0]:.3g}-{x.band_hz[1]:.3g} Hz")
        for x in self.not_fitted:
            out.append(f"  not weighed at step {x.step}: {x.effect}: {x.reason}")
        if not self.consistent:
            out.append(f"  chi2/nu {self.nominal.chi2_nu:.3f} -> {self.final.chi2_nu:.3f}")
        return out
