"""Rates of ``twind diagnose`` over many twin cases: false alarms on nulls, detections at
the corpus' concealment, and whether its p-values are as small as chance allows.

What ``diagnose`` promises on a null is a rate: it claims an effect with probability at
most :data:`~twind.analysis.diagnosis.ALPHA` and locates a band with probability at most
:data:`~twind.analysis.identification.locate.ALPHA`, and every p-value it prints is no
smaller than uniform. One case cannot show a rate. :func:`outcomes` diagnoses corpus cases
(:func:`~twind.lab.corpus.make_cases`: drifted nulls, concealed effects) side by side in
processes, each measured by the twin's engine; :func:`rate_bound` says how many of a set
may claim before a promised rate is wrong, :func:`p_values_too_small` whether their
p-values are smaller than uniform. :func:`at_settings` measures the same nulls at each of
:data:`SETTINGS` and :func:`settings_report` tabulates them with bounds from the counts
(:func:`upper_bound`) and the catalogue's calibration (:func:`calibration`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from scipy import stats

from twind import progress
from twind.analysis.diagnose import diagnose
from twind.analysis.diagnosis import ALPHA
from twind.commissioning.measurement import measure_tfs
from twind.config import OpticConfig
from twind.commissioning.concealed import EXCITED, reference_data
from twind.lab.corpus import Case, make_cases, score
from twind.lab.workers import side_by_side
from twind.model.effects import CATALOGUE

PROMISED = 0.01
"""The rate docs/diagnose.md promises for a claim, and for a located band, on a null."""
NULLS = {"bw": 0.1, "averages": 10, "rms": 3.0}
"""The nulls' measurement: the corpus' at twice its MCAP route's bin width (half the bins,
the same statistics at half the cost)."""
CONCEALED = {"bw": 0.05, "averages": 10, "rms": 3.0}
"""The concealed effects' measurement: the corpus' MCAP route."""
SETTINGS = {"0.01 Hz": {"bw": 0.01}, "0.02 Hz": {"bw": 0.02}, "0.05 Hz": {},
            "0.1 Hz": {"bw": 0.1}, "5 averages": {"averages": 5},
            "20 averages": {"averages": 20}, "half the excitation": {"rms": 1.5},
            "LPM": {"estimator": "lpm"}}
"""The settings the rates are measured at, each a change of :data:`CONCEALED` alone."""
NEAR_LIMIT = ("osem_imbalance", "wire_asymmetry")
"""Effects at the corpus' concealment checked by default: the corpus' hardest key, and one
parameter that delta BIC favours over an imbalance's two."""


@dataclass(frozen=True)
class Outcome:
    """What the diagnosis of one case found.

    Attributes
    ----------
    name : str
        The case's (``null #3``, ``osem_imbalance #2``).
    effect : str or None
        The effect hidden in it (None for a null).
    named : bool
        The hidden effect chosen or declared equivalent to the chosen (a null: nothing
        claimed), as the corpus scores it.
    chosen : tuple of str
        The effects chosen, best first.
    best_claimed : str or None
        Of the effects claimed at the first step, the one of highest delta BIC.
    located : int
        Bands located as misfit of the nominal model.
    p_values : dict of str to float
        Every hypothesis of the first step and its p-value.
    not_fitted : tuple of str
        Hypotheses of the first step that gave no fit to weigh.
    controller : tuple of str
        DOFs whose measured controller was called different from the configuration's.
    lr : dict of str to (float, int)
        Each first-step hypothesis's likelihood ratio (in the nulls' units) and the
        directions it adds.
    tried : int
        Hypotheses of the first step (the Bonferroni factor).
    """

    name: str
    effect: str | None
    named: bool
    chosen: tuple[str, ...]
    best_claimed: str | None
    located: int
    p_values: dict[str, float]
    not_fitted: tuple[str, ...]
    controller: tuple[str, ...] = ()
    lr: dict[str, tuple[float, int]] = field(default_factory=dict)
    tried: int = 1

    @property
    def p_min(self) -> float:
        """The smallest p-value of the first step: on a null no smaller than uniform, as
        each is corrected for the hypotheses tried."""
        return min(self.p_values.values(), default=1.0)


def outcome(cfg: OpticConfig, measurement: dict, job: tuple[Case, int]) -> Outcome:
    """Measure one case on the twin's engine and diagnose it against the nominal `cfg`.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    measurement : dict
        Keywords of :func:`~twind.commissioning.measurement.measure_tfs` (POS, PIT and YAW excited in
        turn).
    job : (Case, int)
        The case and the seed of its measurement.

    Returns
    -------
    Outcome
    """
    case, seed = job
    d = diagnose(measure_tfs(case.real, EXCITED, seed=seed, plant=case.plant, **measurement),
                 cfg)
    claimed = [e for e in d.first_step if e.p_value < ALPHA]
    best = max(claimed, key=lambda e: e.delta_bic).effect if claimed else None
    return Outcome(case.name, case.effect, score(case, d, 0.0).named,
                   tuple(e.effect for e in d.chosen), best, len(d.located), dict(d.p_values),
                   tuple(x.effect for x in d.not_fitted if x.step == 1),
                   tuple(dict.fromkeys(x.dof for x in d.controller.differences)),
                   {e.effect: (e.lr, e.k) for e in d.first_step
                    if e.effect in CATALOGUE and not e.searched}, d.hypotheses)


def outcomes(cfg: OpticConfig, cases: Sequence[Case], seed: int, workers: int = 2,
             **measurement: float | int | str) -> list[Outcome]:
    """:func:`outcome` of each of `cases`, `workers` processes side by side.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    cases : sequence of Case
        What the twin measures.
    seed : int
        Case ``k`` is measured with seed ``seed + k``.
    workers : int
        Processes (the outcomes do not depend on it).
    **measurement
        Of :func:`~twind.commissioning.measurement.measure_tfs` (``bw``, ``averages``, ``rms``,
        ``estimator``): default :data:`CONCEALED`'s.

    Returns
    -------
    list of Outcome
        In the order of `cases`.
    """
    one = partial(outcome, cfg, {**CONCEALED, **measurement})
    jobs = [(case, seed + k) for k, case in enumerate(cases)]
    out: list[Outcome] = []
    with side_by_side(workers) as pmap:
        for o in pmap(one, jobs):
            out.append(o)
            progress.note(f"case {len(out)}/{len(jobs)}, named so far "
                          f"{sum(x.named for x in out)}")
    return out


def rate_bound(n: int, alpha: float, tail: float = 1e-3) -> int:
    """The most of `n` independent cases that may claim when each does with probability
    `alpha` at most: more happen by chance less often than `tail`.

    Parameters
    ----------
    n : int
        Cases (nulls).
    alpha : float
        The promised rate.
    tail : float
        The chance of exceeding the bound at exactly that rate.

    Returns
    -------
    int

    Examples
    --------
    >>> rate_bound(20, 0.01)
    3
    """
    return int(stats.binom.isf(tail, n, alpha))


def p_values_too_small(p: Sequence[float]) -> float:
    """The p-value of the one-sided Kolmogorov-Smirnov test that `p` are smaller than
    uniform: small when a diagnosis states more confidence than its nulls allow.

    Parameters
    ----------
    p : sequence of float
        p-values, one per null.

    Returns
    -------
    float
    """
    return float(stats.kstest(np.asarray(p), "uniform", alternative="greater").pvalue)


def nulls(cfg: OpticConfig, n: int, seed: int = 500, workers: int = 2,
          **measurement: float | int | str) -> list[Outcome]:
    """`n` drifted optics with no effect (the corpus' nulls), measured with :data:`NULLS`
    and `measurement`'s changes to it.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    n : int
        Nulls.
    seed : int
        Seed of the drifts (the measurements use ``seed + 100 + k``).
    workers : int
        Processes side by side.
    **measurement
        Keywords of :func:`~twind.commissioning.measurement.measure_tfs` that differ from
        :data:`NULLS` (``estimator="lpm"``: the local polynomial method's nulls).

    Returns
    -------
    list of Outcome
    """
    cases = make_cases(cfg, None, per_effect=0, nulls=n, seed=seed)
    return outcomes(cfg, cases, seed + 100, workers, **{**NULLS, **measurement})


def concealed(cfg: OpticConfig, per_effect: int, effects: Sequence[str] = NEAR_LIMIT,
              seed: int = 700, workers: int = 2) -> list[Outcome]:
    """`per_effect` cases of each of `effects` at the corpus' concealment (each one's
    largest change of a bin 3 standard errors), measured with :data:`CONCEALED`.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    per_effect : int
        Cases of each effect.
    effects : sequence of str
        Kinds hidden (:func:`~twind.lab.corpus.make_cases`).
    seed : int
        Seed of the drifts, directions and reference (the measurements use
        ``seed + 100 + k``).
    workers : int
        Processes side by side.

    Returns
    -------
    list of Outcome
    """
    reference = reference_data(cfg, seed, route="mcap", **CONCEALED)
    cases = make_cases(cfg, reference, per_effect, 0, seed, effects)
    return outcomes(cfg, cases, seed + 100, workers, **CONCEALED)


def report(null_set: Sequence[Outcome], effect_set: Sequence[Outcome]) -> list[str]:
    """A line per case, then the rates against what is promised.

    Parameters
    ----------
    null_set : sequence of Outcome
        From :func:`nulls`.
    effect_set : sequence of Outcome
        From :func:`concealed`.

    Returns
    -------
    list of str
    """
    out = [f"{o.name:20s} {'named' if o.named else 'MISS '}  chosen {', '.join(o.chosen) or '-'}"
           f"  (highest delta BIC claimed: {o.best_claimed or '-'})  located {o.located}  "
           f"smallest p {o.p_min:.2g}" for o in [*null_set, *effect_set]]
    if null_set:
        n = len(null_set)
        out += [f"nulls with an effect claimed: {sum(bool(o.chosen) for o in null_set)}/{n} "
                f"(at most {rate_bound(n, PROMISED)} at the promised {PROMISED})",
                f"nulls with a band located: {sum(o.located > 0 for o in null_set)}/{n} "
                f"(at most {rate_bound(n, PROMISED)})",
                f"nulls with a controller called different: "
                f"{sum(bool(o.controller) for o in null_set)}/{n} "
                f"(at most {rate_bound(n, PROMISED)})",
                f"nulls' smallest p-values: {sum(o.p_min >= 1 for o in null_set)}/{n} at 1; "
                f"KS p that they are smaller than uniform "
                f"{p_values_too_small([o.p_min for o in null_set]):.2g} (fails below 1e-3)"]
    if effect_set:
        out.append(f"effects at the corpus' concealment named (or equivalent): "
                   f"{sum(o.named for o in effect_set)}/{len(effect_set)}")
    ranked = [o for o in [*null_set, *effect_set]
              if (o.chosen[0] if o.chosen else None) != o.best_claimed]
    out.append("first choice the claimed effect of highest delta BIC: "
               + ("every case" if not ranked else f"not in {', '.join(o.name for o in ranked)}"))
    return out


def at_settings(cfg: OpticConfig, n: int, names: Sequence[str] = tuple(SETTINGS),
                seed: int = 500, workers: int = 2) -> dict[str, list[Outcome]]:
    """The same `n` drifted nulls measured and diagnosed at each of `names`' settings.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    n : int
        Nulls per setting.
    names : sequence of str
        Keys of :data:`SETTINGS`.
    seed : int
        Seed of the drifts (the measurements use ``seed + 100 + k`` at every setting).
    workers : int
        Processes side by side.

    Returns
    -------
    dict of str to list of Outcome
    """
    cases = make_cases(cfg, None, per_effect=0, nulls=n, seed=seed)
    out = {}
    for name in names:
        progress.note(f"setting {name}")
        out[name] = outcomes(cfg, cases, seed + 100, workers, **{**CONCEALED, **SETTINGS[name]})
    return out


def upper_bound(k: int, n: int, level: float = 0.95) -> float:
    """One-sided Clopper-Pearson upper bound on a rate seen `k` times in `n`.

    Examples
    --------
    >>> round(upper_bound(0, 299), 4)
    0.01
    """
    return float(stats.beta.ppf(level, k + 1, n - k)) if k < n else 1.0


def calibration(null_set: Sequence[Outcome]) -> dict[str, float]:
    """Each catalogue hypothesis's mean likelihood ratio per direction on `null_set`: 1 when
    its chi^2 reference is exact, below 1 when it asks for more evidence than it needs."""
    ratios: dict[str, list[float]] = {}
    for o in null_set:
        for e, (lr, k) in o.lr.items():
            ratios.setdefault(e, []).append(lr / k)
    return {e: float(np.mean(r)) for e, r in ratios.items()}


def raw_p_values(null_set: Sequence[Outcome]) -> list[float]:
    """The catalogue hypotheses' p-values before the Bonferroni factor, pooled: uniform
    when their reference distribution is exact."""
    return [float(stats.chi2.sf(lr, k)) for o in null_set for lr, k in o.lr.values()]


def claimed_calibrated(o: Outcome, scale: dict[str, float]) -> bool:
    """Whether the hidden effect of `o` would be claimed at the first step with each
    catalogue hypothesis's likelihood ratio divided by its nulls' mean per direction."""
    lr, k = o.lr.get(o.effect or "", (0.0, 1))
    s = scale.get(o.effect or "", 1.0)
    return min(1.0, float(stats.chi2.sf(lr / s, k)) * o.tried) < ALPHA


def settings_report(by_setting: dict[str, list[Outcome]],
                    effect_set: Sequence[Outcome] = ()) -> list[str]:
    """A line per setting: nulls claimed and located with their 95 % bounds, how far the
    p-values are from uniform and the hypotheses' calibration; then the finds at the
    corpus' concealment as the p-values stand and calibrated on the nulls of the base
    setting.

    Parameters
    ----------
    by_setting : dict of str to list of Outcome
        From :func:`at_settings`.
    effect_set : sequence of Outcome
        From :func:`concealed` (measured at the base setting, :data:`CONCEALED`).

    Returns
    -------
    list of str
    """
    out = [f"{'setting':20s} {'claimed':>8s} {'95% bound':>9s} {'located':>8s} "
           f"{'95% bound':>9s} {'p_min 1':>7s} {'raw p mean':>10s} {'KS D':>5s} "
           f"{'LR/k':>5s} {'ctrl':>5s}"]
    for name, nulls_ in by_setting.items():
        n = len(nulls_)
        claimed = sum(bool(o.chosen) for o in nulls_)
        located = sum(o.located > 0 for o in nulls_)
        raw = raw_p_values(nulls_)
        ks = stats.kstest(raw, "uniform").statistic if raw else math.nan
        lr_k = [lr / k for o in nulls_ for lr, k in o.lr.values()]
        out.append(f"{name:20s} {f'{claimed}/{n}':>8s} {upper_bound(claimed, n):9.1%} "
                   f"{f'{located}/{n}':>8s} {upper_bound(located, n):9.1%} "
                   f"{sum(o.p_min >= 1 for o in nulls_):7d} {np.mean(raw):10.2f} {ks:5.2f} "
                   f"{np.mean(lr_k):5.2f} {sum(bool(o.controller) for o in nulls_):5d}"
                   + "".join(f"  {o.name}: {', '.join(o.chosen)} (p {o.p_min:.2g})"
                             for o in nulls_ if o.chosen))
    n_max = max((len(v) for v in by_setting.values()), default=0)
    out.append(f"(promised: claimed and located at most {PROMISED:.0%} each; "
               f"a 95 % bound of {PROMISED:.0%} needs {_needed(PROMISED)} nulls with none, "
               f"here {n_max}; raw p mean 0.50 and LR/k 1.00 when the references are exact)")
    base = by_setting.get("0.05 Hz")
    if base:
        scale = calibration(base)
        out.append("catalogue hypotheses' LR/k on the 0.05 Hz nulls: "
                   + ", ".join(f"{e} {v:.2f}" for e, v in sorted(scale.items())))
        if effect_set:
            now = sum(o.p_values.get(o.effect or "", 1.0) < ALPHA for o in effect_set)
            cal = sum(claimed_calibrated(o, scale) for o in effect_set)
            out.append(f"hidden effects at the corpus' concealment claimed at the first step: "
                       f"{now}/{len(effect_set)} as the p-values stand, {cal}/{len(effect_set)}"
                       f" with each hypothesis's LR scaled by its nulls' LR/k")
    return out


def _needed(rate: float, level: float = 0.95) -> int:
    """Nulls with no claim a one-sided bound of `rate` at `level` needs."""
    return math.ceil(math.log(1 - level) / math.log(1 - rate))
