"""Transfer functions from diaggui XML and MCAP sessions, and the recovered plant."""

from __future__ import annotations

import glob
import io
import json
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from conftest import REFERENCE
from twind import DOFS
from twind.analysis.tf import TFError, from_diaggui, from_session, welch_tf, xml_transfer
from twind.cli import main
from twind.config import load_config
from twind.loop.plant import Plant
from twind.model.analytical import analytical_mechanics
from twind.recording.writer import SessionWriter
from twind.simulation.engine import Engine

NULL = sorted(glob.glob(str(REFERENCE / "example_null" / "*.xml")))


def _model_plant(sus, f: np.ndarray, dofs: list[str]) -> np.ndarray:  # noqa: ANN001
    P = Plant.from_params(sus, analytical_mechanics(sus)).response(f)
    idx = [DOFS.index(d) for d in dofs]
    return P[:, idx][:, :, idx]


def _normalised_power(tfs, sus, min_coherence: float = 0.0) -> np.ndarray:  # noqa: ANN001
    """Mean |P - P_model|^2 / (2 sigma^2) of each diagonal element, over the bins where
    its DOF's IN1 and OUT coherence reaches `min_coherence` (first-order error propagation
    through the matrix inverse holds only where the data are coherent)."""
    P, sigma = tfs.plant()
    r = np.abs(P - _model_plant(sus, tfs.frequency_hz, tfs.excited)) / sigma
    out = []
    for i, dof in enumerate(tfs.excited):
        k = tfs.responses.index(dof)
        keep = np.minimum(tfs.coherence["IN1"][:, k, i], tfs.coherence["OUT"][:, k, i])
        out.append(np.mean(r[keep >= min_coherence, i, i] ** 2) / 2)
    return np.array(out)


def test_xml_transfer_functions_are_dttxml_xfer() -> None:
    import dttxml

    tfs = from_diaggui(NULL)
    assert tfs.excited == ["POS", "PIT", "YAW"] and tfs.responses == list(DOFS)
    assert tfs.averages == 10
    acc = dttxml.DiagAccess(NULL[1])  # ETMX_POS_exc.xml
    x = acc.xfer("C1:SUS-ETMX_SUSPIT_IN2", "C1:SUS-ETMX_SUSPOS_EXC")
    assert np.array_equal(tfs.tf["IN2"][:, DOFS.index("PIT"), 0], x.xfer)
    assert np.array_equal(tfs.coherence["IN2"][:, DOFS.index("PIT"), 0], x.coh)


def test_example_null_plant_matches_its_drifted_truth() -> None:
    """The plant recovered from example_null agrees with the model at its truth.json
    parameters within the errors, and less well with the nominal ones."""
    truth = json.loads((REFERENCE / "example_null" / "truth.json").read_text())["drifted_params"]
    nominal = load_config(None, ["ETMX"]).optics["ETMX"].sus
    tfs = from_diaggui(NULL).band(0.3, 5.0)
    at_truth = _normalised_power(tfs, nominal.updated(**truth))
    at_nominal = _normalised_power(tfs, nominal)
    expected = tfs.averages / (tfs.averages - 2)  # |r|^2 of a 10-average estimate
    assert np.all(np.abs(at_truth / expected - 1) < 0.15), at_truth
    assert np.all(at_nominal > at_truth), (at_nominal, at_truth)


def test_real_diaggui_swept_sine_reads() -> None:
    f, h, g2, n = xml_transfer(REFERENCE / "real" / "H1_DARM_OLGTF_swept_sine_2020-01-03.xml",
                               "H1:LSC-DARM1_IN1", "H1:LSC-DARM1_EXC")
    assert f[0] == pytest.approx(5.619) and len(f) == 46
    assert h[0] == pytest.approx(-0.994 + 0.007j, abs=2e-3)


def test_welch_equals_scipy() -> None:
    from scipy import signal

    rng = np.random.default_rng(1)
    x = rng.standard_normal(40000)
    y = signal.lfilter([0.3, 0.2], [1, -0.5], x) + 0.1 * rng.standard_normal(x.size)
    f, h, g2, n = welch_tf(x, y, 1000.0, 1000)
    _, pxy = signal.csd(x, y, fs=1000.0, nperseg=1000, noverlap=500)
    _, pxx = signal.welch(x, fs=1000.0, nperseg=1000, noverlap=500)
    np.testing.assert_allclose(h, pxy / pxx, rtol=1e-10)
    assert n == 79


def test_session_plant_recovered_from_a_twin_recording(tmp_path: Path) -> None:
    """MCAP route: an engine run with one band-limited excitation per DOF, recorded with
    its injection events; the recovered plant equals the model's within the errors."""
    cfg = load_config(None, ["ETMX"]).optics["ETMX"]
    eng = Engine([cfg.loop()], cfg.noise, seed=4)
    rate, seg = 16384, 60
    amps = {"POS": 2.0, "PIT": 5.0, "YAW": 5.0}  # RMS, in band: white below 10 Hz
    from scipy import signal

    band = signal.butter(4, 10.0, fs=rate, output="sos")
    path = tmp_path / "twin.mcap"
    rng = np.random.default_rng(7)
    gps0 = 1.4e9
    with SessionWriter(path, "C1", gps0) as w:
        for k, (dof, amp) in enumerate(amps.items()):
            start = gps0 + k * seg
            w.write_event({"event": "start", "id": f"e{k}", "channel": f"C1:SUS-ETMX_SUS{dof}_EXC",
                           "gps": start, "start_gps": start, "request": {"duration": seg}})
            for _ in range(seg):
                exc = np.zeros((1, 4, rate))
                exc[0, DOFS.index(dof)] = amp * signal.sosfilt(band, rng.standard_normal(rate)) \
                    * np.sqrt(rate / 2 / 10)
                w.write_block(eng.step(rate, exc=exc))
    tfs = from_session([path], bw=0.25).band(0.3, 8.0)
    assert tfs.excited == ["POS", "PIT", "YAW"]
    power = _normalised_power(tfs, cfg.sus, min_coherence=0.7)
    expected = tfs.averages / (tfs.averages - 2)
    # the plant's sigma treats the IN1 and OUT errors as independent; both come from the
    # same noise, so it is conservative: measured 0.4-0.5 of the expected power here
    assert np.all((power > 0.25 * expected) & (power < 1.2 * expected)), (power, expected)

    out = io.StringIO()
    with redirect_stdout(out):
        assert main(["tf", str(path), "--bw", "0.25", "--json", "--band", "0.3", "8"]) == 0
    obj = json.loads(out.getvalue())
    assert obj["excited"] == ["POS", "PIT", "YAW"]
    assert np.array(obj["plant"]["re"]).shape == (len(tfs.frequency_hz), 3, 3)


def test_results_written_as_hdf5_and_csv(tmp_path: Path) -> None:
    import h5py

    tfs = from_diaggui(NULL).band(0.5, 2.0)
    with h5py.File(tfs.write(tmp_path / "tf.h5")) as f:
        np.testing.assert_array_equal(f["IN1_per_EXC"][()], tfs.tf["IN1"])
        assert list(f.attrs["excited"]) == ["POS", "PIT", "YAW"]
    csv = np.genfromtxt(tfs.write(tmp_path / "tf.csv"), delimiter=",", names=True)
    np.testing.assert_allclose(csv["IN2_PIT_per_POS_re"], tfs.tf["IN2"][:, 1, 0].real)
    with pytest.raises(TFError, match="exists"):
        tfs.write(tmp_path / "tf.csv")


def test_bad_inputs_are_named(tmp_path: Path) -> None:
    bad = tmp_path / "bad.xml"
    bad.write_text("<not diaggui/>")
    with pytest.raises(TFError, match="bad.xml"):
        from_diaggui([bad])
    with pytest.raises(TFError, match="at least|expected one"):
        from_diaggui([REFERENCE / "real" / "H1_DARM_OLGTF_swept_sine_2020-01-03.xml"])
