"""Checks every diagnosis in the tests must pass, whatever it found."""

from __future__ import annotations

from twind.analysis.diagnosis import ALPHA, Diagnosis
from twind.model.effects import CATALOGUE, FAMILIES


def assert_accounted(p_values: dict, not_fitted: list[dict]) -> None:
    """Every hypothesis of the first step has a p-value or a reason it has none: each
    catalogue entry, and each family through at least one of its members."""
    failed = {x["effect"]: x["reason"] for x in not_fitted if x["step"] == 1}
    weighed = set(p_values) | set(failed)
    assert set(CATALOGUE) <= weighed
    for members in FAMILIES.values():
        assert weighed & set(members)
    assert all(0 <= p <= 1 for p in p_values.values())
    assert all(reason for reason in failed.values())


def assert_ranked_on_delta_bic(d: Diagnosis) -> None:
    """The first effect chosen is the one of highest delta BIC among those claimed at the
    first step (unless the final model dropped it), its rivals listed beside it."""
    claimed = [e for e in d.first_step if e.p_value < ALPHA]
    if not claimed:
        assert not d.effects
        return
    best = max(claimed, key=lambda e: e.delta_bic)
    if any(e.effect == best.effect for e in d.effects):
        assert d.chosen[0].effect == best.effect, (best.effect, [e.effect for e in d.effects])


def assert_sound(d: Diagnosis) -> None:
    """:func:`assert_accounted` and :func:`assert_ranked_on_delta_bic`."""
    assert_accounted(d.p_values, [x.to_json() for x in d.not_fitted])
    assert_ranked_on_delta_bic(d)
