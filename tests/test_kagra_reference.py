"""The independent KAGRA reference (twind/lab/kagra_reference.py) finds what a synthetic
measurement holds, and its hand-curated answer key (tests/data/kagra/reference.toml) is
well formed. The full run on the five real files takes minutes: it is kept off the suite
(``python -m twind.lab.kagra_reference -o DIR``)."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from twind.analysis.estimation.diaggui import write_fft_measurement
from twind.lab.kagra_reference import FILES, Model, analyse

ROOT = Path(__file__).resolve().parent.parent
RESONANCES = ((0.9, 30.0, 1.0), (2.3, 50.0, 0.6))
"""Frequency (Hz), Q and DC gain of the two resonances summed."""
DELAY_S = 0.020
FS, SEGMENT_S = 32.0, 128.0  # 2^-7 Hz bins, as in KAGRA's files


def _model() -> Model:
    """The two resonances as one state-space model, named as KAGRA's model names them."""
    blocks = []
    for f0, q, g in RESONANCES:
        w = 2 * math.pi * f0
        blocks.append((np.array([[0.0, 1.0], [-w * w, -w / q]]), np.array([0.0, g * w * w])))
    a = np.zeros((4, 4))
    a[:2, :2], a[2:, 2:] = blocks[0][0], blocks[1][0]
    b = np.concatenate([blocks[0][1], blocks[1][1]])[:, None]
    return Model(a, b, np.array([[1.0, 0.0, 1.0, 0.0]]), np.zeros((1, 1)), ["exc_TMP"],
                 ["OpLev_TMP"])


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Model]:
    """Five Hann averages (half overlapping) of white noise through the resonances, delayed
    and with sensor noise added, written as diaggui writes an FFT test, and its reference."""
    rng = np.random.default_rng(7)
    nseg = int(SEGMENT_S * FS)
    x = rng.standard_normal(3 * nseg)
    f = np.fft.rfftfreq(x.size, 1 / FS)
    model = _model()
    h = model.response(f, ["exc_TMP"], ["OpLev_TMP"])[:, 0, 0] * np.exp(-2j * np.pi * f * DELAY_S)
    y = np.fft.irfft(np.fft.rfft(x) * h, x.size) + 0.01 * rng.standard_normal(x.size)
    kw = {"fs": FS, "window": "hann", "nperseg": nseg}
    freq, pxy = signal.csd(x, y, **kw)
    _, pxx = signal.welch(x, **kw)
    _, coh = signal.coherence(x, y, **kw)
    keep = freq <= 10.0
    path = write_fft_measurement(
        tmp_path_factory.mktemp("kagra") / "SYN_TMP.xml", "K1:VIS-SRM_TM_TEST_P_EXC",
        ["K1:VIS-SRM_TM_OPLEV_PIT_DIAG"], freq[keep], pxx[keep], (pxy / pxx)[keep][None],
        coh[keep][None], averages=5, rate_hz=FS)
    return analyse(path, model)[0], model


def test_it_finds_both_resonances_within_their_sigma(synthetic: tuple[dict, Model]) -> None:
    report, _ = synthetic
    found = report["modes"]  # the antiresonance between them is no peak
    assert len(found) == 2, [m["f"] for m in found]
    for mode, (f0, _, _) in zip(found, RESONANCES, strict=True):
        assert 0 < mode["sigma_f"] < 0.01
        assert abs(mode["f"] - f0) < 3 * mode["sigma_f"], (mode["f"], mode["sigma_f"], f0)
        assert mode["model"] is not None and abs(mode["model"]["f"] - f0) < 1e-6


def test_it_reads_the_scale_and_the_delay(synthetic: tuple[dict, Model]) -> None:
    report, _ = synthetic
    element = report["elements"]["TM_OPLEV_PIT_DIAG"]
    assert element["modelled"] and element["coherent"]
    assert element["scale"]["reliable"] and abs(element["scale"]["magnitude"] - 1) < 0.1
    assert abs(element["scale"]["phase_low_deg"]) < 2  # the delay taken out
    assert abs(element["delay"]["tau_ms"] / (1e3 * DELAY_S) - 1) < 0.1, element["delay"]


def test_the_answer_key_names_the_five_files_only() -> None:
    key = tomllib.loads((ROOT / "tests" / "data" / "kagra" / "reference.toml").read_text())
    assert set(key["files"]) == set(FILES)
    for name, entry in key["files"].items():
        assert entry["modes"], name
        for mode in entry["modes"]:
            assert mode["f"] > 0 and mode["sigma"] > 0 and mode["reason"]
            assert isinstance(mode["model_f"], float) or mode["model_f"] == "none"
