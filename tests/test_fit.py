"""twind fit: parameters with calibrated uncertainties, and what the data cannot determine."""

from __future__ import annotations

import glob
import io
import json
import math
import warnings
from contextlib import redirect_stdout
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import REFERENCE
from measurekit import record_excited_session

from twind.analysis.estimation.tf import from_diaggui, from_session
from twind.analysis.identification.data import FitData
from twind.analysis.identification.fit import fit
from twind.analysis.identification.params import (
    FIT_PARAMS,
    FitError,
    param_value,
    read_truth,
    with_params,
)
from twind.cli import main
from twind.config import NOMINAL_ETMX, load_config, load_optic

NULL = sorted(glob.glob(str(REFERENCE / "example_null" / "*.xml")))
DRIFT = {"wire_length_m": 0.2437963230477589, "b_m": 0.0007186926839598156,
         "R1_m": 0.006704947641614116, "coil_N_per_ct": 2.420818165429093e-09}


@pytest.fixture(scope="module")
def etmx():  # noqa: ANN201
    """The nominal ETMX the example set drifted from."""
    return load_optic(NOMINAL_ETMX)


@pytest.fixture(scope="module")
def null_fit(etmx):  # noqa: ANN001, ANN201
    return fit(from_diaggui(NULL), etmx)


def test_example_null_recovers_its_drift_within_3_sigma(null_fit) -> None:  # noqa: ANN001
    truth = read_truth(REFERENCE / "example_null" / "truth.json")
    got = null_fit.as_dict()
    sigma = dict(zip(null_fit.names, null_fit.sigma, strict=True))
    for name in ("wire_length_m", "b_m", "R1_m", "coil_N_per_ct"):
        assert abs(got[name] - truth[name]) < 3 * sigma[name], (name, got[name], sigma[name])
        # and the drift was worth measuring: nominal is far outside the errors
    assert abs(param_value(load_optic(NOMINAL_ETMX).sus, "wire_length_m")
               - got["wire_length_m"]) > 5 * sigma["wire_length_m"]
    assert "Q_SIDE" in null_fit.unidentifiable and math.isnan(sigma["Q_SIDE"])
    # errors from coherence, checked against the scatter: Hann bins are correlated
    assert 0.8 < null_fit.noise_scale < 1.5
    assert 0.3 < null_fit.bin_correlation[0] < 0.6


@pytest.mark.slow
def test_fit_json_has_the_issue_layout(tmp_path: Path) -> None:
    out = io.StringIO()
    with redirect_stdout(out):
        assert main(["fit", *NULL, "--json", "--band", "0.3", "3",
                     "-o", str(tmp_path / "fit.png")]) == 0
    obj = json.loads(out.getvalue())
    assert set(obj["params"]) == set(FIT_PARAMS)
    assert obj["params"]["Q_SIDE"]["sigma"] is None and "Q_SIDE" in obj["unidentifiable"]
    assert obj["params"]["b_m"]["sigma"] > 0 and obj["chi2_nu"] > 0
    assert (tmp_path / "fit.png").stat().st_size > 10_000


def test_singular_fisher_names_the_determined_combination(etmx) -> None:  # noqa: ANN001
    """PIT alone is driven by coil x lever and read independently of the lever: only their
    product is determined, the ratio is named unidentifiable, nothing raises."""
    pit = [p for p in NULL if p.endswith("PIT_exc.xml")]
    r = fit(from_diaggui(pit), etmx, ["coil_N_per_ct", "osem_lever_m", "Q_SIDE"])
    assert r.unidentifiable.count("coil_N_per_ct/osem_lever_m") == 1
    assert "Q_SIDE" in r.unidentifiable and np.all(np.isnan(r.sigma))
    (combo, d), = r.determined.items()
    assert combo == "coil_N_per_ct*osem_lever_m"
    truth = DRIFT["coil_N_per_ct"] * 0.019
    assert abs(d["value"] - truth) < 3 * d["sigma"] and d["sigma"] < 0.01 * truth


def test_determined_product_ignores_the_other_parameters_signs() -> None:
    """An effect's parameter may be negative (a gain deficit): the product a pair of
    log-scaled parameters determines is still their own, not NaN."""
    from twind.analysis.identification.result import name_null as _name_null

    null = np.array([[1.0], [-1.0], [0.0]])  # a/b unidentifiable
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no log of the negative gain
        unident, determined = _name_null(["a", "b", "gain"], null, np.array([2.0, 3.0, -0.5]),
                                          np.eye(3) * 1e-4, np.array([True, True, False]))
    assert unident == ["a/b"] and determined["a*b"]["value"] == pytest.approx(6.0)


def test_bad_requests_are_named(etmx) -> None:  # noqa: ANN001
    tfs = from_diaggui(NULL)
    with pytest.raises(FitError, match="unknown fit parameter"):
        fit(tfs, etmx, ["wire_length"])
    with pytest.raises(FitError, match="coherence"):
        fit(tfs, etmx, band=(40.0, 50.0))
    with pytest.raises(FitError, match="coherence"):
        fit(tfs, etmx, min_coherence=1.01)


def test_twin_recording_of_a_drifted_optic(tmp_path: Path, etmx) -> None:  # noqa: ANN001
    """MCAP route: the twin serves a drifted ETMX; the fit finds the drift within 3 sigma."""
    real = replace(etmx, sus=with_params(etmx.sus, {**DRIFT, "osem_lever_m": 0.0195}))
    path = record_excited_session(real, tmp_path / "drifted.mcap",
                                  {"POS": 2.0, "PIT": 5.0, "YAW": 5.0}, seconds=55)
    r = fit(from_session([path], bw=0.1), etmx)
    got, sigma = r.as_dict(), dict(zip(r.names, r.sigma, strict=True))
    for name in (*DRIFT, "osem_lever_m"):
        truth = param_value(real.sus, name)
        assert abs(got[name] - truth) < 3 * sigma[name], (name, got[name], truth, sigma[name])
    assert r.chi2_nu < 2.0


def test_a_left_out_coil_imbalance_is_fitted_and_worth_its_parameters(etmx) -> None:  # noqa: ANN001
    """The twin runs a plant whose face coils differ by a few % (its actuation matrix scaled
    here, not through the effects module); nominal + coil_imbalance explains it, the nominal
    model alone does not."""
    from twind.model.plant import Plant
    from twind.commissioning.measurement import measure_tfs

    gains = np.array([0.03, -0.02, 0.01, -0.025])
    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    act = plant.actuation.copy()
    act[:, :4] *= 1 + gains
    real = replace(plant, actuation=act)
    tfs = measure_tfs(etmx, bw=0.05, averages=10, rms=3.0, seed=3, plant=real)
    params = ["wire_length_m", "b_m", "R1_m", "osem_lever_m"]
    nominal = fit(tfs, etmx, params)
    augmented = fit(tfs, etmx, params, effect="coil_imbalance")
    assert nominal.bic - augmented.bic > 100
    assert augmented.chi2_nu < 1.5 < nominal.chi2_nu
    # four coils drive three DOFs: the "butterfly" UL - UR - LL + LR moves nothing
    assert augmented.unidentifiable == ["gain_UL - gain_UR - gain_LL + gain_LR"]
    got = np.array([augmented.as_dict()[f"gain_{f}"] for f in ("UL", "UR", "LL", "LR")])
    butterfly = np.array([1, -1, -1, 1]) / 2
    miss = (got - gains) - butterfly * (butterfly @ (got - gains))
    assert np.max(np.abs(miss)) < 0.002, (got, gains)


@pytest.mark.slow
def test_pull_test_side_by_side_is_the_same_test() -> None:
    """Realisation i is seed + i whichever process runs it: two workers give the pulls one
    gives, and the report prints the pooled figure."""
    from twind.lab.calibration import pull_test

    cfg = load_config(None, ["ETMX"]).optics["ETMX"]
    kw = {"n": 2, "bw": 0.2, "estimator": "lpm"}
    one, two = pull_test(cfg, workers=1, **kw), pull_test(cfg, workers=2, **kw)
    assert np.array_equal(one.pulls, two.pulls, equal_nan=True)
    assert np.isfinite(one.pulls).sum() >= 8
    assert "pooled: " in one.lines()[-1]


def test_correlated_responses_are_whitened_together() -> None:
    """Errors of two responses correlated at 0.95 come out of the whitening independent and
    of unit variance, also where one response is not used."""
    rng = np.random.default_rng(3)
    nf, rho = 4000, 0.95 * np.exp(0.4j)
    C = np.array([[1, rho], [np.conj(rho), 1]])
    L = np.linalg.cholesky(C)
    e = (rng.standard_normal((nf, 2)) + 1j * rng.standard_normal((nf, 2))) @ L.T
    sigma = np.array([0.5, 2.0])
    H = (e * sigma)[:, :, None]
    mask = np.ones((nf, 2, 1), bool)
    mask[::3, 1] = False  # one bin in three without the second response
    corr = np.broadcast_to(C[None, :, :, None], (nf, 2, 2, 1))
    data = FitData(np.arange(1.0, nf + 1), ["POS", "PIT"], ["POS"], H,
                   np.broadcast_to(sigma[None, :, None], H.shape), mask, 10,
                   correlation=corr)
    z = data.whiten(np.zeros_like(H))
    assert abs(np.var(z) - 1) < 0.05
    n = data.bins
    full = np.flatnonzero(mask[:, 1, 0])
    zc = (z[:n] + 1j * z[n:])
    pos = np.cumsum(mask.reshape(nf, 2)).reshape(nf, 2) - 1  # index among the used bins
    a, b = zc[pos[full, 0]], zc[pos[full, 1]]
    assert abs(np.mean(a * np.conj(b))) < 0.1  # it was 0.95 before
    plain = FitData(data.frequency_hz, data.responses, data.excited, H, data.sigma, mask, 10)
    zp = plain.whiten(np.zeros_like(H))
    zp = zp[:n] + 1j * zp[n:]
    assert abs(np.mean(zp[pos[full, 0]] * np.conj(zp[pos[full, 1]])) / 2) > 0.9
