"""``twind diagnose``: is the nominal model enough, where does it miss, which physics left out
explains the miss, and how much better the augmented model fits.

1. The nominal parameters are refitted (:func:`~twind.analysis.identification.fit.fit`); the residuals are
   searched band by band with the false alarms of the whole search controlled
   (:func:`~twind.analysis.identification.locate.locate`).
2. Effects are chosen one by one (forward selection): every hypothesis (the catalogue,
   :data:`~twind.model.effects.CATALOGUE`, with ``resonance``, a mode anywhere in the
   band, and the ``channel_filter`` family, one channel's own stage) is fitted together
   with the nominal parameters and the effects already chosen. Its evidence is the drop in
   residual power, normalised by the residuals' own noise level (robust scale,
   F-distributed tails, bin correlation, as ``locate`` uses): a likelihood ratio with
   ``k`` parameters, its p-value (searches paid for, Bonferroni over the hypotheses of the
   step) and ``delta_bic = LR - k ln(N)``. The claimed one with the highest delta BIC
   joins; claimed ones that fit about as well (likelihood ratio within
   :data:`EQUIVALENT_LR`) are its rivals, not told apart by these data. An effect the
   later ones made redundant (its p-value given the others at least :data:`ALPHA`) leaves.
3. What the final model still misses is searched band by band again: ``unexplained``, and
   the chosen effects are partial. Consistent: nothing located and nothing claimed.
   The method: ``docs/diagnose.md``.

``bounce_roll`` is fitted on more bins: its modes' bands, every bin whatever its coherence
(the BounceRoll notches leave little there), and from where a search over the modes'
frequencies put it (:mod:`twind.analysis.identification.narrow`), which its p-value pays for.
The claims are scored on a corpus of concealed effects by ``twind bench --suite diagnose``
(:mod:`twind.lab.corpus`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from twind import progress
from twind.analysis.diagnosis import (
    ALPHA,
    EQUIVALENT_LR,
    FEW_AVERAGES,
    Diagnosis,
    EffectFit,
    NotFitted,
)
from twind.analysis.estimation.tfset import TFSet
from twind.analysis.identification import locate as search
from twind.analysis.identification import narrow
from twind.analysis.identification.controller import check_controller
from twind.analysis.identification.data import FitData
from twind.analysis.identification.fit import fit
from twind.analysis.identification.inmatrix import InputMatrixCheck
from twind.analysis.identification.locate import _null_moments, locate
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.params import FIT_PARAMS, FitError, with_params
from twind.analysis.identification.result import FitResult
from twind.analysis.separation import separating_measurement
from twind.config import OpticConfig
from twind.errors import MeasurementWarning
from twind.model.effects import (
    BODY_DOFS,
    CATALOGUE,
    FAMILIES,
    entry,
    own_values,
    param_name,
    parts,
)

MIN_COHERENCE = 0.0
"""Of the bins ``diagnose`` fits (:func:`diagnose`)."""


def diagnose(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig,
             params: Sequence[str] = FIT_PARAMS,
             min_coherence: float = MIN_COHERENCE, max_effects: int | None = None,
             controller: bool = True, input_matrix: InputMatrixCheck | None = None
             ) -> Diagnosis:
    """Diagnose measured TFs of `cfg`'s optic against its nominal model.

    Forward selection: every hypothesis (:data:`~twind.model.effects.CATALOGUE`, the
    ``resonance`` family among them) is fitted with the nominal parameters and the effects
    chosen so far; the one with the highest delta BIC among those claimed (p below
    :data:`ALPHA`, Bonferroni over the hypotheses tried at that step) joins the model, up
    to :data:`MAX_EFFECTS`. A null claims nothing at the first step with probability
    1 - ALPHA, and nothing after. The residuals of the final model are searched band by
    band again: what remains is ``unexplained`` and the chosen effects are partial.

    Parameters
    ----------
    tfs : TFSet or sequence of TFSet
    cfg : OpticConfig
    params : sequence of str
        The nominal parameters refitted alongside every hypothesis.
    min_coherence : float
        Bins fitted (see :meth:`~twind.analysis.identification.data.FitData.from_tfset`): by default every
        response wherever the excitation reached the optic, coherent or not. An effect
        that couples one DOF into another lifts that element out of the noise only where
        it is large; spread thinly, it is plain only in the many incoherent bins together,
        whose errors are the noise's.
    max_effects : int, optional
        Effects chosen at most (default :data:`MAX_EFFECTS`).
    controller : bool
        Check each DOF's measured controller (OUT/IN2) against `cfg`'s first
        (:func:`~twind.analysis.identification.controller.check_controller`) and read the
        plant through the measured one.
    input_matrix : InputMatrixCheck, optional
        The input matrix measured from the recording
        (:func:`~twind.analysis.identification.inmatrix.recorded_input_matrix`); the plant
        is read through it (and through the controller measured after it).

    Returns
    -------
    Diagnosis
    """
    if _averages(tfs) < FEW_AVERAGES:
        warnings.warn(f"{_averages(tfs)} averages: below {FEW_AVERAGES} the band search and "
                      "the claims are not held to their 1 % (at 5, bands were located on 12 "
                      f"of 60 nulls); measure with at least {FEW_AVERAGES}",
                      MeasurementWarning, stacklevel=2)
    cfg = input_matrix.config(cfg) if input_matrix else cfg
    check = check_controller(tfs, cfg) if controller else None
    cfg = check.config if check else cfg
    nominal = fit(tfs, cfg, params, min_coherence)
    tests = search.searched(tfs, cfg, nominal)
    located = search.significant(tests)
    checked = {"controller": check, "input_matrix": input_matrix,
               "p_band": search.smallest_corrected(tests),
               "bands": len(tests), "hypotheses": len(_candidates([]))}
    unit = _unit(nominal, tfs)
    chosen, rivals, first_step, not_fitted = _select(
        tfs, cfg, params, nominal, unit, MAX_EFFECTS if max_effects is None else max_effects)
    if not chosen:
        return Diagnosis(nominal, located, [], nominal, located, first_step=first_step,
                         not_fitted=not_fitted, **checked)
    final = _prune(tfs, cfg, params, chosen, unit)
    rivals = [r for r in rivals if any(c.effect == r.rival_of for c in chosen)]
    unexplained = locate(tfs, cfg, final)
    for c in chosen:
        c.step_result, c.result, c.partial = c.result, final, bool(unexplained)
    bin_hz = float(np.median(np.diff(_sets(tfs)[0].frequency_hz)))
    separations = {(r.rival_of, r.effect): separating_measurement(
        cfg, _alone(chosen, r), r.result, bin_hz=bin_hz) for r in rivals}
    return Diagnosis(nominal, located, chosen + rivals, final, unexplained, separations,
                     first_step, not_fitted, **checked)


def _select(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, params: Sequence[str],
            nominal: FitResult, unit: float, most: int
            ) -> tuple[list[EffectFit], list[EffectFit], list[EffectFit], list[NotFitted]]:
    """Forward selection from the refitted `nominal` model, up to `most` effects: the
    chosen ones (best first), the rivals of each, every hypothesis of the first step, and
    those of every step that gave no fit to weigh."""
    chosen: list[EffectFit] = []
    rivals: list[EffectFit] = []
    first_step: list[EffectFit] = []
    not_fitted: list[NotFitted] = []
    current, whole = nominal, ()
    for _ in range(most):
        tried, failed = _step(tfs, cfg, params, [c.effect for c in chosen], current, whole,
                              unit)
        not_fitted += failed
        if not chosen:
            first_step = tried
        claimed = sorted((c for c in tried if c.p_value < ALPHA), key=lambda c: -c.delta_bic)
        if not claimed:
            break
        best = claimed[0]
        best.equivalent = [c.effect for c in claimed[1:] if best.lr - c.lr < EQUIVALENT_LR]
        chosen.append(best)
        rivals += [replace(c, rival_of=best.effect) for c in claimed[1:]
                   if c.effect in best.equivalent]
        current, whole = best.result, best.whole
    return chosen, rivals, first_step, not_fitted


def _step(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, params: Sequence[str],
          chosen: list[str], current: FitResult, whole: tuple[tuple[float, float], ...],
          unit: float) -> tuple[list[EffectFit], list[NotFitted]]:
    """Every hypothesis not yet `chosen`, each fitted with them (:func:`_candidates`): the
    fits, and those that gave none to weigh. Each is tried even when no band stands out:
    an effect spread thinly over many bands can be plain in its own fit and invisible band
    by band."""
    left = _candidates(chosen)
    outcomes: list[EffectFit | NotFitted] = []
    for e in left:
        progress.note(f"step {len(chosen) + 1}: {e}")
        if e in FAMILIES:
            outcomes += _try_family(tfs, cfg, params, chosen, e, current, whole, unit,
                                    len(left))
        else:
            outcomes.append(_try(tfs, cfg, params, chosen, e, current, whole, unit, len(left)))
    return ([x for x in outcomes if isinstance(x, EffectFit)],
            [x for x in outcomes if isinstance(x, NotFitted)])


def _prune(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, params: Sequence[str],
           chosen: list[EffectFit], unit: float) -> FitResult:
    """Backward: each chosen effect's p-value given the others; the one the others made
    most redundant leaves `chosen` while its p-value is at least :data:`ALPHA`. Returns
    the final joint fit."""
    current, whole = chosen[-1].result, chosen[-1].whole
    while True:
        without = _given_others(tfs, cfg, params, chosen, current, whole, unit)
        worst = max(chosen, key=lambda c: c.p_given_others or 0.0)
        if len(chosen) < 2 or (worst.p_given_others or 0.0) < ALPHA:
            return current
        chosen.remove(worst)
        current = without[worst.effect]


MAX_EFFECTS = 3
"""Effects a diagnosis chooses at most."""


def _candidates(chosen: Sequence[str]) -> list[str]:
    """The hypotheses a step tries: every catalogue entry not yet chosen, each family
    (:data:`~twind.model.effects.FAMILIES`) with a member left, and another mode in no
    list (``resonance#2``) once one is."""
    left = [e for e in CATALOGUE if e not in chosen]
    left += [f for f, members in FAMILIES.items() if set(members) - set(chosen)]
    for repeatable in (e.id for e in CATALOGUE.values() if e.repeatable):
        taken = sum(_base(c) == repeatable for c in chosen)
        if taken:
            left.append(f"{repeatable}#{taken + 1}")
    return left


def _base(effect: str) -> str:
    """The catalogue entry a repeated one (``resonance#2``) stands for."""
    return effect.partition("#")[0]


def _alone(chosen: list[EffectFit], rival: EffectFit) -> FitResult:
    """The fit of the chosen effect `rival` stood against, as it was when chosen."""
    return next(c for c in chosen if c.effect == rival.rival_of).step_result


def _try_family(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, params: Sequence[str],
                chosen: Sequence[str], family: str, current: FitResult,
                whole: tuple[tuple[float, float], ...], unit: float, tried: int
                ) -> list[EffectFit | NotFitted]:
    """The likeliest members of `family` (a channel filter: which channel), each as
    :func:`_try` fits one: the members ranked by the drop in chi^2 their first-order
    change alone would make, the best :data:`FAMILY_FITS` fitted from the best of a grid
    of stages (rivals of one another), the choice paid for as a search over every member
    (Bonferroni). The others are ranked out, not failed."""
    members = [m for m in FAMILIES[family] if m not in chosen]
    first = _sets(tfs)[0]
    data = FitData.from_tfset(first, current.min_coherence, whole=whole).span()
    ranked = sorted(members, key=lambda m: -_first_order_drop(data, cfg, current, chosen, m))
    fits = [_try(tfs, cfg, params, chosen, m, current, whole, unit, tried,
                 _filter_start(data, cfg, current, chosen, m)) for m in ranked[:FAMILY_FITS]]
    for c in fits:
        if isinstance(c, EffectFit):
            c.p_value = min(1.0, c.p_value * len(members))
    return fits


FAMILY_FITS = 3
"""Members of a family fitted in full (the others ranked out at first order)."""
_STAGES = [(pole, zero) for pole in (1.0, 3.0, 10.0, 30.0, 100.0, 300.0)
           for zero in (math.inf, 0.5 * pole, 0.8 * pole, 1.25 * pole, 2 * pole)]
"""A channel filter's starts: poles across and above the band, zeros none or near."""


def _augmented(data: FitData, cfg: OpticConfig, current: FitResult, chosen: Sequence[str],
               member: str) -> Callable[[dict[str, float]], NDArray]:
    """`member` added to the current model at its values: the whitened residuals as a
    function of the member's own parameters."""
    combo = "+".join([*chosen, member])
    base = {**{n: v for n, v in current.as_dict().items() if n in FIT_PARAMS},
            **_renamed(current, combo)}
    model = ClosedLoopModel.of(cfg, data, combo).for_data(data)

    def residual(own: dict[str, float]) -> NDArray:
        return data.whiten(model({**base, **{param_name(combo, member, n): v
                                             for n, v in own.items()}}))
    return residual


def _first_order_drop(data: FitData, cfg: OpticConfig, current: FitResult,
                      chosen: Sequence[str], member: str) -> float:
    """Drop in chi^2 a filter member's first-order change (a zero minus a pole, in 1/Hz)
    would make alone on the current residuals."""
    residual = _augmented(data, cfg, current, chosen, member)
    r = residual({})
    col = (residual({"inv_zero_hz": 1e-4}) - r) / 1e-4
    return float((col @ r) ** 2 / max(col @ col, 1e-300))


def _filter_start(data: FitData, cfg: OpticConfig, current: FitResult,
                  chosen: Sequence[str], member: str) -> dict[str, float]:
    """The stage of :data:`_STAGES` (and its mirror, pole and zero swapped) that fits the
    current residuals best, as a filter member's start."""
    residual = _augmented(data, cfg, current, chosen, member)
    best, start = math.inf, {}
    for pole, zero in _STAGES:
        for a, b in ((pole, zero), (zero, pole)):
            own = {"inv_pole_hz": 1 / a, "inv_zero_hz": 1 / b}
            with np.errstate(over="ignore", invalid="ignore"):
                r = residual(own)
            chi2 = float(r @ r) if np.all(np.isfinite(r)) else math.inf
            if chi2 < best:
                best, start = chi2, own
    return start


def _try(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, params: Sequence[str],
         chosen: Sequence[str], effect: str, current: FitResult,
         whole: tuple[tuple[float, float], ...], unit: float, tried: int,
         own_start: dict[str, float] | None = None) -> EffectFit | NotFitted:
    """Hypothesis `effect` fitted with the nominal parameters and the `chosen` effects
    (all refitted), against `current` (the model without it); :class:`NotFitted` when its
    fit fails or adds no direction the data determine. Its p-value is Bonferroni'd over the `tried`
    hypotheses of this step; `own_start` starts its own parameters."""
    start, free = _refitted(cfg, current, params)
    combo = "+".join([*chosen, effect])
    held = _renamed(current, combo)
    held.update({param_name(combo, effect, n): v for n, v in (own_start or {}).items()})
    paths: list[float] = []
    scan = None
    try:
        reference = current
        if entry(effect).search == "model_modes":  # fitted on bands around those modes
            first = _sets(tfs)[0]
            res = FitData.from_tfset(first, current.min_coherence).resolution_hz
            whole = tuple(narrow.bands(start, res))
            reference = fit(tfs, start, free, current.min_coherence, effect=current.effect,
                            effect_start=current.as_dict(), whole=whole)
        if entry(effect).narrow:
            found, paths, scan = _search(tfs, start, free, reference, effect, whole, unit)
            held.update({param_name(combo, effect, n): v for n, v in found.items()})
        result = fit(tfs, start, free, current.min_coherence, effect=combo,
                     effect_start=held, whole=whole, unfitted=_unseen(tfs, combo))
    except FitError as err:
        return NotFitted(effect, len(chosen) + 1, f"its fit failed: {err}")
    # directions the effect adds that the data determine (a coil imbalance's common mode
    # is the coil strength's, its butterfly mode moves nothing: two of four gains count)
    k = result.rank - reference.rank
    if k <= 0:
        return NotFitted(effect, len(chosen) + 1, "it adds no direction the data determine "
                         f"(rank {result.rank}, {reference.rank} without it)")
    lr = max(reference.chi2 - result.chi2, 0.0) / unit
    n = 2 * reference.bins
    p = _p_value(lr, k, paths, _searched(result, combo, effect))
    return EffectFit(effect, result, lr, k, min(1.0, p * tried),
                     lr - k * math.log(max(n, 1)), whole=whole, searched=paths,
                     radius_m=cfg.sus.radius_m,
                     f_ranges=scan.plausible(F_MARGIN * unit) if scan else [])


F_MARGIN = float(stats.chi2.ppf(0.95, 1))
"""How much less of the misfit (chi^2, in the nulls' units) a trial frequency of a
``resonance`` search may remove than the best and still be reported as allowed: 95 % for
one parameter."""


def evidence(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, diagnosis: Diagnosis,
             effect: str, start: dict[str, float]) -> tuple[float, float]:
    """The p-value `effect` would be given at the first step from a fit started at `start`
    (its search's look-elsewhere cost and the hypotheses tried paid as ``diagnose`` pays
    them), and that fit's likelihood ratio over the nominal model: what the data hold for
    it, whatever the search finds. For a benchmark that knows the truth; (1, 0) when the
    fit fails.

    Parameters
    ----------
    tfs : TFSet or sequence of TFSet
        The measurements diagnosed.
    cfg : OpticConfig
        The optic; the fit starts at `diagnosis`'s refitted nominal parameters.
    diagnosis : Diagnosis
        The diagnosis of `tfs` (its nominal fit and first step).
    effect : str
        The catalogue entry weighed.
    start : dict of str to float
        `effect`'s parameters the fit starts from (the truth, for a benchmark).

    Returns
    -------
    p_value : float
    lr : float
        The likelihood ratio over the nominal model, in the nulls' units.
    """
    nominal = diagnosis.nominal
    first = next((c for c in diagnosis.first_step if c.effect == effect), None)
    paths = first.searched if first else []
    cfg, free = _refitted(diagnosis.read_through(cfg), nominal)
    try:
        result = fit(tfs, cfg, free, nominal.min_coherence, effect=effect, effect_start=start,
                     unfitted=_unseen(tfs, effect))
    except FitError:
        return 1.0, 0.0
    k = result.rank - nominal.rank
    lr = max(nominal.chi2 - result.chi2, 0.0) / _unit(nominal, tfs)
    if k <= 0:
        return 1.0, lr
    p = _p_value(lr, k, paths, _searched(result, effect, effect))
    return min(1.0, p * max(len(diagnosis.first_step), 1)), lr


def explained(tfs: TFSet | Sequence[TFSet], diagnosis: Diagnosis) -> float:
    """The final model's likelihood ratio over the refitted nominal, in the nulls' units
    (:func:`evidence`'s): how much of the misfit the chosen effects explain."""
    nominal, final = diagnosis.nominal, diagnosis.final
    return max(nominal.chi2 - final.chi2, 0.0) / _unit(nominal, tfs)


PROFILE_FACTORS = (0.7, 0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15, 1.2, 1.3)
"""Where a ``resonance``'s frequency is held, relative to its start, to profile it."""


def f_profile(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, diagnosis: Diagnosis,
              start: dict[str, float], factors: Sequence[float] = PROFILE_FACTORS
              ) -> tuple[float, float]:
    """The range of a ``resonance``'s frequency the data allow at 95 % (one parameter's
    chi^2 rise of 3.84, in the nulls' units) from fits started at `start` with its
    frequency held at each of `factors` times ``start["f_hz"]``, the other parameters
    refitted: whether a structure's frequency is fixed by the data at all. For a benchmark
    that knows the truth; the range reaches a grid end when the data do not bound it there.

    Parameters
    ----------
    tfs : TFSet or sequence of TFSet
        The measurements diagnosed.
    cfg : OpticConfig
        The optic (the fits start at `diagnosis`'s refitted nominal parameters).
    diagnosis : Diagnosis
        The diagnosis of `tfs` (its nominal fit, and the controller it was read through).
    start : dict of str to float
        The ``resonance``'s parameters the fits start from (the truth, for a benchmark).
    factors : sequence of float
        Where f is held, relative to ``start["f_hz"]``, ascending.

    Returns
    -------
    (float, float)
        Lowest and highest f (Hz) allowed; (nan, nan) when no fit succeeds.
    """
    nominal = diagnosis.nominal
    cfg, free = _refitted(diagnosis.read_through(cfg), nominal)
    unit = _unit(nominal, tfs)
    f_name = param_name("resonance", "resonance", "f_hz")
    chi2 = {}
    for x in factors:
        try:
            r = fit(tfs, cfg, free, nominal.min_coherence, effect="resonance",
                    effect_start=start, unfitted=_unseen(tfs, "resonance"),
                    held={f_name: start["f_hz"] * x})
        except FitError:
            continue
        chi2[x] = r.chi2 / unit
    if not chi2:
        return math.nan, math.nan
    best = min(chi2.values())
    inside = [x for x, c in chi2.items() if c - best <= stats.chi2.ppf(0.95, 1)]
    return start["f_hz"] * min(inside), start["f_hz"] * max(inside)


def _refitted(cfg: OpticConfig, result: FitResult, params: Sequence[str] = FIT_PARAMS
              ) -> tuple[OpticConfig, list[str]]:
    """`cfg` at `result`'s identified nominal parameters, and those of `params` to free:
    the ones the data left undetermined (a Q without its resonance) are held, which a
    hypothesis fit would otherwise chase again to its evaluation limit."""
    start = replace(cfg, sus=with_params(cfg.sus, {n: v for n, v in result.identified().items()
                                                   if n in FIT_PARAMS}))
    return start, [p for p in params if p in result.names and p not in result.unidentifiable]


def _unseen(tfs: TFSet | Sequence[TFSet], combo: str) -> list[str]:
    """The couplings of `combo`'s resonances to DOFs no measurement excites: a body's pull
    on them reaches the data only through products with the others, too weakly to tell
    from a drift of the nominal model, so they are held at zero."""
    excited = {d for t in _sets(tfs) for d in t.excited}
    return [param_name(combo, e, f"g_{d}") for e in parts(combo)
            if entry(e).body for d in BODY_DOFS if d not in excited]


def _p_value(lr: float, k: int, paths: Sequence[float], searched: int) -> float:
    """A likelihood ratio's p-value: chi^2 with `k` directions, or, for a mode searched
    for, Davies' bound over each search (the `searched` parameters it set are paid for by
    the paths, not counted)."""
    if not paths:
        return float(stats.chi2.sf(lr, k))
    return sum(narrow.p_value(lr, k - searched, path) for path in paths)


def _searched(result: FitResult, combo: str, effect: str) -> int:
    """How many of `effect`'s searched parameters `result` determined."""
    names = {param_name(combo, effect, n) for n in (*entry(effect).narrow,
                                                    *entry(effect).searched)}
    return sum(math.isfinite(s) for n, s in zip(result.names, result.sigma, strict=True)
               if n in names)


def _search(tfs: TFSet | Sequence[TFSet], start: OpticConfig, free: list[str],
            reference: FitResult, effect: str, whole: tuple[tuple[float, float], ...],
            unit: float) -> tuple[dict[str, float], list[float], narrow.Scan | None]:
    """Where `effect`'s mode starts, searched on the first measurement in the residuals of
    `reference` (:mod:`~twind.analysis.identification.narrow`), the searches' paths and, for a
    ``resonance``, its scan."""
    first = _sets(tfs)[0]
    data = FitData.from_tfset(first, reference.min_coherence, whole=whole).span()
    values = reference.as_dict()
    if entry(effect).search == "model_modes":
        found, path = narrow.search(data, start, values, free, unit, reference.effect)
        return found, [path], None
    return narrow.search_resonance(data, start, values, free, reference.effect)


def _renamed(result: FitResult, combo: str) -> dict[str, float]:
    """`result`'s effect parameters under the names the combination `combo` gives them."""
    if not result.effect:
        return {}
    values = result.as_dict()
    return {param_name(combo, entry, n): v for entry in parts(result.effect)
            for n, v in own_values(result.effect, entry, values).items()}


def _given_others(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, params: Sequence[str],
                  chosen: list[EffectFit], final: FitResult,
                  whole: tuple[tuple[float, float], ...], unit: float
                  ) -> dict[str, FitResult]:
    """Each chosen effect's p-value against the final model without it (two or more), and
    the fits without each."""
    if len(chosen) < 2:
        for c in chosen:
            c.p_given_others = None
        return {}
    start, free = _refitted(cfg, final, params)
    fits = {}
    for c in chosen:
        rest = "+".join(o.effect for o in chosen if o is not c)
        c.p_given_others = None
        try:
            without = fit(tfs, start, free, final.min_coherence, effect=rest,
                          effect_start=_renamed(final, rest), whole=whole,
                          unfitted=_unseen(tfs, rest))
        except FitError:
            continue
        fits[c.effect] = without
        k = final.rank - without.rank
        lr = max(without.chi2 - final.chi2, 0.0) / unit
        c.p_given_others = (min(1.0, _p_value(lr, k, c.searched,
                                              _searched(final, final.effect, c.effect)))
                            if k > 0 else 1.0)
    return fits


def _unit(nominal: FitResult, tfs: TFSet | Sequence[TFSet]) -> float:
    """The unit of a likelihood ratio: the null's per-bin power (robust scale, F tails of
    coherence-based errors) over independent bins (Hann neighbours are correlated).

    It is about twice what pure noise takes from one real direction, so the chi^2
    reference is conservative (the catalogue's likelihood ratios average 0.2-0.95 of their
    directions on nulls). A unit matched to each hypothesis's mean share of the noise
    (``tr(P R)``, P the projection onto its directions, R the bins' correlation) brought
    those means near 1 but claimed on 9 of 160 twin nulls, 5 of 20 at 5 averages: the
    heavy tails of the coherence-based errors, not the mean, set the rate at 1 %
    (docs/limits.md)."""
    mu, _ = _null_moments(_averages(tfs))
    inflation = 1.0 + 2.0 * sum(r * r for r in nominal.bin_correlation)
    return 2 * nominal.noise_scale**2 * mu * inflation


def _averages(tfs: TFSet | Sequence[TFSet]) -> int:
    return min(t.averages for t in _sets(tfs))


def _sets(tfs: TFSet | Sequence[TFSet]) -> list[TFSet]:
    """The measurements, one or several."""
    return [tfs] if isinstance(tfs, TFSet) else list(tfs)
