"""``twind diagnose`` of a plant given as a state-space model: where the model misses the
measurement, which of its modes moved or vanished, what it lacks, and how much better the fit
becomes.

The diagnosis of an SOS (:mod:`twind.analysis.diagnose`), for a model known by its matrices
alone:

1. What any real measurement adds to a model is fitted first, with a loss that grossly wrong
   bins cannot drag (a narrow mode off its frequency): each readback's calibration, a delay
   and a low-pass (:mod:`~twind.analysis.statespace.fit`). Its residuals are searched band
   by band (:func:`~twind.analysis.identification.locate.band_tests`, Holm over all).
2. The model's modes the data show elsewhere are moved all at once: each visible mode
   matched, by the shape of its response as well as its frequency, to the peaks the data
   show over the whole band (:mod:`~twind.analysis.statespace.moves`), each peak given to
   one mode, those fitted together with the calibrations, and each kept only while the data
   need it given the others. A real suspension differs from its model in several modes at
   once; chosen one at a time, a moved mode would be read as a new one beside the old.
3. Further changes are chosen one at a time (forward selection) from the families of
   :data:`~twind.analysis.statespace.model.FAMILIES`: a mode moved or scaled (0: missing),
   a mode in no model (tried near the data's peaks), a readback that also reads another, a
   drive's flat crosstalk into a readback, a drive that also drives another input of its
   stage (:mod:`~twind.analysis.statespace.couplings`; with the modes that input reveals
   moved where the data have them, as in 2), a readback's own first-order stage.
   The members are screened on the residuals (:mod:`~twind.analysis.statespace.search`), the
   nearest a claim fitted in full with the calibrations, the delay and the changes chosen
   before. The evidence is the drop in deviance under the errors' own distribution
   (Student's t, :class:`~twind.analysis.statespace.fit.Noise`), over the bins'
   correlation: a likelihood ratio whose p-value pays for the searches (Davies) and for
   every member and family tried (Bonferroni). The claimed change of highest delta BIC
   joins, up to :data:`MAX_EFFECTS`; those the later ones made redundant leave. In a closed
   loop whose other damping loops are closed too, a mode's change is screened and fitted
   through the whole closed loop.
4. What the final model still misses is searched again: ``unexplained``.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from twind import progress
from twind.analysis.identification import narrow
from twind.analysis.identification.data import FitData
from twind.analysis.identification.fit import bin_correlation
from twind.analysis.identification.narrow import SEARCH_Q
from twind.analysis.identification.locate import Located, band_tests, significant
from twind.analysis.identification.params import FitError
from twind.analysis.statespace import bounds
from twind.analysis.statespace.couplings import screen as screen_couplings
from twind.analysis.statespace.fit import (
    ROBUST_SCALE,
    Noise,
    PlantFit,
    fit_baseline,
    fit_plant,
    modelled_entries,
    one_blas_thread,
    recalibrated,
)
from twind.analysis.statespace.measurement import PlantSet
from twind.analysis.statespace.model import FAMILIES, Effect, PlantModel, other_loops
from twind.analysis.statespace.moves import (
    Candidate,
    assign,
    candidates,
    holders,
    unheld,
    unshown,
)
from twind.analysis.statespace.peaks import Peak, measured_peaks
from twind.analysis.statespace.report import Claim, PlantDiagnosis
from twind.analysis.statespace.search import SHIFT, Residuals, grid
from twind.config.statespace import StateSpaceOptic

ALPHA = 0.01
"""False-alarm probability of claiming a change."""
EQUIVALENT_LR = 6.0
"""Claimed changes whose likelihood ratios lie within this of the best one's are its rivals
(as for an SOS, :data:`twind.analysis.diagnosis.EQUIVALENT_LR`)."""
MAX_EFFECTS = 6
"""Changes a diagnosis chooses at most: a real suspension may differ from its model in
several modes."""
STEP_FITS = 3
"""Members fitted in full at a step: those whose screens come nearest a claim, whatever their
family (the others ranked out on the residuals)."""
COUPLING_FITS = 2
"""Drives that also drive another input fitted at a step besides the :data:`STEP_FITS`
nearest, those whose screens come nearest a claim: a share screened with the other input's
modes where the model has them sees little of them where they moved, which only its fit
with the moves it reveals shows (:func:`_revealing`)."""
VISIBLE = 1.0
"""A model mode is tried only where its response adds at least this to the data's chi^2 in
the noise's units: one the data cannot see can be neither moved nor missing."""
_STAGES = [(p, z) for p in (0.3, 1.0, 3.0, 10.0, 30.0, 100.0) for z in (math.inf, 0.5 * p, 2 * p)]
"""A readback's stage's starts: poles across and above the band, zeros none or near."""
BUDGET_S = 90.0
"""A diagnosis's default time budget (s): no step of choosing starts past it."""
HOPELESS = 0.25
"""A member whose screen drops the chi^2 by less than this part of what a claim needs is not
fitted: its full fit (the calibrations refitted with it) seldom gains that much more."""


@one_blas_thread
def diagnose_plant(plant: PlantSet, optic: StateSpaceOptic, max_effects: int = MAX_EFFECTS,
                   budget_s: float = BUDGET_S) -> PlantDiagnosis:
    """Diagnose a measured plant against `optic`'s state-space model, on one BLAS thread
    (:data:`~twind.analysis.statespace.fit.one_blas_thread`): a file gives the same
    diagnosis every time.

    Parameters
    ----------
    plant : PlantSet
        The measurement (:func:`~twind.analysis.statespace.measurement.read_plant`).
    optic : StateSpaceOptic
    max_effects : int
        Changes chosen at most.
    budget_s : float
        Seconds after which no further change is tried (the diagnosis says so): a large
        multi-drive set's fits take tens of seconds each.

    Returns
    -------
    PlantDiagnosis

    Raises
    ------
    FitError
        If no bin of the measurement is coherent.
    """
    deadline = time.monotonic() + budget_s
    base = fit_baseline(plant, optic)
    data, model, free, noise, nominal = base.data, base.model, base.free, base.noise, base.fit
    unit = _unit(nominal, data, noise)
    located = _located(data, model, nominal)
    model, moves, current = _moves(data, model, optic, plant, free, nominal, noise, unit,
                                   base.modelled)
    if moves:  # the noise as the moved modes leave the residuals, not as their misfit did
        noise = Noise.of(current.residual[modelled_entries(data, base.modelled)],
                         data.averages)
        current = fit_plant(data, model, current.nuisance, free, current.effects, noise=noise,
                            limits=bounds.limits(model, data, current.effects))
        unit = _unit(current, data, noise)
        for c in moves:
            c.fit = current
    model, chosen, rivals, first, stopped = _select(data, model, optic, plant, free, current,
                                                    noise, unit, max_effects, moves, deadline)
    if not chosen:
        return PlantDiagnosis(optic, plant, data, model, nominal, noise, located, [], nominal,
                              located, first, stopped)
    final_model, final = _prune(data, model, optic, plant, free, chosen, noise, unit)
    final_model, final, pinned = _unpinned(data, final_model, optic, plant, free, final, noise,
                                           nominal)
    chosen = [c for c in chosen if c.effect.key() not in pinned]
    unexplained = _located(data, final_model, final)
    for c in chosen:
        c.fit, c.partial = final, bool(unexplained)
        c.local = _local(data, base.model, final_model, nominal, final, c.effect)
    rivals = [r for r in rivals if any(c.effect.key() == r.rival_of for c in chosen)]
    return PlantDiagnosis(optic, plant, data, final_model, nominal, noise, located,
                          chosen + rivals, final, unexplained, first, stopped)


def _local(data: FitData, nominal_model: PlantModel, model: PlantModel, nominal: PlantFit,
           final: PlantFit, effect: Effect) -> tuple[float, float, int] | None:
    """chi2/nu of `nominal` (on `nominal_model`) and of `final` (on `model`) over the bins
    where `effect` (at its final values) moves the final prediction by more than the error,
    and their number."""
    without = [(e, e.null(v) if e.key() == effect.key() else v) for e, v in final.effects]
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


# ------------------------------------------------------------------------------ moved modes
def _moves(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
           free: list[str], nominal: PlantFit, noise: Noise, unit: float,
           modelled: NDArray[np.bool_]) -> tuple[PlantModel, list[Claim], PlantFit]:
    """The model's modes the data show elsewhere, all at once: each visible mode tried at
    the data's peaks (:func:`~twind.analysis.statespace.moves.candidates`), the places
    given out best first, each mode one and each place one mode
    (:func:`~twind.analysis.statespace.moves.assign`), those fitted together with the
    calibrations, then each kept only while the data need it given the others
    (:func:`_prune`). A real suspension differs from its model in several modes at once:
    chosen one at a time, the first changes would be fitted against residuals of all the
    others, and a mode the model has in the wrong place would be read as a new one beside
    the old.

    Returns
    -------
    PlantModel
        With its other loops' feedback made from the moved modes.
    list of Claim
        The moves kept, each with its p-value given the others.
    PlantFit
        The fit holding them (`nominal` when none).
    """
    res = _residuals(data, model, free, nominal)
    screen_unit = _screen_unit(noise, unit)
    visible = _visible(res, model, [], unit)
    members = len(visible) * len(FAMILIES)
    chosen = _places(res, visible, screen_unit, HOPELESS * _needed(members, 3))
    effects = [c.effect(model, data.resolution_hz) for c in chosen]
    if not effects:
        return model, [], nominal
    progress.note(f"{len(effects)} modes moved together")
    looped, fit = _together(data, model, optic, plant, free, nominal, noise, effects,
                            _needed(members, 3) * unit)
    looped, fit, _ = _unpinned(data, looped, optic, plant, free, fit, noise, nominal)
    fitted = {e.key() for e, _ in fit.effects}
    kept = [(e, c) for (e, _), c in zip(effects, chosen, strict=True) if e.key() in fitted]
    if not kept:
        return model, [], nominal
    fit = recalibrated(data, looped, fit, free, modelled, noise,
                       bounds.limits(looped, data, fit.effects))
    model, fit = _relooped(data, looped, optic, plant, free, fit, noise)
    claims = [Claim(e, fit, 0.0, 3, 1.0, 0.0, members=members, paths=c.paths)
              for e, c in kept]
    model, fit = _prune(data, model, optic, plant, free, claims, noise, unit, nominal, members)
    seen_in = _seen_in(data, nominal, fit)
    for c in claims:
        c.fit, c.p_value, c.seen_in = fit, c.p_given_others or 0.0, seen_in
    return model, claims, fit


def _together(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
              free: list[str], nominal: PlantFit, noise: Noise,
              effects: Sequence[tuple[Effect, dict]], need: float
              ) -> tuple[PlantModel, PlantFit]:
    """The moves `effects` (best first) fitted together, with the model they leave.

    Started where each was found, two modes can share one peak, each holding part of it: a
    false minimum, which shows as a joint fit worse than the first move alone. Then the
    moves are added one at a time to the first instead, each kept only if it drops the
    deviance by `need` (a claim's likelihood ratio, in deviance) and is not pinned."""
    looped = _looped(data, model, optic, plant, effects)
    fit = fit_plant(data, looped, nominal.nuisance, free, effects, noise=noise,
                    limits=bounds.limits(looped, data, effects))
    if len(effects) == 1:
        return looped, fit
    first = list(effects[:1])
    alone_model = _looped(data, model, optic, plant, first)
    alone = fit_plant(data, alone_model, nominal.nuisance, free, first, noise=noise,
                      limits=bounds.limits(alone_model, data, first))
    if alone.deviance >= fit.deviance:
        return looped, fit
    progress.note("fitted together, moves shared a peak: adding them one at a time")
    looped, fit, _ = _added(data, model, optic, plant, free, alone, effects[1:], noise, need)
    return (alone_model if looped is None else looped), fit


def _added(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
           free: list[str], fit: PlantFit, effects: Sequence[tuple[Effect, dict]],
           noise: Noise, need: float
           ) -> tuple[PlantModel | None, PlantFit, list[tuple[Effect, float, str]]]:
    """`fit` with each of the moves `effects` (best first) added in turn, each kept only if
    it drops the deviance by `need` and is not pinned: the model they leave (None when none
    is kept), the fit, and each kept with its drop in deviance and where it is seen."""
    looped, kept = None, []
    for effect in effects:
        progress.tick()
        trial = [*fit.effects, effect]
        trial_model = _looped(data, model, optic, plant, trial)
        try:
            tried = fit_plant(data, trial_model, fit.nuisance, free, trial, noise=noise,
                              new=effect[0], limits=bounds.limits(trial_model, data, trial))
        except FitError:
            continue
        drop = fit.deviance - tried.deviance
        if drop >= need and not bounds.pinned(tried, effect[0], trial_model):
            kept.append((effect[0], drop, _seen_in(data, fit, tried)))
            looped, fit = trial_model, tried
    return looped, fit, kept


def _resonance_places(data: FitData, peaks: Sequence[Peak],
                      avoid: Sequence[tuple[float, float]]) -> tuple[NDArray[np.float64], float]:
    """Where a mode in no model is tried: trial frequencies within two widths (and two bins)
    of each peak the data show, but where a moved mode lies (`avoid`, Hz); and how many
    times more trials a sweep of the whole band would take."""
    lo, hi = bounds.band(data)
    every = grid(lo, hi, SEARCH_Q[-1], data.resolution_hz)
    near = np.zeros(every.size, dtype=bool)
    for p in peaks:
        near |= np.abs(every - p.f_hz) <= 2 * p.width_hz + 2 * data.resolution_hz
    for a, b in avoid:
        near &= (every <= a) | (every >= b)
    return every[near], every.size / max(int(near.sum()), 1)


def _residuals(data: FitData, model: PlantModel, free: list[str], fit: PlantFit) -> Residuals:
    """`fit`'s residuals, for the screens."""
    return Residuals(data, model, model(fit.nuisance, fit.effects),
                     model.gain(fit.nuisance, fit.effects),
                     {r: fit.nuisance[f"g_{r}"] for r in range(data.H.shape[1])
                      if f"g_{r}" in free})


def _screen_unit(noise: Noise, unit: float) -> float:
    """A screen's drop in chi^2 that one fitted parameter makes in pure noise: for residuals
    within the noise, a drop in chi^2 is (dof + 1) / dof / scale^2 of deviance."""
    return noise.scale**2 * noise.dof / (noise.dof + 1) * unit


def _taken(chosen: Sequence[Claim]) -> list[int]:
    """The model's modes the changes `chosen` move or scale."""
    return [c.effect.target[0] for c in chosen
            if c.effect.family in ("mode_frequency", "mode_amplitude")]


def _visible(res: Residuals, model: PlantModel, taken: Sequence[int], unit: float) -> list[int]:
    """The model's modes, but `taken`, within :data:`SHIFT` of the coherent band whose
    response there adds at least :data:`VISIBLE` to the chi^2: one the data cannot see can be
    neither moved nor missing."""
    lo, hi = bounds.band(res.data)
    return [k for k, m in enumerate(model.modal.modes)
            if k not in taken and lo / SHIFT <= m.f_hz <= SHIFT * hi
            and res.power(model.closed_term(k)) >= VISIBLE * unit]


# ------------------------------------------------------------------------------ selection
def _select(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
            free: list[str], current: PlantFit, noise: Noise, unit: float, most: int,
            moves: Sequence[Claim], deadline: float
            ) -> tuple[PlantModel, list[Claim], list[Claim], dict[str, float], str]:
    """Forward selection from the modes `moves` moved (fitted in `current`): the model as the
    chosen changes leave it (its other loops' feedback), the chosen changes (best first),
    their rivals, the p-value of every member fitted at the first step, and why the choice
    stopped early (no step starts past `deadline`, :func:`time.monotonic`)."""
    chosen: list[Claim] = list(moves)
    rivals: list[Claim] = []
    first: dict[str, float] = {}
    for step in range(most):
        if time.monotonic() > deadline:
            return model, chosen, rivals, first, (
                f"the time budget ran out after {step} step(s) of choosing: further changes "
                "were not tried (twind diagnose --budget)")
        claims = _step(data, model, optic, plant, free, chosen, current, noise, unit,
                       deadline)
        if step == 0:
            first = {c.effect.key(): c.p_value for c in claims}
        claimed = sorted((c for c in claims if c.p_value < ALPHA), key=lambda c: -c.delta_bic)
        if not claimed:
            break
        best = claimed[0]
        best.equivalent = [c.effect.key() for c in claimed[1:] if best.lr - c.lr < EQUIVALENT_LR]
        chosen += [best, *best.revealed]
        rivals += [replace(c, rival_of=best.effect.key()) for c in claimed[1:]
                   if c.effect.key() in best.equivalent]
        model, current = _relooped(data, model, optic, plant, free, best.fit, noise)
        best.fit = current
    return model, chosen, rivals, first, ""


def _relooped(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
              free: list[str], fit: PlantFit, noise: Noise, new: Effect | None = None
              ) -> tuple[PlantModel, PlantFit]:
    """`model` with the other loops' feedback of the model as `fit` changes it
    (:func:`_looped`), and `fit` refitted with it."""
    looped = _looped(data, model, optic, plant, fit.effects)
    if looped is model:
        return model, fit
    return looped, fit_plant(data, looped, fit.nuisance, free, fit.effects, noise=noise,
                             new=new, limits=bounds.limits(looped, data, fit.effects))


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
          free: list[str], chosen: list[Claim], current: PlantFit, noise: Noise, unit: float,
          deadline: float = math.inf) -> list[Claim]:
    """Every family's likeliest members (:data:`STEP_FITS`, :data:`COUPLING_FITS`), each
    fitted with the changes `chosen` (the first always, the others while `deadline` has not
    passed); their p-values paid for the members and the families screened."""
    res = _residuals(data, model, free, current)
    screen_unit = _screen_unit(noise, unit)
    families = {name: members for name, members in _screen(res, model, chosen, current,
                                                            screen_unit).items() if members}
    ranked = sorted(((m, m.drop / _needed(len(members) * len(families), len(m.start)), f)
                     for f, members in families.items() for m in members),
                    key=lambda x: -x[1])
    claims: list[Claim] = []
    fitted = ranked[:STEP_FITS] + [x for x in ranked[STEP_FITS:] if x[2] == "drive_coupling"
                                   and x[1] >= HOPELESS][:COUPLING_FITS]
    for n, (m, margin, family) in enumerate(fitted):
        if margin < HOPELESS or (n and time.monotonic() > deadline):
            continue
        progress.note(f"step {len(chosen) + 1}: {m.effect.key()}")
        if family == "channel_response":
            m = replace(m, start=_stage_start(data, model, current, m.effect))
        claim = _try(data, model, optic, plant, free, chosen, m, current, noise, unit)
        if claim is None:
            continue
        if family == "drive_coupling":
            claim = _revealing(data, model, optic, plant, free, chosen, claim, current, noise,
                               unit)
        if family == "resonance":
            claim = _narrower(claim, res, model)
            moved = _as_moved(data, model, optic, plant, free, chosen, claim, current, noise,
                              unit, res)
            claim = claim if moved is None else moved  # paid for as the search found it
        claim.members = len(families[family])
        claim.p_value = min(1.0, claim.p_value * claim.members * len(families))
        for move in claim.revealed:  # chosen with it: its p-value is theirs
            move.p_value = claim.p_value
        claims.append(claim)
    return claims


def _revealing(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
               free: list[str], chosen: list[Claim], claim: Claim, current: PlantFit,
               noise: Noise, unit: float) -> Claim:
    """`claim` (a drive that also drives another input) with the modes that input shows
    moved where the data have them, as the modes of a drive are moved
    (:func:`_moves`): the share is screened with the model's modes in place, so where the
    other input's modes moved, its screen and its fit see little of it until they move
    too. Each move is kept only if it pays a claim's likelihood ratio and is not pinned;
    the claim then holds them all, its p-value paying for their searches. `claim` itself
    in a closed loop, or when none is kept."""
    if model.loops is not None:
        return claim
    found, tried = _revealed(data, model, free, chosen, claim, noise, unit)
    moves = [c.effect(model, data.resolution_hz) for c in found]
    _, fit, kept = _added(data, model, optic, plant, free, claim.fit, moves, noise,
                          _needed(tried, 3) * unit)
    if not kept:
        return claim
    k = fit.rank - current.rank
    lr = max(current.deviance - fit.deviance, 0.0) / unit
    paths = {e.key(): c.paths for (e, _), c in zip(moves, found, strict=True)}
    every = (*claim.paths, *(p for e, _, _ in kept for p in paths[e.key()]))
    p, per_bin = min(1.0, _p_value(lr, k, every)), math.log(max(2 * data.bins, 1))
    return replace(claim, fit=fit, lr=lr, k=k, p_value=p, delta_bic=lr - k * per_bin,
                   revealed=[
                       Claim(e, fit, drop / unit, 3, p, drop / unit - 3 * per_bin,
                             seen_in=seen, paths=paths[e.key()]) for e, drop, seen in kept])


def _revealed(data: FitData, model: PlantModel, free: list[str], chosen: list[Claim],
              claim: Claim, noise: Noise, unit: float) -> tuple[list[Candidate], int]:
    """Where the data show the modes a drive coupling `claim` reveals: those it shows more
    than the drive itself does (the others were tried as the drive's), each at the peaks
    of the elements it shows in through the coupling, the places given out
    (:func:`~twind.analysis.statespace.moves.assign`), each started at its peak; and how
    many modes were looked for."""
    view = model.seen_through(*claim.effect.target, claim.fit.own(claim.effect))
    res = _residuals(data, model, free, claim.fit)
    res.model = view  # the fit's residuals, screened with the modes as the coupling shows them
    taken = _taken(chosen)
    visible = _visible(res, view, taken, unit)
    shown = [k for k in visible if res.power(view.closed_term(k) - model.closed_term(k))
             >= res.power(model.closed_term(k))]
    screen_unit = _screen_unit(noise, unit)
    places = _places(res, shown, screen_unit, HOPELESS * _needed(max(len(shown), 1), 3),
                     visible)
    return ([c if c.peak_hz is None else replace(c, f_hz=c.peak_hz) for c in places],
            max(len(shown), 1))


def _places(res: Residuals, modes: Sequence[int], unit: float, least: float,
            holding: Sequence[int] | None = None) -> list[Candidate]:
    """Where the data show each of `modes` of ``res.model``: each tried at the peaks no other
    mode of `holding` (`modes` when None) holds where the model has it, its drop at least
    `least` (in `unit`), the places given out
    (:func:`~twind.analysis.statespace.moves.assign`)."""
    data = res.data
    peaks = measured_peaks(data)
    held = holders(res, res.model, modes if holding is None else holding, peaks)
    found = []
    for k in modes:
        progress.tick()
        found += candidates(res, res.model, k, unheld(peaks, held, k, data.resolution_hz),
                            unit, least)
    return assign(found, data.resolution_hz)


MOVE_TRIES = 2
"""The model modes, nearest first, a mode in no model is tried as instead."""


def _as_moved(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
              free: list[str], chosen: list[Claim], claim: Claim, current: PlantFit,
              noise: Noise, unit: float, res: Residuals) -> Claim | None:
    """`claim` (a mode in no model) read as one of the model's modes moved there, when a
    visible mode the data no longer show where the model has it
    (:func:`~twind.analysis.statespace.moves.unshown`) explains the data within
    :data:`EQUIVALENT_LR` of it: the model's own shape is the likelier reading, and fewer
    parameters. None when none does."""
    own = claim.fit.own(claim.effect)
    taken = _taken(chosen)
    visible = _visible(res, model, taken, unit)
    f, q = own["f_hz"], max(own["q"], bounds.MODE_Q[0])
    for k in unshown(res, model, visible, measured_peaks(data), f)[:MOVE_TRIES]:
        effect, start = Candidate(k, f, q, 1.0, 0.0, claim.paths).effect(
            model, data.resolution_hz)
        member = _Member(effect, 0.0, start, claim.paths)
        moved = _try(data, model, optic, plant, free, chosen, member, current, noise, unit)
        if moved is not None and moved.lr >= claim.lr - EQUIVALENT_LR:
            return moved
    return None


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
    data = res.data
    taken = _taken(chosen)
    peaks = measured_peaks(data)
    visible = _visible(res, model, taken, unit)
    held = holders(res, model, visible, peaks)
    out: dict[str, list[_Member]] = {"mode_frequency": [], "mode_amplitude": []}
    for k in visible:
        progress.tick()
        found = candidates(res, model, k, unheld(peaks, held, k, data.resolution_hz), unit,
                           0.0)
        if found:
            best = max(found, key=lambda c: c.drop)
            effect, start = best.effect(model, data.resolution_hz)
            out["mode_frequency"].append(_Member(effect, best.drop, start, best.paths))
        drop, coef = res.linear(res.G * model.closed_term(k))
        out["mode_amplitude"].append(_Member(Effect("mode_amplitude", (k,)), drop / unit,
                                             {"amplitude": 1.0 + coef}))
    repeat = sum(c.effect.family == "resonance" for c in chosen)
    trials, scale = _resonance_places(data, peaks, bounds.moved_to(model, base.effects))
    nr, nd = res.z.shape[1:]
    out["resonance"] = []
    if trials.size:
        sweep = res.resonance(unit, trials)
        start = {"f_hz": sweep.f_hz, "q": sweep.q,
                 **{f"b{i}": float(b) for i, b in enumerate(sweep.coefficients)}}
        out["resonance"].append(_Member(Effect("resonance", (repeat,)), sweep.drop, start,
                                        tuple(p * scale for p in sweep.paths)))
    for family, members in screen_couplings(res, model, base, unit).items():
        out[family] = [_Member(e, drop, start) for e, drop, start in members]
    out["channel_response"] = []
    for r in (i for i in range(nr) if f"g_{i}" in base.names):
        column = np.zeros_like(res.z)
        column[:, r] = (1j * res.data.frequency_hz[:, None] * res.predicted[:, r]
                        * res.whitener[:, r])
        drop, _ = res.linear(column)
        out["channel_response"].append(_Member(Effect("channel_response", (r,)), drop / unit,
                                               {"inv_pole_hz": 0.0, "inv_zero_hz": 0.0}))
    return out


def _unpinned(data: FitData, model: PlantModel, optic: StateSpaceOptic, plant: PlantSet,
              free: list[str], fit: PlantFit, noise: Noise, bare: PlantFit
              ) -> tuple[PlantModel, PlantFit, set[str]]:
    """`fit` refitted without the changes it leaves pinned
    (:func:`~twind.analysis.statespace.bounds.pinned`), until none is
    (`bare`, the fit without any change, when none is left): the model as they leave it, the
    fit, and the keys of those dropped. Fitted with all the others, their places proved
    other modes'."""
    dropped: set[str] = set()
    while pinned := {e.key() for e, _ in fit.effects if bounds.pinned(fit, e, model)}:
        dropped |= pinned
        rest = [(e, v) for e, v in fit.effects if e.key() not in pinned]
        model = _looped(data, model, optic, plant, rest)
        fit = fit_plant(data, model, fit.nuisance, free, rest, noise=noise,
                        limits=bounds.limits(model, data, rest)) if rest else bare
    return model, fit, dropped


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
        within = bounds.limits(model, data, effects)
        fit = fit_plant(data, looped, current.nuisance, free, effects, noise=noise,
                        new=member.effect, limits=within)
        if looped is not model:
            _, fit = _relooped(data, model, optic, plant, free, fit, noise, member.effect)
    except FitError:
        return None
    if bounds.pinned(fit, member.effect, model, within):
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
           free: list[str], chosen: list[Claim], noise: Noise, unit: float,
           floor: PlantFit | None = None, tried: int = 1) -> tuple[PlantModel, PlantFit]:
    """Each chosen change's likelihood ratio and p-value given the others (times `tried`,
    the members its search chose among); the most redundant leaves while its p-value is at
    least :data:`ALPHA`. With `floor` (the fit without any of them) the last may leave too.
    Returns the final model (its other loops' feedback made with the changes that stay) and
    fit."""
    final = chosen[-1].fit
    while len(chosen) > (0 if floor is not None else 1):
        without = {}
        for c in chosen:
            if _sure(c, final, tried):
                continue
            rest = [(e, v) for e, v in final.effects if e.key() != c.effect.key()]
            looped = _looped(data, model, optic, plant, rest)
            try:
                fit = floor if floor is not None and not rest else fit_plant(
                    data, looped, final.nuisance, free, rest, noise=noise,
                    limits=bounds.limits(looped, data, rest))
            except FitError:
                c.p_given_others = None
                continue
            without[c.effect.key()] = looped, fit
            k = c.k = max(final.rank - fit.rank, 1)  # a drop in deviance takes a direction
            c.lr = max(fit.deviance - final.deviance, 0.0) / unit
            c.p_given_others = min(1.0, tried * _p_value(c.lr, k, c.paths))
        worst = max(chosen, key=lambda c: c.p_given_others or 0.0)
        if (worst.p_given_others or 0.0) < ALPHA or worst.effect.key() not in without:
            break
        chosen.remove(worst)
        model, final = without[worst.effect.key()]
    return model, final


WALD_SURE = 4.0
"""A change whose Wald statistic in the final fit is this many times what a claim needs is
kept without refitting the model without it (its likelihood ratio taken as the Wald
statistic): the refit only confirms what the covariance already says."""


def _sure(claim: Claim, fit: PlantFit, tried: int) -> bool:
    """Whether `claim` is beyond doubt in `fit` by its Wald statistic (:data:`WALD_SURE`);
    if so, its likelihood ratio, directions and p-value given the others are set from it."""
    w = fit.wald(claim.effect)
    k = len(fit.own(claim.effect))
    if w is None or w < WALD_SURE * _needed(max(tried, 1), k):
        return False
    claim.lr, claim.k = w, k
    claim.p_given_others = min(1.0, tried * _p_value(w, k, claim.paths))
    return True
