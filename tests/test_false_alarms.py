"""Rates, not single cases (``twind.lab.rates``): what ``diagnose`` promises on data with no
effect is a claim with probability 0.01 at most and p-values no smaller than uniform, which
only many nulls can check; on an effect at the corpus' concealment, that it is found, which
a handful of seeds checks better than one effect at 1e-200; and that the effect chosen is
the claimed one of highest delta BIC. Every case is a drifted ETMX measured by the twin's
engine, diagnosed two at a time; the nulls are measured as Welch's estimates and as the local
polynomial method's."""

from __future__ import annotations

import pytest
from scipy import stats

from twind.config import NOMINAL_ETMX, load_optic
from twind.lab import rates
from twind.model.effects import CATALOGUE

pytestmark = pytest.mark.slow

PROMISED = 0.01
"""The rate docs/diagnose.md promises (the code's own constants would move with a bug)."""
N_NULLS = 16
PER_EFFECT = 8
FOUND = 0.75
"""The rate at which OSEM imbalances at the corpus' concealment are found: 24 of 32, the
cases of ``rates.concealed(etmx, 16, ("osem_imbalance",))`` with this engine's noise and with
the previous one's (by hand)."""


@pytest.fixture(scope="module")
def etmx():  # noqa: ANN201
    return load_optic(NOMINAL_ETMX)


@pytest.fixture(scope="module")
def welch_nulls(etmx):  # noqa: ANN001, ANN201
    return rates.nulls(etmx, N_NULLS)


@pytest.fixture(scope="module")
def lpm_nulls(etmx):  # noqa: ANN001, ANN201
    return rates.nulls(etmx, N_NULLS, estimator="lpm")


@pytest.fixture(scope="module", params=["welch_nulls", "lpm_nulls"])
def nulls(request):  # noqa: ANN001, ANN201
    """The same drifted optics, measured with each estimator."""
    return request.getfixturevalue(request.param)


@pytest.fixture(scope="module")
def concealed(etmx):  # noqa: ANN001, ANN201
    """OSEM imbalances, the corpus' hardest key, at its concealment. (Wire asymmetries
    concealed so are found less often, 1 of 5 in ``twind bench --suite rates``: a finding
    docs/limits.md keeps, not a rate this test can hold.)"""
    return rates.concealed(etmx, PER_EFFECT, ("osem_imbalance",))


def test_nulls_claim_effects_no_more_often_than_promised(nulls) -> None:  # noqa: ANN001
    claims = [(o.name, o.chosen) for o in nulls if o.chosen]
    assert len(claims) <= rates.rate_bound(N_NULLS, PROMISED), claims


def test_nulls_p_values_are_no_smaller_than_uniform(nulls) -> None:  # noqa: ANN001
    smallest = sorted(o.p_min for o in nulls)
    assert rates.p_values_too_small(smallest) > 1e-3, smallest


def test_nulls_locate_bands_no_more_often_than_promised(nulls) -> None:  # noqa: ANN001
    located = [(o.name, o.located) for o in nulls if o.located]
    assert len(located) <= rates.rate_bound(N_NULLS, PROMISED), located


def test_every_hypothesis_is_weighed_or_its_failure_reported(nulls, concealed  # noqa: ANN001
                                                              ) -> None:
    for o in [*nulls, *concealed]:
        assert set(CATALOGUE) <= set(o.p_values) | set(o.not_fitted), o.name


def test_effects_at_the_corpus_concealment_are_found(concealed) -> None:  # noqa: ANN001
    # fewer than this is found 1 % of the time at the rate FOUND (3 of 8: 0.4 %); a diagnosis
    # that found one in four would fail two times in three, one that found none always
    least = int(stats.binom.ppf(0.01, len(concealed), FOUND))
    assert sum(o.named for o in concealed) >= least, [(o.name, o.chosen) for o in concealed]


def test_the_effect_chosen_is_the_claimed_one_of_highest_delta_bic(nulls, concealed  # noqa: ANN001
                                                                   ) -> None:
    for o in [*nulls, *concealed]:
        assert (o.chosen[0] if o.chosen else None) == o.best_claimed, (o.name, o.chosen)


def test_the_report_states_the_rates(nulls, concealed) -> None:  # noqa: ANN001
    lines = rates.report(nulls, concealed)
    assert len(lines) == len(nulls) + len(concealed) + 6
    assert lines[-6].startswith(f"nulls with an effect claimed: "
                                f"{sum(bool(o.chosen) for o in nulls)}/{N_NULLS}")
    assert lines[-4].startswith(f"nulls with a controller called different: "
                                f"{sum(bool(o.controller) for o in nulls)}/{N_NULLS}")
