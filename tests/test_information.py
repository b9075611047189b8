"""Information-mode excitation design (D-optimal multisines) and the identification campaign."""

from __future__ import annotations

import io
import json
from contextlib import redirect_stdout
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from servicekit import serving

from twind.analysis.identification.params import param_value, with_params
from twind.cli import main
from twind.config import NOMINAL_ETMX, load_config, load_optic
from twind.analysis.design.coherence import ExcitationDesignError
from twind.analysis.design.information import design_information, tone_fisher
from twind.lab.calibration import DRIFT
from twind.commissioning.campaign import BusTwin, LocalTwin, run_campaign


@pytest.fixture(scope="module")
def etmx():  # noqa: ANN201
    """The nominal ETMX, the campaign's drifts (``calibration.DRIFT``) are relative to it."""
    return load_optic(NOMINAL_ETMX)


@pytest.fixture(scope="module")
def design(etmx):  # noqa: ANN001, ANN201
    return design_information(etmx, ["POS", "PIT", "YAW"], (0.1, 10.0), rms=10.0,
                              duration_s=100.0, period_s=20.0)


def test_design_is_d_optimal_and_beats_white_noise(etmx, design) -> None:  # noqa: ANN001
    assert design.unidentifiable == ["Q_SIDE"]  # SIDE is neither excited nor coupled
    assert design.gain > 5.0
    # Kiefer-Wolfowitz: no candidate tone would add more information than the design's mean
    f = np.arange(2, 201) / 20.0
    F = tone_fisher(etmx, design.params, list(design.tones), f, 100.0)
    M = np.zeros((len(design.params), len(design.params)))
    for i, d in enumerate(design.tones):
        k = np.searchsorted(f, design.tones[d])
        M = M + np.einsum("k,kpq->pq", design.amps[d] ** 2 / 2, F[i, k])
    Minv = np.linalg.inv(M)
    for i, d in enumerate(design.tones):
        var = np.einsum("pq,kqp->k", Minv, F[i]) * design.rms[d] ** 2
        k = np.searchsorted(f, design.tones[d])
        mean = np.sum(design.amps[d] ** 2 / 2 * var[k]) / design.rms[d] ** 2
        assert var.max() <= 1.01 * mean, d
    assert np.allclose(np.linalg.inv(M), design.covariance, rtol=1e-3)


def test_waveform_has_the_rms_and_tones(design) -> None:  # noqa: ANN001
    rate = 16384.0
    x = design.waveform("POS", int(20 * rate), rate)
    assert np.sqrt(np.mean(x**2)) == pytest.approx(10.0, rel=1e-9)
    spec = np.abs(np.fft.rfft(x)) / x.size * 2
    k = np.rint(design.tones["POS"] * 20).astype(int)
    np.testing.assert_allclose(spec[k], design.amps["POS"], rtol=1e-9)
    assert spec.sum() == pytest.approx(spec[k].sum(), rel=1e-9)


def test_singular_request_names_what_it_cannot_inform(etmx) -> None:  # noqa: ANN001
    # YAW, decoupled from the rest, is driven by coil x lever and read without the lever:
    # only their product can be informed
    d = design_information(etmx, ["YAW"], (0.3, 3.0), 5.0, 100.0,
                           params=["coil_N_per_ct", "osem_lever_m", "Q_SIDE"])
    assert "Q_SIDE" in d.unidentifiable and len(d.params) == 1
    with pytest.raises(ExcitationDesignError, match="tones"):
        design_information(etmx, ["POS"], (0.1, 0.12), 5.0, 100.0)


def test_excite_information_cli(tmp_path: Path) -> None:
    out = io.StringIO()
    with redirect_stdout(out):
        assert main(["excite", "--mode", "information", "--band", "0.2", "5", "--dof", "POS",
                     "--dof", "PIT", "--json", "-o", str(tmp_path / "info.png")]) == 0
    obj = json.loads(out.getvalue())
    assert obj["det_cov_gain_over_white"] > 1 and set(obj["excitations"]) == {"POS", "PIT"}
    assert (tmp_path / "info.png").stat().st_size > 10_000
    assert main(["excite", "--mode", "information", "--band", "0.2", "5", "--rms", "90"]) == 2


def _drifted(etmx):  # noqa: ANN001, ANN202
    return replace(etmx, sus=with_params(etmx.sus, {k: param_value(etmx.sus, k) * f
                                                    for k, f in DRIFT.items()}))


def test_campaign_on_a_local_twin_converges_on_the_truth(etmx) -> None:  # noqa: ANN001
    real = _drifted(etmx)
    rounds = run_campaign(etmx, LocalTwin(real), ["POS", "PIT"], (0.2, 5.0), rms=10.0,
                          period_s=10.0, averages=5, max_rounds=2, target=1e-9)
    assert len(rounds) == 2 and rounds[1].twin_s == 2 * rounds[0].twin_s
    first, last = rounds[0].relative_sigma, rounds[1].relative_sigma
    assert all(last[n] < first[n] for n in set(first) & set(last))
    fit = rounds[-1].fit
    # a sigma is NaN only for a parameter in a combination the fit says the data cannot fix
    # (a Q of a DOF never excited), and every other value lies within 4 sigma of the truth
    undetermined = {n for n, s in zip(fit.names, fit.sigma, strict=True) if not np.isfinite(s)}
    named = {n for n in fit.names if any(n in combo for combo in fit.unidentifiable)}
    assert undetermined <= named and len(undetermined) < len(fit.names) / 2
    for n, v, s in zip(fit.names, fit.values, fit.sigma, strict=True):
        if n not in undetermined:
            assert abs(v - param_value(real.sus, n)) < 4 * s, n


@pytest.mark.slow
def test_campaign_against_a_running_twin_pushes_its_fit(tmp_path: Path) -> None:
    """The bus route: inject streams into a served twin, record, fit, push into a second
    twin (the self-updating one)."""
    served = load_config(None, ["ETMX"]).optics["ETMX"]
    with serving("--optics", "ETMX", "--speed", "8") as real, \
            serving("--optics", "ETMX", "--speed", "1") as model:
        twin = BusTwin([real], "ETMX", update=[model], workdir=tmp_path)
        rounds = run_campaign(served, twin, ["POS"], (0.3, 3.0), rms=5.0, period_s=5.0,
                              averages=5, params=["wire_length_m", "coil_N_per_ct"],
                              max_rounds=1)
        pushed = twin.updated.params("ETMX").params
    fit = rounds[0].fit
    assert np.all(np.isfinite(fit.sigma)) and fit.chi2_nu < 3
    assert pushed["wire_length_m"] == pytest.approx(fit.values[0], rel=1e-12)
    assert len(list(tmp_path.glob("*.mcap"))) == 1
