"""Transfer functions from diaggui XML and MCAP sessions, and the recovered plant."""

from __future__ import annotations

import glob
import io
import json
from contextlib import redirect_stdout
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import REFERENCE
from measurekit import record_excited_session

from twind import DOFS
from twind.analysis.estimation.tf import from_diaggui, from_session, xml_transfer
from twind.analysis.estimation.tfset import _READERS, ReadOptions, TFError, TFSet, register_reader
from twind.analysis.estimation.welch import welch_tf
from twind.cli import main
from twind.config import load_config
from twind.errors import MeasurementWarning, TwindError
from twind.model.analytical import analytical_mechanics
from twind.model.plant import Plant

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
    f, h, g2, n = xml_transfer(REFERENCE / "H1_DARM_OLGTF_swept_sine_2020-01-03.xml",
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


@pytest.mark.slow
def test_session_plant_recovered_from_a_twin_recording(tmp_path: Path) -> None:
    """MCAP route: an engine run with one band-limited excitation per DOF, recorded with
    its injection events; the recovered plant equals the model's within the errors."""
    cfg = load_config(None, ["ETMX"]).optics["ETMX"]
    path = record_excited_session(cfg, tmp_path / "twin.mcap",
                                  {"POS": 2.0, "PIT": 5.0, "YAW": 5.0}, seconds=60)
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


@pytest.mark.slow
def test_session_lpm_errors_are_the_residuals_of_the_model(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture) -> None:
    """MCAP route, local polynomial method: over each 60 s excitation (windows of 0.25 Hz,
    wider than the 0.14 Hz POS resonance) IN1/EXC differs from the model, seen through
    the LPM's kernel, by its own errors: ``|z|^2 / 2`` averages F(2, 2q)'s mean."""
    from twind.analysis.identification.data import FitData
    from twind.analysis.identification.model import ClosedLoopModel

    cfg = load_config(None, ["ETMX"]).optics["ETMX"]
    path = record_excited_session(cfg, tmp_path / "twin.mcap",
                                  {"POS": 2.0, "PIT": 5.0, "YAW": 5.0}, seconds=60)
    tfs = from_session([path], estimator="lpm", max_hz=10.0)
    assert tfs.window == "lpm" and tfs.kernel is not None
    data = FitData.from_tfset(tfs, band=(0.3, 8.0))
    z = (data.H - ClosedLoopModel.of(cfg, data).for_data(data)({})) / data.sigma
    q = tfs.averages - 1
    powers = []
    for j in range(len(data.excited)):
        i = data.responses.index(data.excited[j])
        k = data.mask[:, i, j]
        assert k.sum() > 20, data.excited[j]
        powers.append(np.abs(z[k, i, j]) ** 2 / 2)
    # neighbouring bins share samples, so their mean scatters more than F's: over seeds 0-5
    # of this and the previous noise streams, the three DOFs' pooled mean over F's mean lay
    # in 0.79-1.15 (each DOF's alone in 0.59-1.78); errors off by a factor of 2 in variance
    # give 0.46 or 1.85
    ratio = np.mean(np.concatenate(powers)) / (q / (q - 1))
    assert 0.55 < ratio < 1.6, ratio

    out = io.StringIO()
    with redirect_stdout(out):
        assert main(["tf", str(path), "--estimator", "lpm", "--json", "--band", "0.3", "8"]) == 0
    obj = json.loads(out.getvalue())
    assert np.allclose(np.array(obj["sigma_IN1"]), tfs.band(0.3, 8).sigma("IN1"))
    capsys.readouterr()
    assert main(["tf", *NULL, "--estimator", "lpm"]) != 0
    assert "diaggui's Welch estimates only" in capsys.readouterr().err


def test_channels_joined_late_are_cut_by_their_own_start(tmp_path: Path) -> None:
    """A recorder that joins mid-stream can miss one channel's first block: each channel is
    cut by its own start time, so the TFs are those of a complete recording."""
    cfg = load_config(None, ["ETMX"]).optics["ETMX"]
    amps = {"POS": 2.0}
    whole = record_excited_session(cfg, tmp_path / "whole.mcap", amps, seconds=12)
    late = record_excited_session(cfg, tmp_path / "late.mcap", amps, seconds=12,
                                  late=("_IN2", "_OUT"))
    a = from_session([whole], bw=0.5, settle_s=1.0)
    b = from_session([late], bw=0.5, settle_s=1.0)
    np.testing.assert_allclose(b.tf["OUT"], a.tf["OUT"], rtol=1e-9, atol=1e-12)


def test_diaggui_files_written_by_twind_read_back_as_the_originals(tmp_path: Path) -> None:
    """example_null's POS measurement, rewritten from its own ASD, TFs and coherences, gives
    dttxml the same numbers (to float32, the file's precision)."""
    import dttxml

    from twind.analysis.estimation.diaggui import write_fft_measurement

    src = [p for p in NULL if p.endswith("POS_exc.xml")][0]
    acc = dttxml.DiagAccess(src)
    exc = "C1:SUS-ETMX_SUSPOS_EXC"
    chans = [f"C1:SUS-ETMX_SUS{d}_{p}" for d in DOFS for p in ("IN1", "IN2", "OUT")]
    got = [xml_transfer(acc, c, exc) for c in chans]
    out = write_fft_measurement(tmp_path / "ETMX_POS_exc.xml", exc, chans, got[0][0],
                                np.asarray(acc.asd(exc).asd, dtype=float) ** 2,
                                np.array([g[1] for g in got]), np.array([g[2] for g in got]),
                                got[0][3], rate_hz=256.0)
    a, b = from_diaggui([src]), from_diaggui([out])
    assert b.averages == a.averages == 10
    for p in ("IN1", "IN2", "OUT"):
        np.testing.assert_allclose(b.tf[p], a.tf[p], rtol=1e-6, atol=1e-30)
        np.testing.assert_allclose(b.coherence[p], a.coherence[p], rtol=1e-6)
    with pytest.raises(TFError, match="exists"):
        write_fft_measurement(out, exc, chans, got[0][0], np.ones(len(got[0][0])),
                              np.zeros((len(chans), len(got[0][0]))),
                              np.zeros((len(chans), len(got[0][0]))), 10)


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


def test_results_written_for_matlab(tmp_path: Path) -> None:
    import scipy.io

    tfs = from_diaggui(NULL).band(0.5, 2.0)
    assert main(["tf", *NULL, "--band", "0.5", "2", "-o", str(tmp_path / "tf.mat")]) == 0
    m = scipy.io.loadmat(tmp_path / "tf.mat")
    assert m["IN1_per_EXC"].shape == (len(tfs.frequency_hz), 4, 3)
    np.testing.assert_array_equal(m["IN2_per_EXC"], tfs.tf["IN2"])
    np.testing.assert_array_equal(m["frequency_hz"].ravel(), tfs.frequency_hz)
    P, _ = tfs.plant()
    np.testing.assert_allclose(m["plant"], P)
    g2 = tfs.coherence["IN1"]
    np.testing.assert_allclose(m["SNR_IN1"], g2 / (1 - g2))
    assert [str(c[0]) for c in m["EXC_channels"].ravel()] == [
        "C1:SUS-ETMX_SUSPOS_EXC", "C1:SUS-ETMX_SUSPIT_EXC", "C1:SUS-ETMX_SUSYAW_EXC"]
    assert str(m["OUT_channels"].ravel()[3][0]) == "C1:SUS-ETMX_SUSSIDE_OUT"
    with pytest.raises(TFError, match="exists"):
        tfs.write(tmp_path / "tf.mat")


def test_bad_inputs_are_named(tmp_path: Path) -> None:
    bad = tmp_path / "bad.xml"
    bad.write_text("<not diaggui/>")
    with pytest.raises(TFError, match="bad.xml"):
        from_diaggui([bad])


@pytest.mark.parametrize(("n", "nperseg", "overlap"),
                         [(40000, 1000, 0.5), (30001, 777, 0.3), (50000, 4096, 0.75),
                          (20000, 2000, 0.0), (9999, 1001, 0.5)])
def test_welch_tfs_equal_scipy_csd_welch_coherence(n: int, nperseg: int, overlap: float) -> None:
    """One FFT per segment and signal gives scipy.signal's four estimates (to 1e-10),
    for even and odd segments, with and without overlap, a DC offset, and two threads."""
    from scipy import signal

    from twind.analysis.estimation.tf import welch_tfs

    rng = np.random.default_rng(n)
    x = rng.standard_normal(n) + 3.0
    ys = [signal.lfilter([0.3, 0.2], [1, -0.5], x) + 0.1 * rng.standard_normal(n),
          5.0 * rng.standard_normal(n) - 2.0]
    kw = {"fs": 512.0, "window": "hann", "nperseg": nperseg, "noverlap": int(nperseg * overlap)}
    for workers in (1, 2):
        psd = np.empty(nperseg // 2 + 1)
        f, h, g2, avg = welch_tfs(x, ys, 512.0, nperseg, overlap, workers=workers, psd=psd)
        for i, y in enumerate(ys):
            f0, pxy = signal.csd(x, y, **kw)
            _, pxx = signal.welch(x, **kw)
            _, coh = signal.coherence(x, y, **kw)
            np.testing.assert_allclose(psd, pxx, rtol=1e-10)
            np.testing.assert_array_equal(f, f0)
            np.testing.assert_allclose(h[i], pxy / pxx, rtol=1e-10)
            np.testing.assert_allclose(g2[i], coh, rtol=1e-10)
        assert avg == 1 + (n - nperseg) // (nperseg - int(nperseg * overlap))


def test_the_virtual_measurements_in2_is_its_in1_plus_exc() -> None:
    """measure_tfs derives IN2's column from IN1's (IN2 = IN1 + EXC); the direct Welch
    estimate of IN2 agrees to rounding, on the excited DOF and on the others."""
    from scipy import signal

    from twind.analysis.estimation.tf import welch_tfs
    from twind.commissioning.measurement import _welch_column

    rng = np.random.default_rng(7)
    n, nperseg = 40000, 2000
    x = rng.standard_normal(n)
    in1 = [signal.lfilter([0.3, -0.2], [1, -0.6], x) * (j + 1) + rng.standard_normal(n)
           for j in range(len(DOFS))]
    in1[3] = rng.standard_normal(n)  # SIDE: no coherence with the drive at all
    outs = [signal.lfilter([1.0], [1, 0.3], y) for y in in1]
    ys = [y for pair in zip(in1, outs, strict=True) for y in pair]
    _, h, g2, _ = welch_tfs(x, ys, 512.0, nperseg)
    for excited in ("POS", "YAW"):
        column = _welch_column(h, g2, excited)
        in2 = [y + x if d == excited else y for d, y in zip(DOFS, in1, strict=True)]
        _, h2, c2, _ = welch_tfs(x, in2, 512.0, nperseg)
        for j, d in enumerate(DOFS):
            np.testing.assert_allclose(column[(d, "IN2")][0], h2[j], rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(column[(d, "IN2")][1], c2[j], rtol=1e-9, atol=1e-12)
            np.testing.assert_array_equal(column[(d, "OUT")][0], h[2 * j + 1])


def test_fast_reader_equals_read_session(tmp_path: Path) -> None:
    """read_channels gives read_session's channels, events and configuration."""
    from twind.lab.tf_speed import session_channels, write_session
    from twind.recording.fastread import read_channels
    from twind.recording.reader import read_session

    path = write_session(tmp_path / "s.mcap", duration=6.0)
    names = session_channels()
    slow, fast = read_session(path, names), read_channels(path, names)
    assert list(fast.channels) == names and fast.events == slow.events
    assert fast.configs == slow.configs and fast.complete and not fast.problems
    for name in names:
        a, b = slow[name], fast[name]
        np.testing.assert_array_equal(a.samples, b.samples)
        np.testing.assert_array_equal(a.sequences, b.sequences)
        np.testing.assert_array_equal(a.gps_starts, b.gps_starts)
        assert (a.unit, a.rate, a.t0, a.gaps) == (b.unit, b.rate, b.t0, b.gaps)
    exc = read_channels(path, lambda n: n.endswith("_EXC"))
    assert list(exc.channels) == [n for n in names if n.endswith("_EXC")]


@pytest.mark.slow
def test_tf_benchmark_runs_end_to_end(tmp_path: Path) -> None:
    """``twind bench --suite tf`` machinery on 60 s: a session written, timed in process and
    as the CLI, and removed unless kept."""
    from twind.lab.tf_speed import run_tf_benchmark

    res = run_tf_benchmark(60.0, workdir=tmp_path, echo=False)
    assert res.channels == 12 and res.in_process_s > 0 and res.cli_s > 0
    assert res.target_s == pytest.approx(20.0 / 60)
    assert not list(tmp_path.glob("*.mcap"))
    out = io.StringIO()
    with redirect_stdout(out):
        assert main(["bench", "--suite", "tf", "--duration", "60", "--workdir",
                     str(tmp_path), "--keep"]) == 0
    assert "x the" in out.getvalue() and len(list(tmp_path.glob("*.mcap"))) == 1


# --- Welch sums taken while reading ---------------------------------------------------------

RATE, BLOCK = 1024.0, 64
GPS_START = 1_400_000_000.0


def _small_session(path: Path, seconds: float, stop: tuple[float, float] | None = None,
                   gap: int | None = None) -> Path:
    """POS excited with noise at 1024 Hz; `stop` = (GPS offset of a stop event, offset of the
    data it is recorded among); `gap` drops one IN1 block."""
    from twind.bus.codec import SampleBlock
    from twind.recording.writer import McapSession

    rng = np.random.default_rng(1)
    n = int(seconds * RATE) // BLOCK
    exc = rng.standard_normal(n * BLOCK)
    b, a = signal_butter()
    resp = {"IN1": lfilter(b, a, exc), "IN2": -0.5 * lfilter(b, a, exc), "OUT": exc.copy()}
    start = {"event": "start", "id": "e1", "gps": GPS_START, "start_gps": GPS_START,
             "channel": "C1:SUS-ETMX_SUSPOS_EXC",
             "request": {"waveform": "noise", "duration": n * BLOCK / RATE}}
    with McapSession(path, "C1", {"optics": ["ETMX"]}, chunk_bytes=16 * 1024) as f:
        f.write_event(start)
        for seq in range(n):
            gps = GPS_START + seq * BLOCK / RATE
            if stop and abs(gps - GPS_START - stop[1]) < 0.5 * BLOCK / RATE:
                f.write_event({"event": "stop", "id": "e1", "gps": GPS_START + stop[0]})
            cut = slice(seq * BLOCK, (seq + 1) * BLOCK)
            for point, x in [("EXC", exc), *resp.items()]:
                if point == "IN1" and seq == gap:
                    continue
                noise = 0.0 if point == "EXC" else 0.1 * rng.standard_normal(BLOCK)
                name = f"C1:SUS-ETMX_SUSPOS_{point}"
                f.write_block(SampleBlock(name, gps, RATE, seq, x[cut] + noise, "um").encode())
        f.write_event({**start, "event": "end", "gps": GPS_START + n * BLOCK / RATE})
    return path


def signal_butter():  # noqa: ANN201
    from scipy import signal

    return signal.butter(2, 0.1)


def lfilter(b, a, x):  # noqa: ANN001, ANN201
    from scipy import signal

    return signal.lfilter(b, a, x)


def _read_whole(monkeypatch: pytest.MonkeyPatch, path: Path, **kw):  # noqa: ANN202
    import twind.analysis.estimation.tf as tf

    with monkeypatch.context() as m:
        m.setattr(tf, "_streamed", lambda *a, **k: None)
        return tf.from_session([path], **kw)


def _assert_same(a, b) -> None:  # noqa: ANN001
    assert (a.excited, a.responses, a.averages) == (b.excited, b.responses, b.averages)
    np.testing.assert_array_equal(a.frequency_hz, b.frequency_hz)
    for p in ("IN1", "IN2", "OUT"):
        np.testing.assert_allclose(a.tf[p], b.tf[p], rtol=1e-12)
        np.testing.assert_allclose(a.coherence[p], b.coherence[p], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("window", ["hann", "boxcar"])
def test_sums_taken_while_reading_equal_reading_whole(tmp_path: Path, window: str,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The Welch sums taken while the file is read are those of the samples read whole,
    with settling skipped and a stop recorded on time."""
    from twind.analysis.estimation.tf import _streamed

    path = _small_session(tmp_path / "s.mcap", 120.0, stop=(100.0, 100.0))
    streamed = _streamed([path], 0.5, 0.5, None, window, 3.0)
    assert streamed is not None  # the stream was used, not the fallback
    whole = _read_whole(monkeypatch, path, bw=0.5, window=window, settle_s=3.0)
    assert whole.averages == 1 + (97 * 1024 - 2048) // 1024
    _assert_same(streamed, whole)
    _assert_same(from_session([path], bw=0.5, window=window, settle_s=3.0), whole)


def test_a_late_stop_or_a_gap_reads_the_recording_whole(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A stop event recorded 30 s after its time (past the stream's lag) or a lost block: the
    sums taken while reading are not the right ones, and from_session says so by reading the
    file whole, with the same answer as that path."""
    from twind.analysis.estimation.tf import _streamed
    from twind.analysis.estimation.welch import LAG_S
    from twind.recording.session import GapWarning

    late = _small_session(tmp_path / "late.mcap", 120.0, stop=(60.0, 60.0 + 3 * LAG_S))
    assert _streamed([late], 0.5, 0.5, None, "hann", 0.0) is None
    whole = _read_whole(monkeypatch, late, bw=0.5)
    assert whole.averages == 1 + (60 * 1024 - 2048) // 1024
    _assert_same(from_session([late], bw=0.5), whole)
    gappy = _small_session(tmp_path / "gap.mcap", 60.0, gap=100)
    with pytest.warns(GapWarning):
        assert _streamed([gappy], 0.5, 0.5, None, "hann", 0.0) is None
        assert from_session([gappy], bw=0.5).averages == 1 + (60 * 1024 - 2048) // 1024


def test_the_stream_keeps_a_few_segments_of_samples(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Memory: the samples held while reading stay at a few segments (plus the lag, the
    history kept for late start events and a batch of chunks), however long the recording."""
    from twind.analysis.estimation.tf import _exc, _Plan, _segments
    from twind.analysis.estimation.welch import HISTORY_S, LAG_S, WelchStream
    from twind.recording import fastread

    path = _small_session(tmp_path / "long.mcap", 600.0)
    # a batch is a few MB: seconds of twelve 16 kHz channels, minutes of these four at 1 kHz
    batch_s = 2.0
    monkeypatch.setattr(fastread, "_BATCH_BYTES", int(batch_s * 4 * RATE * 8))

    def planner(events, extents):  # noqa: ANN001, ANN202
        return {k: _Plan.of(k, s, e, extents, 0.0).segment
                for k, (s, e) in _segments(events, RATE).items() if _exc(k) in extents}

    stream = WelchStream(planner, bw=0.5)
    fastread.stream_channels([path], lambda n: "SUSPOS" in n, stream)
    assert stream.result() is not None and len(stream.tails) == 4
    # a channel holds at most the history, or a segment, the lag, the look interval, a batch
    seconds = max(HISTORY_S, 2.0 + LAG_S) + 8.0 + batch_s
    assert max(t.peak for t in stream.tails.values()) <= 2 * seconds * RATE < 600 * RATE / 4


def test_non_finite_bins_are_named_left_out_and_written_as_null(tmp_path: Path,
                                                                capsys) -> None:  # noqa: ANN001
    """example_null's POS file with ten NaN bins in PIT's IN1: ``tf`` says which channel and
    how many, and its JSON (standard JSON, no bare NaN) has null there."""
    import dttxml

    from twind.analysis.estimation.diaggui import write_fft_measurement

    src = [p for p in NULL if p.endswith("POS_exc.xml")][0]
    acc = dttxml.DiagAccess(src)
    exc = "C1:SUS-ETMX_SUSPOS_EXC"
    chans = [f"C1:SUS-ETMX_SUS{d}_{p}" for d in DOFS for p in ("IN1", "IN2", "OUT")]
    got = [xml_transfer(acc, c, exc) for c in chans]
    tf = np.array([g[1] for g in got])
    tf[chans.index("C1:SUS-ETMX_SUSPIT_IN1"), 10:20] = np.nan
    out = write_fft_measurement(tmp_path / "ETMX_POS_exc.xml", exc, chans, got[0][0],
                                np.asarray(acc.asd(exc).asd, dtype=float) ** 2, tf,
                                np.array([g[2] for g in got]), got[0][3], rate_hz=256.0)
    assert main(["tf", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    assert (f"twind: warning: {out}: C1:SUS-ETMX_SUSPIT_IN1/{exc}: 10 of {len(got[0][0])} "
            "bins are NaN or inf and are left out") in captured.err

    def no_nan(word: str) -> None:
        raise AssertionError(f"{word} is not JSON")

    obj = json.loads(captured.out, parse_constant=no_nan)
    pit = obj["responses"].index("PIT")
    assert all(obj["IN1_per_EXC"]["re"][k][pit][0] is None for k in range(10, 20))


def test_the_coherent_band_is_where_some_excited_dof_is_coherent() -> None:
    """What ``twind tf`` keeps of a recording by default: no excited DOF's IN1 is driven by
    its EXC outside it, and a threshold no bin meets gives no band."""
    tfs = from_diaggui(NULL)
    lo, hi = tfs.coherent_band()
    f = tfs.frequency_hz
    assert f[0] <= lo < hi <= f[-1]
    rows = [tfs.responses.index(d) for d in tfs.excited]
    driven = tfs.coherent()[:, rows, np.arange(len(rows))]
    outside = (f < lo) | (f > hi)
    assert not driven[outside].any() and driven[f == lo].any()
    g2 = tfs.coherence["IN1"][:, rows, np.arange(len(rows))]
    assert (g2[driven] >= 0.5).all() and (g2[~driven] < 0.9).all()
    assert tfs.coherent_band(at_least=2.0) is None


def test_noise_over_few_averages_is_not_taken_for_a_driven_band() -> None:
    """Three averages, 200 000 bins: undriven bins pass 0.5 a quarter of the time (their
    coherence is Beta(1, 2)); only the driven band counts."""
    tfs = from_diaggui(NULL)
    f = 0.01 * np.arange(200_000)
    shape = (f.size, *tfs.coherence["IN1"].shape[1:])
    rng = np.random.default_rng(1)
    g2 = rng.beta(1, 2, shape)
    g2[100:1000] = 0.999999
    noisy = replace(tfs, frequency_hz=f, averages=3,
                    tf={k: np.ones(shape, complex) for k in tfs.tf},
                    coherence={k: g2 for k in tfs.coherence})
    assert (g2[1000:] >= 0.5).any()
    assert noisy.coherent_band() == (f[100], f[999])


def test_an_excitation_too_short_for_the_resolution_says_which_would_do(tmp_path: Path) -> None:
    cfg = load_config(None, "ETMX").optics["ETMX"]
    path = record_excited_session(cfg, tmp_path / "short.mcap", {"POS": 1.0}, seconds=12)
    with pytest.raises(TFError, match=r"less than 1/bw = 100 s \(--bw, default 0\.01 Hz\); "
                                      r"--bw 0\.1 needs 10 s"):
        from_session([path], bw=0.01)


def test_events_no_twin_sends_are_left_out_with_a_warning() -> None:
    """A start without its channel (a forged or careless message recorded before the recorder
    checked events) is left out, said once, and the excitation beside it still read."""
    from twind.analysis.estimation.tf import _segments

    good = {"event": "start", "id": "e1", "channel": "C1:SUS-ETMX_SUSPOS_EXC",
            "gps": 1e9, "start_gps": 1e9, "request": {"duration": 10.0}}
    forged = [{"event": "start", "id": "e2", "gps": 1e9, "start_gps": 1e9},
              {"event": "stop", "id": "e1", "channel": good["channel"], "start_gps": 1e9,
               "gps": 1e300}]
    with pytest.warns(MeasurementWarning, match="2 event.s. in the recording left out"):
        segments = _segments([good, *forged])
    assert segments == {("C1", "ETMX", "POS"): (1e9, 1e9 + 10.0)}


def test_one_way_in_finds_the_format_by_its_registered_identifier(tmp_path: Path) -> None:
    """``TFSet.read`` picks the reader whose identifier takes the files (diaggui XML here,
    the same set as its reader's), refuses a mix naming every registered format, and takes a
    format registered later, as gwpy's registry does."""
    via_registry = TFSet.read(NULL)
    direct = from_diaggui(NULL)
    _assert_same(via_registry, direct)
    with pytest.raises(TwindError, match="estimator lpm needs the time series"):
        TFSet.read(NULL, ReadOptions(estimator="lpm"))
    other = tmp_path / "x.csv"
    other.write_text("1,2\n")
    with pytest.raises(TFError, match=r"all diaggui \.xml or all \.mcap or all HDF5"):
        TFSet.read([NULL[0], other])
    register_reader("csv-test", ".csv", lambda ps: all(p.suffix == ".csv" for p in ps),
                    lambda ps, options: direct)
    try:
        assert TFSet.read([other]) is direct
    finally:
        _READERS.pop("csv-test")
