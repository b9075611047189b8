"""Rates of ``twind diagnose`` over many twin cases: false alarms on nulls, detections at
the corpus' concealment, and whether its p-values are as small as chance allows.

What ``diagnose`` promises on a null is a rate: it claims an effect with probability at
most :data:`~twind.analysis.diagnose.ALPHA` and locates a band with probability at most
:data:`~twind.analysis.identification.locate.ALPHA`, and every p-value it prints is no
smaller than uniform. One case cannot show a rate. :func:`outcomes` diagnoses corpus cases
(:func:`~twind.lab.corpus.make_cases`: drifted nulls, concealed effects) side by side in
processes, each measured by the twin's engine; :func:`rate_bound` says how many of a set
may claim before a promised rate is wrong, :func:`p_values_too_small` whether their
p-values are smaller than uniform.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
from scipy import stats

from twind import progress
from twind.analysis.diagnose import ALPHA, diagnose
from twind.config import OpticConfig
from twind.lab.corpus import EXCITED, Case, make_cases, reference_data, score
from twind.lab.measurement import measure_tfs
from twind.lab.workers import side_by_side


PROMISED = 0.01
"""The rate docs/diagnose.md promises for a claim, and for a located band, on a null."""
NULLS = {"bw": 0.1, "averages": 10, "rms": 3.0}
"""The nulls' measurement: the corpus' at twice its MCAP route's bin width (half the bins,
the same statistics at half the cost)."""
CONCEALED = {"bw": 0.05, "averages": 10, "rms": 3.0}
"""The concealed effects' measurement: the corpus' MCAP route."""
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
    """

    name: str
    effect: str | None
    named: bool
    chosen: tuple[str, ...]
    best_claimed: str | None
    located: int
    p_values: dict[str, float]
    not_fitted: tuple[str, ...]

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
        Keywords of :func:`~twind.lab.measurement.measure_tfs` (POS, PIT and YAW excited in
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
                   tuple(x.effect for x in d.not_fitted if x.step == 1))


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
        Of :func:`~twind.lab.measurement.measure_tfs` (``bw``, ``averages``, ``rms``,
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
        Keywords of :func:`~twind.lab.measurement.measure_tfs` that differ from
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
