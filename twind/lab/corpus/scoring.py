"""The corpus's scoring: the right effect named with its key parameter within
:data:`KEY_TOLERANCE`, nothing claimed on the nulls, and the summary of a run."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from twind.commissioning.hidden import FACES, SEEN
from twind.lab.corpus.cases import Case

KEY_TOLERANCE = 0.35
RESOLVED_F = 0.15
"""A body the data resolve fixes its frequency within this fraction of it (95 %)."""
RESOLVED_MARGIN = 3.84
"""How much more (chi^2, nulls' units) the truth's structure must explain than what was
called a full explanation for that call to be wrong: one parameter's 95 %."""
AS_GOOD = 1.0
"""A hidden body's miss is the measurement's, not the search's, when the fit started at the
truth beats the search's by no more than this in chi^2 (one parameter's 1 sigma)."""
@dataclass
class Score:
    """How ``diagnose`` did on one case."""

    case: Case
    named: bool  # the case's effect is the winner or declared equivalent (nulls: nothing)
    claimed: list[str]
    key_error: float  # relative error of the key parameter (nan: not named, or a null)
    key_z: float  # the same error in units of the fit's own sigma (RMS over its components)
    chi2_nu_nominal: float
    chi2_nu_final: float
    seconds: float  # measurement and diagnosis
    p_value: float = math.nan  # the hidden effect's; a null's smallest (its nearest claim)
    diagnosis_seconds: float = math.nan  # the diagnosis alone (what a blind set costs)
    located: bool = False  # a resonance: a band holding f +- 15 % located, or modelled
    forced: bool = False  # a resonance passed off as catalogue effects, nothing unexplained
    truth_p: float = math.nan  # a resonance: its p-value from a fit started at the truth
    truth_margin: float = math.nan
    """A resonance: how much better (in chi^2) the fit started at the truth explains the data
    than the search's own first fit; at or below :data:`AS_GOOD` the data do not prefer the
    truth to what the search found."""
    coupled: list[str] = field(default_factory=list)  # a resonance: the claimed one's DOFs
    f_in_range: bool | None = None  # a claimed resonance: f inside the ranges it allows
    f_range_width: float = math.nan  # their total width, relative to f
    f_allowed: tuple[float, float] = (math.nan, math.nan)
    """A resonance: the f range the data allow a fit of the truth's structure (95 %)."""
    final_lr: float = math.nan
    """A resonance: the final model's likelihood ratio over the nominal (nulls' units)."""
    truth_lr: float = math.nan
    """A resonance: the truth's structure's, fitted from the truth."""

    @property
    def resolved(self) -> bool:
        """A resonance the data resolve: the truth's structure, fitted from the truth, beats
        the nominal at the detection level and fixes f within :data:`RESOLVED_F` of it."""
        f = self.case.truth.get("f_hz", math.nan) if self.case.truth else math.nan
        lo, hi = self.f_allowed
        return (self.truth_p < 0.01 and lo >= (1 - RESOLVED_F) * f
                and hi <= (1 + RESOLVED_F) * f)

    @property
    def coupled_right(self) -> bool:
        """A resonance modelled with the DOFs the body couples (POS among them)."""
        return bool(self.coupled) and set(self.coupled) <= set(self.case.truth["coupled"])

    @property
    def wrongly_full(self) -> bool:
        """Catalogue effects called a full explanation of a body whose structure fits
        better than them by more than the noise (one parameter's 95 %)."""
        return self.forced and self.truth_lr - self.final_lr > RESOLVED_MARGIN

    @property
    def kind(self) -> str:
        """null, single (a catalogue effect), resonance, channel_filter or pair."""
        effect = self.case.effect
        if effect is None:
            return "null"
        if "+" in effect:
            return "pair"
        return effect if effect in ("resonance", "channel_filter") else "single"


def key_error(effect: str, truth: dict, fitted: dict) -> float:
    """Relative error of an effect's key parameter: the face gains' pitch- and yaw-like
    part (what the measurement determines), ``extra_s``, ``f_hz``, ``sensing``, ``delta_m``
    or ``vertical`` (the bounce's coupling: its compliance is what IN1/EXC shows).

    Parameters
    ----------
    effect : str
        A catalogue effect (not ``resonance`` or ``channel_filter``).
    truth : dict
        The hidden effect's parameters (:func:`hidden`).
    fitted : dict
        The claimed effect's parameters in the same names (``EffectFit.to_json``'s).

    Returns
    -------
    float
    """
    if effect in ("coil_imbalance", "osem_imbalance"):
        t = SEEN @ np.array([truth["gains"][f] for f in FACES])
        g = SEEN @ np.array([fitted["gains"][f] for f in FACES])
        return float(np.linalg.norm(g - t) / np.linalg.norm(t))
    key = {"loop_delay": "extra_s", "actuator_pole": "f_hz", "side_coupling": "sensing",
           "wire_asymmetry": "delta_m", "bounce_roll": "vertical"}[effect]
    return abs(fitted[key] - truth[key]) / abs(truth[key])


def key_z(effect: str, truth: dict, result) -> float:  # noqa: ANN001 - FitResult
    """The key parameter's error in units of the fit's own sigma: RMS over the determined
    components (pitch- and yaw-like gains), 1 on average when the sigmas are honest.

    Parameters
    ----------
    effect : str
        A catalogue effect (not ``resonance`` or ``channel_filter``).
    truth : dict
        The hidden effect's parameters (:func:`hidden`).
    result : FitResult
        The fit holding the claimed effect (alone or in a combination).

    Returns
    -------
    float
        NaN when the key combination is not determined.
    """
    pre = f"{effect}." if result.effect and result.effect != effect else ""  # joint fits
    got = result.as_dict()
    if effect in ("coil_imbalance", "osem_imbalance"):
        combos = [{f"{pre}gain_{f}": w for f, w in zip(FACES, row, strict=True)}
                  for row in SEEN]
        d = SEEN @ np.array([got[f"{pre}gain_{f}"] - truth["gains"][f] for f in FACES])
    else:  # a driver pole is fitted as 1/f
        name = {"loop_delay": "extra_s", "actuator_pole": "inv_f_hz",
                "side_coupling": "sensing", "wire_asymmetry": "delta_m",
                "bounce_roll": "vertical"}[effect]
        value = 1 / truth["f_hz"] if effect == "actuator_pole" else truth[name]
        combos = [{pre + name: 1.0}]
        d = np.array([got[pre + name] - value])
    cov = result.combination_covariance(combos)
    if not np.all(np.isfinite(cov)):
        return math.nan
    return float(np.sqrt(d @ np.linalg.lstsq(cov, d, rcond=None)[0] / d.size))


def score(case: Case, diagnosis, seconds: float,  # noqa: ANN001 - Diagnosis
          diagnosis_seconds: float = math.nan) -> Score:
    """Score one diagnosis (None: it failed) against its case; `seconds` with the
    measurement, `diagnosis_seconds` without.

    A catalogue effect is named when it is claimed (chosen, or a rival of the chosen);
    a pair when both are, its key error the worse of the two; a channel filter when its
    channel is, its key error its stage's low-frequency delay's; a resonance when a
    ``resonance`` is claimed within 15 % of its frequency, coupling no DOF the body leaves
    alone and POS among them, its key error the frequency's ("passed off" when no
    resonance is claimed, catalogue effects are and nothing is left unexplained).

    Parameters
    ----------
    case : Case
    diagnosis : Diagnosis or None
        What ``diagnose`` found; None when it failed.
    seconds : float
        Measurement and diagnosis (s).
    diagnosis_seconds : float
        The diagnosis alone (s).

    Returns
    -------
    Score
    """
    if diagnosis is None:
        return Score(case, False, ["(failed)"], math.nan, math.nan, math.nan, math.nan,
                     seconds, diagnosis_seconds=diagnosis_seconds)
    out = diagnosis.to_json()
    claimed = [e["effect"] for e in out["effects"]]
    entries = {e.effect: e for e in diagnosis.effects}
    tried = diagnosis.p_values
    effect, err, z, located, forced = case.effect, math.nan, math.nan, False, False
    body: dict = {}
    p = min(tried.values(), default=math.nan) if effect is None else tried.get(
        effect, tried.get(case.truth.get("channel", ""), math.nan))
    if effect is None:
        named = not claimed
    elif effect == "resonance":
        body = _resonance(case.truth, diagnosis)
        named, err, z, located = (body.pop(k) for k in ("named", "err", "z", "located"))
        forced = (not any(e.effect.startswith("resonance") for e in diagnosis.effects)
                  and bool(diagnosis.chosen) and not diagnosis.unexplained)
    elif effect == "channel_filter":
        named = case.truth["channel"] in claimed
        if named:
            err = stage_error(case.truth, entries[case.truth["channel"]].to_json()["params"])
    elif "+" in effect:
        parts = effect.split("+")
        named = all(e in claimed for e in parts)
        if named:
            err = max(key_error(e, case.truth[e], entries[e].to_json()["params"])
                      for e in parts)
    else:
        named = effect in claimed
        if named:
            err = key_error(effect, case.truth, entries[effect].to_json()["params"])
            z = key_z(effect, case.truth, entries[effect].result)
    return Score(case, named, claimed, err, z, out["chi2_nu_nominal"],
                 out["chi2_nu_final"], seconds, p, diagnosis_seconds, located, forced, **body)


def body_start(truth: dict) -> dict[str, float]:
    """A hidden body (:func:`attached_body`, pulling along the beam) in the catalogue
    ``resonance``'s parameters: ``g = sqrt(m2) (1, z0, y0, 0)``."""
    y, z = truth["point_m"]
    g = math.sqrt(truth["mass_kg"]) * np.array([1.0, z, y, 0.0])
    return {"f_hz": truth["f_hz"], "q": truth["q"],
            **{f"g_{d}": float(x) for d, x in zip(("POS", "PIT", "YAW", "SIDE"), g,
                                                 strict=True)}}


def stage_error(truth: dict, fitted: dict) -> float:
    """A channel stage's key error: its low-frequency delay ``(1/p - 1/z) / 2 pi`` (the
    stage's change is ``-j f (1/p - 1/z)`` to first order below its corners) against the
    truth's, relative to it. A concealed stage's corners lie close together and its change
    is seen below them: the data fix this slope, not each corner (a stage fitted hundreds of
    Hz above the band has the same slope).

    Parameters
    ----------
    truth, fitted : dict
        The hidden and the fitted stage: ``pole_hz`` and ``zero_hz``.

    Returns
    -------
    float
    """
    def delay(p: dict) -> float:
        return (1 / p["pole_hz"] - 1 / p["zero_hz"]) / (2 * math.pi)

    return abs(delay(fitted) - delay(truth)) / abs(delay(truth))


def _resonance(truth: dict, diagnosis) -> dict:  # noqa: ANN001 - Diagnosis
    """A hidden body's scores: ``named`` (modelled), ``err`` (relative frequency error) and
    ``z`` (the same in the fit's own sigma), ``located``, and for the nearest claimed
    resonance the DOFs it couples, whether f lies in the ranges it allows and their width
    relative to f."""
    f = truth["f_hz"]
    bands = [x.band_hz for x in (*diagnosis.located, *diagnosis.unexplained)]
    located = any(lo <= 1.15 * f and hi >= 0.85 * f for lo, hi in bands)
    # chosen, or a rival the data do not tell from the chosen effect (as for the catalogue)
    fits = [e.to_json() for e in diagnosis.effects if e.effect.startswith("resonance")]
    if not fits:
        return {"named": False, "err": math.nan, "z": math.nan, "located": located}
    best = min(fits, key=lambda e: abs(e["params"]["f_hz"] - f))
    err = abs(best["params"]["f_hz"] - f) / f
    sigma = best["sigma"]["f_hz"]
    coupled = best["reading"]["coupled"]
    modelled = err <= 0.15 and "POS" in coupled and set(coupled) <= set(truth["coupled"])
    ranges = best["reading"]["f_hz_ranges"]
    return {"named": modelled, "err": err,
            "z": math.nan if not sigma else abs(best["params"]["f_hz"] - f) / sigma,
            "located": located or modelled, "coupled": coupled,
            "f_in_range": any(lo <= f <= hi for lo, hi in ranges),
            "f_range_width": sum(hi - lo for lo, hi in ranges) / f}




def _line(s: Score) -> str:
    c = s.case
    hidden_ = (f"largest bin {c.largest_sigma:.1f} sigma, present {c.present:6.0f}"
               if c.effect else "drift only" + " " * 27)
    if c.effect == "resonance":
        lo, hi = s.f_allowed
        hidden_ += (f" (body {c.truth['f_hz']:.3g} Hz, Q {c.truth['q']:.2g}; from the truth "
                    f"p {s.truth_p:.1g}, chi2 {s.truth_margin:+.1f} on the search's, f "
                    f"allowed {lo:.3g}-{hi:.3g} Hz: "
                    f"{'resolved' if s.resolved else 'not resolved'})")
    elif c.effect == "channel_filter":
        hidden_ += (f" ({c.truth['channel']} {c.truth['pole_hz']:.3g}/"
                    f"{c.truth['zero_hz']:.3g} Hz)")
    key = "" if math.isnan(s.key_error) else (f"  key param {100 * s.key_error:5.1f} % "
                                               f"({s.key_z:.1f} sigma)")
    verdict = ", ".join(s.claimed) or "consistent"
    if s.coupled:
        verdict += (f" (resonance coupling {'/'.join(s.coupled)}, f "
                    f"{'in' if s.f_in_range else 'outside'} the ranges it allows, "
                    f"{100 * s.f_range_width:.0f} % wide)")
    return (f"{c.name:18s} {hidden_}  chi2/nu {s.chi2_nu_nominal:6.2f} -> "
            f"{s.chi2_nu_final:5.2f}  {'ok ' if s.named else 'MISS'} {verdict}{key}"
            f"  p {s.p_value:.1g}  [{s.seconds:.0f} s, diagnosis {s.diagnosis_seconds:.0f} s]")


def _median_pct(x: Sequence[float]) -> str:
    return f"{100 * np.median(x):.0f} %" if len(x) else "-"


def summary(scores: Sequence[Score]) -> list[str]:
    """The issue's targets, as measured on `scores` (a corpus without effect cases or without
    nulls leaves their lines out)."""
    out = []
    for kind, label, target in (("resonance", "modes in no list (resonance)", 80),
                                ("channel_filter", "one channel's own stage (channel_filter)",
                                 90),
                                ("pair", "two effects at once, both named", 80)):
        some = [s for s in scores if s.kind == kind]
        if some:
            named = [s for s in some if s.named]
            keyed = [s for s in named if s.key_error <= KEY_TOLERANCE]
            out.append(f"{label}: {len(named)}/{len(some)} = {100 * len(named) / len(some):.0f}"
                       f" % (target >= {target} %), key parameters within "
                       f"{100 * KEY_TOLERANCE:.0f} %: {len(keyed)}/{len(some)}")
            if kind == "resonance":
                held = [s for s in some if s.truth_p < 0.01]
                limited = [s for s in held if not s.named and s.truth_margin <= AS_GOOD]
                out.append(f"  with evidence enough from a fit started at the truth (p < 0.01, "
                           f"the search's cost paid): {len(held)}/{len(some)}, of which "
                           f"modelled {sum(s.named for s in held)}; missed where the search's "
                           f"fit explains the data as well as the truth's (chi2 within "
                           f"{AS_GOOD:g}): {len(limited)}")
                resolved = [s for s in some if s.resolved]
                others = [s for s in some if not s.resolved]
                right = [s for s in resolved if s.key_error <= RESOLVED_F and s.coupled_right]
                told = [s for s in others if math.isfinite(s.key_error)]
                out.append(f"  resolved by the data (the truth's structure, fitted from the "
                           f"truth, beats the nominal at p < 0.01 and fixes f within "
                           f"{100 * RESOLVED_F:.0f} %): {len(resolved)}/{len(some)}; of them "
                           f"modelled with f within {100 * RESOLVED_F:.0f} % and the coupled "
                           f"DOFs right: {len(right)}/{len(resolved)} (target >= 90 %)")
                out.append(f"  not resolved: {len(others)}; catalogue effects called the full "
                           f"explanation where the truth's structure fits better by more "
                           f"than the noise: {sum(s.wrongly_full for s in others)} (target 0); "
                           f"a resonance claimed with f in the range the data allow: "
                           f"{sum(bool(s.f_in_range) for s in told)}/{len(told)}")
                claims = [s for s in some if math.isfinite(s.key_error)]
                out.append(f"  claimed within 15 % of its frequency, whatever DOFs it couples: "
                           f"{sum(s.key_error <= 0.15 for s in some)}/{len(some)}; of the "
                           f"{len(claims)} claimed, f within 2 of its own sigmas: "
                           f"{sum(s.key_z <= 2 for s in claims)}, f in the ranges the data "
                           f"allow: {sum(bool(s.f_in_range) for s in claims)} (their width "
                           f"median {_median_pct([s.f_range_width for s in claims])} of f)")
                out.append(f"  located (a band holding f +- 15 %, or modelled): "
                           f"{sum(s.located for s in some)}/{len(some)}; passed off as "
                           f"catalogue effects with nothing unexplained: "
                           f"{sum(s.forced for s in some)}/{len(some)} (target 0)")
    effects = [s for s in scores if s.kind == "single"]
    nulls = [s for s in scores if not s.case.effect]
    named = [s for s in effects if s.named]
    keyed = [s for s in named if s.key_error <= KEY_TOLERANCE]
    secs = np.array([s.seconds for s in scores])
    if effects:
        z = np.array([s.key_z for s in named if math.isfinite(s.key_z)] or [np.nan])
        out += [f"catalogue effects named (or equivalent): {len(named)}/{len(effects)} "
                f"= {100 * len(named) / len(effects):.0f} % (target >= 90 %)",
                f"  with the key parameter within {100 * KEY_TOLERANCE:.0f} %: {len(keyed)}/"
                f"{len(effects)} = {100 * len(keyed) / len(effects):.0f} %",
                f"  key parameter errors in the fit's own sigmas: RMS "
                f"{np.sqrt(np.mean(z**2)):.2f} over {int(np.isfinite(z).sum())} cases (1 when "
                f"the sigmas are honest), beyond 2 sigma in {int(np.sum(z > 2))}"]
    if nulls:
        out.append(f"nulls with an effect claimed: {sum(not s.named for s in nulls)}/"
                   f"{len(nulls)} (target 0)")
    final = [s.chi2_nu_final for s in named]
    null_chi = [s.chi2_nu_nominal for s in nulls]
    chi = [f"mean {np.mean(final):.2f}, max {np.max(final):.2f}" if final else "",
           f"nulls' mean {np.mean(null_chi):.2f}, max {np.max(null_chi):.2f}" if null_chi else ""]
    if any(chi):
        label = "chi2/nu after augmentation" if final else "chi2/nu"
        out.append(f"{label}: " + "; ".join(c for c in chi if c))
    if len(secs):
        diag = np.array([s.diagnosis_seconds for s in scores])
        out.append(f"seconds per case: diagnosis median {np.median(diag):.0f} (target <= 15), "
                   f"max {np.max(diag):.0f} (target <= 30); with the measurement median "
                   f"{np.median(secs):.0f}, max {np.max(secs):.0f}")
        measuring = secs - diag
        out.append(f"measurement (the twin's engine and the estimates): {np.sum(measuring):.0f} s "
                   f"over {len(secs)} cases, median {np.median(measuring):.1f} s a case")
    return out
