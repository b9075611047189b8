"""Narrow modes (bounce and roll, Q 1000): a Hann-windowed bin sees a mode's area under the
window's power kernel, and the search that starts a bounce_roll fit finds where it lies."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twind import DOFS
from twind.analysis.identification.data import FitData
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.narrow import Scan, _columns, p_value, search
from twind.config import load_config
from twind.model.effects import MODE_SEARCH, with_effect
from twind.model.plant import Plant

RES = 0.05
ROLL = {"roll": 0.01, "f_roll_hz": 22.713, "roll_angle": 1.1}


@pytest.fixture(scope="module")
def etmx():  # noqa: ANN201
    return load_config(None, ["ETMX"]).optics["ETMX"]


def _hann_power(offsets_bins: np.ndarray, n: int = 256) -> np.ndarray:
    """|DFT of a Hann window|^2 at fractional-bin offsets, from the window itself."""
    t = np.arange(n)
    w = np.hanning(n + 1)[:-1]
    return np.abs(np.exp(-2j * np.pi * np.outer(offsets_bins, t) / n) @ w) ** 2


def test_a_bin_sees_a_narrow_mode_averaged_over_the_hann_kernel(etmx) -> None:  # noqa: ANN001
    """ClosedLoopModel's bins next to a mode narrower than a bin equal the exact closed
    loop averaged over the Hann window's own power spectrum, sampled 1/128 bin apart; the
    two-point rule alone is far off there."""
    plant = with_effect(Plant.from_params(etmx.sus, etmx.mechanics()), etmx.sus,
                        "bounce_roll", ROLL)
    f = np.round(ROLL["f_roll_hz"] / RES) * RES + RES * np.arange(-4, 5)
    model = ClosedLoopModel(etmx, f, RES).response(plant)
    d = np.linspace(-3, 3, 6 * 128 + 1)
    w = _hann_power(d)
    exact = ClosedLoopModel(etmx, (f[:, None] + RES * d).ravel()).response(plant)
    brute = np.einsum("k,fkij->fij", w / w.sum(), exact.reshape(f.size, d.size, 4, 4))
    yaw = DOFS.index("YAW")
    scale = np.abs(brute[:, yaw, yaw]).max()
    np.testing.assert_allclose(model[:, yaw, yaw], brute[:, yaw, yaw], atol=2e-3 * scale)
    two_point = 0.5 * sum(ClosedLoopModel(etmx, f + s * RES / math.sqrt(3)).response(plant)
                          for s in (-1, 1))
    assert np.abs(two_point[:, yaw, yaw] - brute[:, yaw, yaw]).max() > 0.05 * scale


@pytest.mark.parametrize("res", [0.05, 0.1, 0.25])
def test_bins_near_the_damped_modes_see_them_through_the_hann_kernel(etmx, res: float  # noqa: ANN001
                                                                      ) -> None:
    """The closed loop's damped modes (Q about 5) are narrower than the two-point rule
    allows as the resolution coarsens: every element of ClosedLoopModel's bins up to 8 Hz
    equals the closed loop averaged over the Hann window's own power spectrum (1/32 bin
    apart) to 1 % of that element's largest value, where the two-point rule alone is off by
    5 % at 0.05 Hz, 40 % at 0.1 Hz and more than the element itself at 0.25 Hz."""
    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    f = np.arange(1, round(8 / res)) * res
    model = ClosedLoopModel(etmx, f, res).response(plant)
    d = np.linspace(-3, 3, 6 * 32 + 1)
    w = _hann_power(d)
    exact = ClosedLoopModel(etmx, (f[:, None] + res * d).ravel()).response(plant)
    brute = np.einsum("k,fkij->fij", w / w.sum(), exact.reshape(f.size, d.size, 4, 4))
    scale = np.abs(brute).max(axis=0)
    two_point = 0.5 * sum(ClosedLoopModel(etmx, f + s * res / math.sqrt(3)).response(plant)
                          for s in (-1, 1))
    assert (np.abs(model - brute) / scale).max() < 0.01
    assert (np.abs(two_point - brute) / scale).max() > {0.05: 0.05, 0.1: 0.4, 0.25: 1}[res]


def test_the_search_finds_a_mode_seen_at_its_peak(etmx) -> None:  # noqa: ANN001
    """A roll mode plain at its peak (a measurement accurate to 1 % everywhere) is found
    within a quarter of a bin, with its coupling and pattern; the bounce, absent, starts
    at most a few percent of that coupling (what it picks up is the two-point rule's error
    next to the BounceRoll notches, plain only with errors this small)."""
    f = np.arange(1, 601) * RES
    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    loop = ClosedLoopModel(etmx, f, RES)
    truth = loop.response(with_effect(plant, etmx.sus, "bounce_roll", ROLL))[:, :, :3]
    sigma = 0.01 * np.abs(loop.response(plant)[:, :, :3]) + 1e-12
    rng = np.random.default_rng(2)
    noise = sigma * (rng.standard_normal(sigma.shape) + 1j * rng.standard_normal(sigma.shape))
    data = FitData(f, list(DOFS), ["POS", "PIT", "YAW"], truth + noise, sigma,
                   np.ones(sigma.shape, dtype=bool), 10, RES)
    start, path = search(data, etmx, {})
    assert start["f_roll_hz"] == pytest.approx(ROLL["f_roll_hz"], abs=RES / 4)
    assert start["roll"] == pytest.approx(ROLL["roll"], rel=0.2)
    assert start["roll_angle"] == pytest.approx(ROLL["roll_angle"], abs=0.1)
    assert abs(start["vertical"]) < 0.02 * ROLL["roll"]
    assert path > 1.0  # a peak turns the signature as the trial frequency sweeps past it


@pytest.mark.parametrize(("dof", "param"), [("VERT", "f_vertical_hz"), ("ROLL", "f_roll_hz")])
def test_the_search_s_columns_are_the_model_s_own_change(etmx, dof, param) -> None:  # noqa: ANN001
    """Each trial's column, rebuilt from the search's short coordinates (the far bins in a
    few shapes), is what ClosedLoopModel's bins change by per unit coupling of a mode at
    that frequency, to 1e-4 of itself (2e-5 in an ad-hoc look, the central difference's
    rounding where a notch leaves IN1/EXC tiny), at the mode and far from it. The bins near
    the closed loop's damped modes, which the model averages over the Hann kernel, the
    search screens by the two-point rule: there to 3 % (1.5 % in an ad-hoc look)."""
    f = np.arange(1, 601) * RES
    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    loop = ClosedLoopModel(etmx, f, RES)
    sigma = 0.01 * np.abs(loop.response(plant)[:, :, :3]) + 1e-12
    mask = np.ones(sigma.shape, dtype=bool)
    mask[::7, 1] = False
    data = FitData(f, list(DOFS), ["POS", "PIT", "YAW"], np.zeros(sigma.shape, complex), sigma,
                   mask, 10, RES)
    _, lo, hi = MODE_SEARCH[param]
    nominal = etmx.sus.uncoupled_frequencies_hz()
    cols, grid, red = _columns(data, etmx, plant, etmx.sus, dof, [{"roll_angle": 0.3}],
                               (lo * nominal[dof], hi * nominal[dof]), np.zeros((2 * data.bins, 0)))
    model = ClosedLoopModel.of(etmx, data, "bounce_roll").for_data(data)
    coupling = "vertical" if dof == "VERT" else "roll"
    damped = np.tile(np.isin(np.nonzero(mask)[0], loop.damped.bins), 2)
    for g in (0, grid.size // 2 + 1, grid.size - 1):
        at = {"vertical": 0.0, "roll": 0.0, "roll_angle": 0.3, "f_vertical_hz": nominal["VERT"],
              "f_roll_hz": nominal["ROLL"], param: grid[g]}
        change = (data.whiten(model({**at, coupling: -1e-5}))
                  - data.whiten(model({**at, coupling: 1e-5}))) / 2e-5
        error = red.back(cols[g, 0]) - change
        for part, tol in ((~damped, 1e-4), (damped, 0.03)):
            assert np.linalg.norm(error[part]) < tol * np.linalg.norm(change[part])
    assert red.near.size + red.basis.shape[0] < 0.5 * red.size  # short


def test_the_search_is_charged_for_where_it_looked() -> None:
    """Davies' bound is the plain chi^2 tail for a search that never turns and grows
    with the path a search turns through."""
    assert p_value(9.0, 1, 0.0) == pytest.approx(0.0027, rel=0.01)
    assert p_value(9.0, 1, 0.0) < p_value(9.0, 1, 5.0) < p_value(9.0, 1, 50.0) <= 1.0
    assert p_value(30.0, 2, 50.0) < 1e-4


def test_with_no_physical_coupling_a_mode_starts_at_its_nominal_frequency() -> None:
    from twind.analysis.identification.narrow import _choice

    drop = np.array([5.0, 9.0, 7.0])
    x = np.full((3, 1), 2.0)  # every trial's coupling above 1: none is physical
    assert _choice(drop, x, at_nominal=2) == 2
    x[1] = 0.5
    assert _choice(drop, x, at_nominal=2) == 1  # the one physical trial


def test_a_scan_reports_every_range_of_frequencies_the_data_cannot_tell_apart() -> None:
    """Runs of trials within the margin of the best, each reaching the trials either side
    (the range ends somewhere between), merged across sweeps; a barred trial (``-inf``,
    no small attachment) breaks a run."""
    scan = Scan((np.arange(1.0, 9.0), np.array([7.5, 9.0, 9.5])),
                (np.array([0.0, 10.0, 9.5, 0.0, 0.0, -np.inf, 9.8, 0.0]),
                 np.array([9.9, 0.0, 0.0])))
    assert scan.plausible(1.0) == [(1.0, 4.0), (6.0, 9.0)]
    assert scan.plausible(0.0) == [(1.0, 3.0)]
    assert scan.plausible(100.0) == [(1.0, 9.5)]
