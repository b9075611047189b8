"""The rates bench's arithmetic (``twind.lab.rates``): bounds from counts and the
calibration of the hypotheses' references, on likelihood ratios drawn from known laws."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from twind.lab.rates import (
    Outcome,
    calibration,
    claimed_calibrated,
    raw_p_values,
    upper_bound,
)


def outcomes(scale: float, n: int = 400, seed: int = 0) -> list[Outcome]:
    """Nulls whose two hypotheses' likelihood ratios are `scale` times chi^2 draws."""
    rng = np.random.default_rng(seed)
    return [Outcome(f"null #{i}", None, True, (), None, 0, {}, (),
                    lr={"wire_asymmetry": (scale * rng.chisquare(1), 1),
                        "coil_imbalance": (scale * rng.chisquare(2), 2)}, tried=10)
            for i in range(n)]


def test_exact_references_read_as_exact() -> None:
    nulls = outcomes(1.0)
    assert all(v == pytest.approx(1.0, abs=0.15) for v in calibration(nulls).values())
    assert stats.kstest(raw_p_values(nulls), "uniform").pvalue > 1e-3


def test_a_conservative_reference_is_measured_and_its_claims_recovered() -> None:
    nulls = outcomes(0.3)
    scale = calibration(nulls)
    assert all(v == pytest.approx(0.3, abs=0.06) for v in scale.values())
    assert np.mean(raw_p_values(nulls)) > 0.6  # p-values pushed towards 1
    # an effect whose LR (in the conservative units) is 3.5: p 0.6 as it stands, well
    # below 1 % once the units are the nulls'
    hidden = Outcome("wire_asymmetry #0", "wire_asymmetry", False, (), None, 0,
                     {"wire_asymmetry": 0.6}, (), lr={"wire_asymmetry": (3.5, 1)}, tried=10)
    assert not claimed_calibrated(hidden, {})
    assert claimed_calibrated(hidden, scale)


@pytest.mark.parametrize(("k", "n", "bound"), [(0, 299, 0.01), (0, 20, 0.139), (1, 80, 0.058)])
def test_upper_bounds_are_clopper_pearson(k: int, n: int, bound: float) -> None:
    assert upper_bound(k, n) == pytest.approx(bound, abs=0.001)
    # the bound's meaning: at that rate, k or fewer happen 5 % of the time
    assert stats.binom.cdf(k, n, upper_bound(k, n)) == pytest.approx(0.05, rel=1e-6)
