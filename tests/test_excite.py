"""``twind excite`` coherence mode: the noise model, the estimator margin, the design, its
exports, the refusals, and an end-to-end measurement on the engine.

Statistical checks use fixed seeds and thresholds with room for the estimators' scatter.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re

import numpy as np
import pytest
from scipy import signal

from twind import DOFS
from twind.analysis.noise import in1_noise_asd
from twind.cli import main
from twind.config import load_config
from twind.excitation import ExcitationRequest, Limits, check, make_waveform
from twind.analysis.design.coherence import (
    ExcitationDesignError,
    coherence_cdf,
    design_coherence,
    design_coherent,
)
from twind.excitation.design import noise_shape
from twind.loop.foton import parse_design
from twind.simulation.engine import Engine

R = 16384.0
RI = int(R)
WIDE = Limits(peak=math.inf, rms=math.inf)


@pytest.fixture(scope="module")
def etmx():
    return load_config(None, ["ETMX"]).select(["ETMX"])[0]


@pytest.fixture(scope="module")
def pos_design(etmx):
    return design_coherent(etmx, ["POS"], (0.5, 5.0), target=0.7, averages=10, bw=0.05)


# --------------------------------------------------------------------------------------------
# the noise the design works against


def test_noise_prediction_matches_the_engine(etmx) -> None:
    """Predicted IN1 noise PSD vs the engine's, averaged over 2-50 Hz (bw 0.25 Hz)."""
    eng = Engine([etmx.loop()], noise=etmx.noise, seed=11)
    eng.step(RI * 4)  # settle
    blk = eng.step(RI * 40)
    f, p = signal.welch(blk.in1[0], fs=R, nperseg=RI * 4)
    sel = (f >= 2.0) & (f <= 50.0)
    pred = in1_noise_asd(etmx, f[sel]) ** 2
    ratio = np.mean(p[:, sel].T / pred, axis=0)
    # ~190 bins x ~19 segments: the mean of the ratio is good to a few percent
    assert np.all(np.abs(ratio - 1.0) < 0.06), ratio


def test_noise_disabled_is_refused(etmx) -> None:
    quiet = dataclasses.replace(etmx, noise=dataclasses.replace(etmx.noise, enabled=False))
    assert np.all(in1_noise_asd(quiet, [1.0, 10.0]) == 0)
    with pytest.raises(ExcitationDesignError, match="noise is disabled"):
        design_coherent(quiet, "POS", (1.0, 3.0))


# --------------------------------------------------------------------------------------------
# the estimator margin


def test_coherence_distribution() -> None:
    # zero true coherence: P(C > c) = (1 - c)^(n - 1), exactly
    for c in (0.1, 0.3, 0.7):
        assert coherence_cdf(c, 0.0, 10) == pytest.approx(1 - (1 - c) ** 9, rel=1e-12)
    # against a Monte Carlo of Gaussian Fourier coefficients
    rng = np.random.default_rng(5)
    n, g2, m = 10, 0.8, 20000
    x = rng.standard_normal((m, n)) + 1j * rng.standard_normal((m, n))
    y = math.sqrt(g2 / (1 - g2)) * x + rng.standard_normal((m, n)) + 1j * rng.standard_normal((m, n))
    c_hat = np.abs(np.sum(x * y.conj(), 1)) ** 2 / (np.sum(abs(x) ** 2, 1) * np.sum(abs(y) ** 2, 1))
    for c in (0.6, 0.7, 0.8, 0.9):
        p = coherence_cdf(c, g2, n)
        assert abs(np.mean(c_hat <= c) - p) < 4 * math.sqrt(p * (1 - p) / m) + 1e-3, c
    # the normal approximation takes over smoothly above the exact range
    assert coherence_cdf(0.7, 0.75, 400) == pytest.approx(coherence_cdf(0.7, 0.75, 401), abs=2e-3)
    # the design coherence: the estimate misses the target with probability 1 - confidence
    g = design_coherence(0.7, 10, 0.95)
    assert 0.7 < g < 1
    assert coherence_cdf(0.7, g, 10) == pytest.approx(0.05, abs=1e-6)
    assert design_coherence(0.7, 1000, 0.95) < g  # more averages, less margin


# --------------------------------------------------------------------------------------------
# the design


def _expected_welch_coherence(optic, d, bw: float) -> np.ndarray:
    """Coherence of Hann-windowed spectra at each bin of design `d`, from the model alone.

    The window's power response comes from the FFT of a discrete Hann window (16 points a
    bin, +-16 bins), independently of the design code's analytic kernel.
    """
    n = 512
    power = np.abs(np.fft.fft(signal.windows.hann(n, sym=False), 16 * n)) ** 2
    x = np.fft.fftfreq(16 * n, 1.0 / n)  # in bins
    keep = np.abs(x) <= 16
    x, k = x[keep], power[keep]
    loop = optic.loop()
    out = []
    for fk in d.f_hz:
        f = fk + x * bw
        fa = np.maximum(np.abs(f), 1e-6)
        t = loop.responses(fa)["closed_loop_IN1_per_EXC"][:, 0, 0]
        t[f < 0] = t[f < 0].conj()
        n2 = in1_noise_asd(optic, fa, loop)[:, 0] ** 2
        a2 = np.abs(parse_design(d.foton).response(fa)) ** 2
        sxy, sxx = np.sum(k * t * a2), np.sum(k * a2)
        syy = np.sum(k * (np.abs(t) ** 2 * a2 + n2))
        out.append(abs(sxy) ** 2 / (sxx * syy))
    return np.array(out)


def test_design_reaches_the_target_in_every_bin(etmx, pos_design) -> None:
    d = pos_design.dofs["POS"]
    assert pos_design.target == 0.7 and pos_design.design_coherence > 0.7
    assert d.f_hz[0] == pytest.approx(0.5) and d.f_hz[-1] == pytest.approx(5.0)
    assert np.allclose(np.diff(d.f_hz), 0.05)
    # recomputed from the model, the noise and the exported shape alone
    coh = _expected_welch_coherence(etmx, d, pos_design.bw)
    assert np.all(coh >= pos_design.design_coherence - 2e-3), coh.min()
    assert np.allclose(coh, d.coherence, atol=2e-3)
    assert np.all(d.coherence >= pos_design.design_coherence * (1 - 1e-9))
    assert np.all(d.design_asd >= d.required_asd)
    # the textbook requirement, for a bin that sees only its own frequency
    loop = etmx.loop()
    T = np.abs(loop.responses(d.f_hz)["closed_loop_IN1_per_EXC"][:, 0, 0])
    n = in1_noise_asd(etmx, d.f_hz, loop)[:, 0]
    g2 = pos_design.design_coherence
    assert np.allclose(d.narrowband_asd, math.sqrt(g2 / (1 - g2)) * n / T, rtol=1e-9)
    # at this fine resolution the window's leakage changes it by a few percent only
    assert np.allclose(d.required_asd, d.narrowband_asd, rtol=0.1)
    # the shape is tight where it matters: within a factor 1.05 of the requirement somewhere
    assert np.min(d.design_asd / d.required_asd) < 1.05
    # ... and it rolls off outside the band
    assert d.asd(0.05) < 1e-2 * d.asd(0.5) and d.asd(50.0) < 1e-2 * d.asd(5.0)


def test_design_exports(etmx, pos_design) -> None:
    d = pos_design.dofs["POS"]
    zpk = parse_design(d.foton)
    f = np.geomspace(0.05, 100, 50)
    assert np.allclose(zpk.response(f), d.zpk.response(f), rtol=1e-12)
    # stable and minimum phase
    assert np.all(zpk.poles.real < 0) and np.all(zpk.zeros.real <= 0)
    # the zpk JSON is the same filter (foton "f" plane convention)
    j = d.to_json()
    z = np.array([complex(*r) for r in j["zpk"]["zeros_hz"]]) * 2 * np.pi
    p = np.array([complex(*r) for r in j["zpk"]["poles_hz"]]) * 2 * np.pi
    s = 2j * np.pi * f
    h = j["zpk"]["gain"] * np.prod(s[:, None] - z, 1) / np.prod(s[:, None] - p, 1)
    assert np.allclose(h, zpk.response(f), rtol=1e-9)
    # the request, through its JSON form, is accepted by the excitation checks
    req = ExcitationRequest.from_json(json.loads(json.dumps(j["request"])))
    assert req.waveform == "noise" and req.shape == d.foton
    assert req.channel == "C1:SUS-ETMX_SUSPOS_EXC"
    check(req, Limits(peak=100.0, rms=30.0), R)
    # its RMS makes |zpk| the ASD: amp = noise gain x sqrt(rate / 2)
    assert req.amp == pytest.approx(noise_shape(d.foton, R).gain_rms * math.sqrt(R / 2))
    assert d.rms == req.amp and d.peak == pytest.approx(6 * d.rms)
    assert req.duration >= pos_design.averages / pos_design.bw
    assert "--shape" in d.inject_command() and d.channel in d.inject_command()


def test_impossible_limits_are_refused(etmx, pos_design) -> None:
    rms = pos_design.dofs["POS"].rms
    with pytest.raises(ExcitationDesignError, match="RMS limit") as err:
        design_coherent(etmx, "POS", (0.5, 5.0), bw=0.05, limits=Limits(peak=100, rms=rms / 2))
    assert f"{rms:.4g}" in str(err.value) and f"{rms / 2:.4g}" in str(err.value)
    assert "C1:SUS-ETMX_SUSPOS_EXC" in str(err.value)
    with pytest.raises(ExcitationDesignError, match="peak limit") as err:
        design_coherent(etmx, "POS", (0.5, 5.0), bw=0.05, limits=Limits(peak=3 * rms, rms=30))
    assert f"{6 * rms:.4g}" in str(err.value) and f"{3 * rms:.4g}" in str(err.value)
    # the notches of the damping filter: IN1/EXC has zeros there
    with pytest.raises(ExcitationDesignError, match="zero or a sharp resonance") as err:
        design_coherent(etmx, "POS", (10.0, 20.0), bw=0.05)
    assert re.search(r"bin at 1[56]\.\d+ Hz", str(err.value))


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"band": (3.0, 1.0)}, "band"),
    ({"band": (1.0, 9000.0)}, "Nyquist"),
    ({"target": 1.0}, "target"),
    ({"averages": 1}, "averages"),
    ({"bw": 5.0}, "bin"),
    ({"dofs": ["ROLL"]}, "unknown DOF"),
    ({"dofs": ["POS", "YAW"], "responses": "all"}, "does not respond"),
    # a 0.25 Hz Hann bin at 1 Hz spans the loop's resonances: the measured coherence there
    # stays near 0.5 whatever the drive (seen on the engine), so the design refuses
    ({"band": (1.0, 4.0), "bw": 0.25}, "bin at 1 Hz"),
])
def test_bad_settings(etmx, kwargs, match) -> None:
    args = {"dofs": ["POS"], "band": (1.0, 3.0), "bw": 0.05} | kwargs
    with pytest.raises(ExcitationDesignError, match=match):
        design_coherent(etmx, args.pop("dofs"), args.pop("band"), **args)


def test_several_dofs_and_responses(etmx) -> None:
    d = design_coherent(etmx, ["POS", "PIT"], (1.5, 3.0), bw=0.05, responses="all",
                        limits=WIDE)
    assert list(d.dofs) == ["POS", "PIT"]
    g2 = d.design_coherence
    for j, x in enumerate(d.dofs.values()):
        assert x.responses == ("POS", "PIT") and x.noise_asd.shape == (x.f_hz.size, 2)
        assert np.all(x.coherence >= g2 * (1 - 1e-9))
        each = math.sqrt(g2 / (1 - g2)) * x.noise_asd / x.transfer
        assert np.allclose(x.narrowband_asd, each.max(axis=1))
        # the cross-coupled response needs more drive than the excited DOF's own
        assert np.all(each[:, 1 - j] > each[:, j])
        assert x.request.channel == f"C1:SUS-ETMX_SUS{x.dof}_EXC"


# --------------------------------------------------------------------------------------------
# the command line


def test_cli(tmp_path, capsys) -> None:
    png = tmp_path / "excite.png"
    assert main(["excite", "--dof", "PIT", "--band", "1", "3", "--bw", "0.1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["mode"] == "coherence" and out["target"] == 0.7 and out["averages"] == 10
    pit = out["dofs"]["PIT"]
    req = ExcitationRequest.from_json(pit["request"])
    check(req, Limits(peak=out["limits"]["peak"], rms=out["limits"]["rms"]), R)
    assert main(["excite", "--dof", "PIT", "--band", "1", "3", "--bw", "0.1", "-o", str(png)]) == 0
    text = capsys.readouterr().out
    assert "foton: zpk(" in text and "twind inject C1:SUS-ETMX_SUSPIT_EXC noise" in text
    assert f"wrote {png}" in text and png.stat().st_size > 10_000
    assert main(["excite", "--dof", "PIT", "--band", "1", "3", "--bw", "0.1",
                 "--rms", "0.01"]) == 2
    err = capsys.readouterr().err
    assert "RMS limit 0.01" in err and "Traceback" not in err


# --------------------------------------------------------------------------------------------
# end to end: the designed excitation on the engine


def test_measured_coherence_reaches_the_target(etmx) -> None:
    """Inject the design into the engine and measure the coherence as diaggui would."""
    bw, averages, target, band = 0.2, 10, 0.7, (1.5, 4.0)
    d = design_coherent(etmx, ["POS"], band, target=target, averages=averages, bw=bw,
                        seed=3).dofs["POS"]
    assert d.order >= 1 and d.f_hz.size == 13
    req = d.request
    wave = make_waveform(req, R)
    n_total = round(req.duration * R)
    eng = Engine([etmx.loop()], noise=etmx.noise, seed=4)
    exc, in1 = np.empty(n_total), np.empty(n_total)
    block = RI * 4
    for a in range(0, n_total, block):
        m = min(block, n_total - a)
        drive = np.zeros((1, len(DOFS), m))
        drive[0, 0] = wave.next(m)
        b = eng.step(m, exc=drive)
        exc[a:a + m], in1[a:a + m] = b.exc[0, 0], b.in1[0, 0]
    # the flat part of the excitation: after the ramp (and the shaping filter's start)
    r = round(req.ramp * R)
    x, y = exc[r:n_total - r], in1[r:n_total - r]
    assert x.size >= averages / bw * R * 0.99
    assert np.std(x) == pytest.approx(req.amp, rel=0.1)
    f, coh = signal.coherence(x, y, fs=R, nperseg=round(R / bw))
    inband = (f >= band[0] - 1e-9) & (f <= band[1] + 1e-9)
    assert np.allclose(f[inband], d.f_hz)
    frac = float(np.mean(coh[inband] >= target))
    assert frac >= 0.9, (frac, coh[inband])
    # the excitation is not wastefully strong: the coherence is not ~1 everywhere, and the
    # model predicts what is measured (medians over 13 bins of 19 overlapped segments)
    assert np.median(coh[inband]) < 0.995
    assert np.median(coh[inband]) == pytest.approx(np.median(d.coherence), abs=0.05)
