"""Any diaggui measurement: a real swept sine saved by diaggui, and an FFT measurement with
another observatory's channel names (written by twind in diaggui's layout)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from twind.analysis.estimation.diaggui import read_transfers, write_fft_measurement
from twind.analysis.estimation.tf import from_diaggui
from twind.analysis.estimation.tfset import TFError
from twind.cli import main

DARM = Path(__file__).parent / "data" / "H1_DARM_OLGTF_swept_sine_2020-01-03.xml"
KAGRA_EXC = "K1:VIS-MCE_TM_TEST_P_EXC"
KAGRA_READBACKS = [f"K1:VIS-MCE_TM_OLDAMP_{d}_IN1_DQ" for d in ("L", "P", "Y")]


def test_a_swept_sine_saved_by_diaggui_is_read_with_its_errors() -> None:
    in1, in2 = read_transfers(DARM)
    assert (in1.name, in2.name) == ("H1:LSC-DARM1_IN1/H1:LSC-DARM1_EXC",
                                    "H1:LSC-DARM1_IN2/H1:LSC-DARM1_EXC")
    assert in1.kind == "swept sine" and in1.averages == 5 and len(in1.frequency_hz) == 46
    assert in1.frequency_hz[0] == pytest.approx(5.619)
    assert abs(in1.tf[0] - (-0.994 + 0.007j)) < 1e-3
    assert np.all(in1.sigma() > 0)
    # IN2 = IN1 + EXC, point by point, within the errors the points carry
    excess = np.abs(in2.tf - in1.tf - 1) / np.hypot(in1.sigma(), in2.sigma())
    assert np.all(excess < 3)


def test_an_fft_measurement_of_another_observatory_is_read(tmp_path: Path) -> None:
    f = np.arange(1, 201) * 0.05
    tf = np.array([(k + 1) / (1 + 1j * f / 2.0) for k in range(3)])
    coherence = np.array([np.full(f.size, c) for c in (0.99, 0.9, 0.5)])
    path = write_fft_measurement(tmp_path / "kagra.xml", KAGRA_EXC, KAGRA_READBACKS, f,
                                 np.ones(f.size), tf, coherence, averages=12)
    transfers = read_transfers(path)
    assert [t.numerator for t in transfers] == KAGRA_READBACKS
    for t, h, g2 in zip(transfers, tf, coherence, strict=True):
        assert t.kind == "FFT" and t.denominator == KAGRA_EXC and t.averages == 12
        np.testing.assert_allclose(t.tf, h, rtol=1e-6)
        np.testing.assert_allclose(t.coherence, g2, rtol=1e-6)
    # Bendat & Piersol: the noisier readback has the larger error
    assert np.all(transfers[2].sigma() / 3 > transfers[0].sigma())
    with pytest.raises(TFError, match="K1:VIS-MCE_TM_TEST_P_EXC.*twind tf"):
        from_diaggui([path])  # fit and diagnose say what a suspension set needs


def test_twind_tf_shows_any_measurement(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["tf", str(DARM)]) == 0
    out = capsys.readouterr().out
    assert "H1:LSC-DARM1_IN1/H1:LSC-DARM1_EXC (swept sine, 5 averages, 46 points" in out
    assert main(["tf", str(DARM), "--json", "--band", "5", "10"]) == 0
    shown = json.loads(capsys.readouterr().out)["transfers"]
    assert [len(t["frequency_hz"]) for t in shown] == [11, 11]  # 5.62-9.10 Hz
    assert all(max(t["frequency_hz"]) <= 10 for t in shown)
    png = tmp_path / "darm.png"
    assert main(["tf", str(DARM), "-o", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
