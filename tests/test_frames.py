"""Recordings of the lab's data system: gwpy HDF5 files and GWF frames with ``_DQ`` names at
their own rates and no injection events, and MCAP sessions without events. Each is made from
one twin measurement (the engine's, recorded with its events) so that the route through the
events is the truth the others must give."""

from __future__ import annotations

import io
import json
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
from gwpy.timeseries import TimeSeries, TimeSeriesDict
from scipy import signal

from twind.analysis.estimation.excitations import found, recognise
from twind.analysis.estimation import tf
from twind.analysis.estimation.tf import from_session
from twind.analysis.estimation.tfset import TFError
from twind.cli import main
from twind.config import NOMINAL_ETMX, load_optic
from twind.excitation.request import ExcitationRequest
from twind.excitation.waveforms import make_waveform
from twind.commissioning.measurement import record_measurement
from twind.model.effects import CATALOGUE
from twind.recording.fastread import event_count
from twind.recording.frames import read_frames, renamer
from twind.recording.reader import getdata, read_session
from twind.recording.session import RecordingError

BW = 0.25
GPS = 1.4e9
EXC_RATE, DQ_RATE = 2048, 4096  # the data system's rates of EXC and of the other points
MAP = {"C2:": "C1:"}  # the files' IFO prefix is another's


@pytest.fixture(scope="module")
def etmx():  # noqa: ANN201
    return load_optic(NOMINAL_ETMX)


@pytest.fixture(scope="module")
def recorded(etmx, tmp_path_factory):  # noqa: ANN001, ANN201
    """One measurement, with and without its injection events, and as HDF5 and GWF."""
    d = tmp_path_factory.mktemp("frames")
    kw = {"bw": BW, "averages": 10, "rms": 3.0, "seed": 5, "gps_start": GPS}
    events = record_measurement(etmx, d / "events.mcap", **kw)
    bare = record_measurement(etmx, d / "bare.mcap", events=False, **kw)
    data = TimeSeriesDict()
    for name, ch in read_session(bare).channels.items():
        q = int(ch.rate // (EXC_RATE if name.endswith("_EXC") else DQ_RATE))
        stored = f"{name.replace('C1:', 'C2:')}_DQ"
        data[stored] = TimeSeries(signal.resample_poly(ch.samples, 1, q), t0=ch.t0,
                                  sample_rate=ch.rate / q, name=stored, channel=stored)
    data.write(str(d / "dq.h5"))
    data.write(str(d / "dq.gwf"))
    TimeSeriesDict({k: v for k, v in data.items() if "_EXC_" not in k}).write(
        str(d / "no_exc.h5"))
    return {"events": events, "bare": bare, "h5": d / "dq.h5", "gwf": d / "dq.gwf",
            "no_exc": d / "no_exc.h5", "written": data}


def _tf_json(*args: str) -> dict:
    out = io.StringIO()
    with redirect_stdout(out):
        assert main(["tf", *args, "--bw", str(BW), "--json", "--band", "0.3", "8"]) == 0
    return json.loads(out.getvalue())


@pytest.mark.parametrize("kind", ["h5", "gwf"])
@pytest.mark.slow
def test_hdf5_and_frames_give_the_tfs_of_the_mcap_route(recorded, kind: str,  # noqa: ANN001
                                                        capsys) -> None:  # noqa: ANN001
    truth = _tf_json(str(recorded["events"]))
    got = _tf_json(str(recorded[kind]), "--map", "C2:=C1:")
    said = capsys.readouterr().err
    assert "resampled to 2048 Hz" in said and "C1:SUS-ETMX_SUSPOS_IN1 (4096 Hz)" in said
    assert said.count("excitation found in the data") == 3
    assert got["excited"] == truth["excited"] == ["POS", "PIT", "YAW"]
    assert np.allclose(got["frequency_hz"], truth["frequency_hz"])
    h = np.array(got["IN1_per_EXC"]["re"]) + 1j * np.array(got["IN1_per_EXC"]["im"])
    h0 = np.array(truth["IN1_per_EXC"]["re"]) + 1j * np.array(truth["IN1_per_EXC"]["im"])
    sigma = np.array(truth["sigma_IN1"])
    coherent = np.array(truth["coherence_IN1"]) > 0.5
    # the same noise, resampled: differences far inside the errors
    assert coherent.sum() > 50
    assert np.max(np.abs(h - h0)[coherent] / sigma[coherent]) < 0.2


def test_an_exc_not_recorded_is_in2_less_in1(recorded, capsys) -> None:  # noqa: ANN001
    """A filter module's IN2 is its IN1 plus its EXC: without the EXC channels the file
    gives the TFs of the MCAP route as well, the excitations found in IN2 - IN1."""
    truth = _tf_json(str(recorded["events"]))
    got = _tf_json(str(recorded["no_exc"]), "--map", "C2:=C1:")
    said = capsys.readouterr().err
    assert "not recorded, taken as IN2 - IN1: C1:SUS-ETMX_SUSPIT_EXC" in said, said
    assert said.count("excitation found in the data") == 3
    assert got["excited"] == truth["excited"]
    h = np.array(got["IN1_per_EXC"]["re"]) + 1j * np.array(got["IN1_per_EXC"]["im"])
    h0 = np.array(truth["IN1_per_EXC"]["re"]) + 1j * np.array(truth["IN1_per_EXC"]["im"])
    coherent = np.array(truth["coherence_IN1"]) > 0.5
    z = np.abs(h - h0)[coherent] / np.array(truth["sigma_IN1"])[coherent]
    assert coherent.sum() > 50 and np.max(z) < 0.2


def test_files_with_their_own_channels_are_read_as_what_they_are(recorded, tmp_path: Path,
                                                                  capsys) -> None:  # noqa: ANN001
    """A data-system export of three measurements, a file each, each file with only its own
    excitation's EXC and the last second of each cut out: the TFs of the MCAP route (but
    for the last segment of each excitation)."""
    events = [e for e in read_session(recorded["events"]).events if e.get("event") == "start"]
    starts = sorted(float(e["start_gps"]) for e in events)
    ends = [*starts[1:], None]
    paths = []
    for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
        own = [n for n in recorded["written"] if "_EXC_" not in n
               or n.startswith(f"C2:SUS-ETMX_SUS{('POS', 'PIT', 'YAW')[k]}_EXC")]
        piece = TimeSeriesDict({n: recorded["written"][n].crop(a, b and b - 1) for n in own})
        paths.append(tmp_path / f"m{k}.h5")
        piece.write(str(paths[-1]))
    truth = _tf_json(str(recorded["events"]))
    got = _tf_json(*map(str, paths), "--map", "C2:=C1:")
    assert got["excited"] == truth["excited"] == ["POS", "PIT", "YAW"]
    h = np.array(got["IN1_per_EXC"]["re"]) + 1j * np.array(got["IN1_per_EXC"]["im"])
    h0 = np.array(truth["IN1_per_EXC"]["re"]) + 1j * np.array(truth["IN1_per_EXC"]["im"])
    coherent = np.array(truth["coherence_IN1"]) > 0.5
    z = np.abs(h - h0)[coherent] / np.array(truth["sigma_IN1"])[coherent]
    assert coherent.sum() > 50 and np.median(z) < 0.2, np.median(z)
    one = from_session([paths[0]], bw=BW, mapping=MAP)
    with pytest.raises(TFError, match="POS is excited in both a.h5 and b.h5"):
        tf.merged([one, one], ["a.h5", "b.h5"])


@pytest.mark.slow
def test_a_session_without_events_finds_the_segments_the_engine_used(
        recorded, etmx, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    rate = etmx.sus.sample_rate_hz
    session = read_session(recorded["bare"])
    assert session.events == []
    stretches = found(session.channels)
    # record_measurement's: each DOF in turn, whole engine blocks of settling and averages
    span = next(iter(stretches.values())).end - GPS
    for k, dof in enumerate(["POS", "PIT", "YAW"]):
        s = stretches[("C1", "ETMX", dof)]
        assert abs(s.start - (GPS + k * span)) < 1 / rate
        assert abs(s.end - (GPS + (k + 1) * span)) < 1 / rate
        assert s.waveform == "noise", s
    events = [e for e in read_session(recorded["events"]).events if e["event"] == "start"]
    assert [e["start_gps"] for e in events] == pytest.approx(
        [stretches[("C1", "ETMX", d)].start for d in ["POS", "PIT", "YAW"]], abs=1 / rate)
    assert (event_count(recorded["bare"]), event_count(recorded["events"])) == (0, 6)
    with monkeypatch.context() as m:  # read once, whole: not streamed first to no end
        m.setattr(tf, "stream_channels", lambda *a, **k: pytest.fail("streamed"))
        bare = from_session([recorded["bare"]], bw=BW)
    truth = from_session([recorded["events"]], bw=BW)
    assert len(bare.found) == 3
    assert np.allclose(bare.tf["IN1"], truth.tf["IN1"], equal_nan=True)
    by_hand = from_session([recorded["bare"]], bw=BW, exc_times={
        d: (s.start, s.end) for (_, _, d), s in stretches.items()})
    assert np.allclose(by_hand.tf["IN1"], truth.tf["IN1"], equal_nan=True)


@pytest.mark.parametrize("kind", ["h5", "gwf"])
@pytest.mark.slow
def test_diagnose_runs_on_the_data_systems_files(recorded, kind: str,  # noqa: ANN001
                                                 capsys) -> None:  # noqa: ANN001
    assert main(["diagnose", str(recorded[kind]), "--map", "C2:=C1:", "--bw", str(BW),
                 "--band", "0.3", "8", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    # the nominal optic measured: its nominal model fits, nothing is claimed (at this 0.25 Hz
    # resolution only with the damped modes seen through the Hann kernel), every hypothesis
    # is weighed
    assert 0.5 < out["chi2_nu_nominal"] < 1.5, out["summary"]
    assert out["consistent"] and not out["effects"], out["summary"]
    assert set(CATALOGUE) <= set(out["p_values"]) | {x["effect"] for x in out["not_fitted"]}


@pytest.mark.parametrize(("waveform", "kw", "tones"), [
    ("sine", {"freq": 3.3}, [3.3]),
    ("sine", {"freq": 0.2}, [0.2]),
    ("multisine", {"freqs": (0.5, 1.1, 2.3, 7.7)}, [0.5, 1.1, 2.3, 7.7]),
    ("sweep", {"freq": 0.1, "f_stop": 30.0}, []),
    ("noise", {}, []),
])
def test_waveforms_are_recognised(waveform: str, kw: dict, tones: list) -> None:
    rate = 16384.0
    req = ExcitationRequest("C1:SUS-ETMX_SUSPOS_EXC", waveform, amp=1.0, duration=40.0, **kw)
    x = make_waveform(req, rate).next(int(40 * rate))
    kind, found_tones = recognise(x, rate)
    assert kind == {"sweep": "swept sine"}.get(waveform, waveform)
    # a multisine's tones fall on its period's grid, within 0.02 Hz of those asked for
    assert np.allclose(found_tones, tones, atol=0.02)


def test_getdata_reads_the_same_files(recorded) -> None:  # noqa: ANN001
    name = "C1:SUS-ETMX_SUSPIT_IN1"
    written = recorded["written"][f"{name.replace('C1:', 'C2:')}_DQ"].crop(GPS + 5, GPS + 15)
    for path in (recorded["h5"], recorded["gwf"]):
        b = getdata(name, 10.0, GPS + 5, source=[path], mapping=MAP)[name]
        assert np.array_equal(np.asarray(b.value), np.asarray(written.value))
        assert float(b.t0.value) == GPS + 5
    a = getdata(name, 10.0, GPS + 5, source=str(recorded["bare"]))[name]
    assert (len(a.value), float(a.t0.value)) == (10 * 16384, GPS + 5)  # the MCAP route too


def test_bad_inputs_are_named(recorded, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5")
    with pytest.raises(RecordingError, match="not readable as hdf5"):
        read_frames([junk])
    with pytest.raises(RecordingError, match="not a mixture"):
        read_frames([recorded["h5"], recorded["gwf"]])
    with pytest.raises(RecordingError, match="none of its channels"):
        read_frames([recorded["h5"]], lambda name: name.startswith("C1:"))
    assert renamer({"C2:SUS-": "C1:SUS-", "C2:": "X1:"})("C2:SUS-A_DQ") == "C1:SUS-A"
    assert main(["tf", str(recorded["h5"]), "--map", "C2"]) != 0
    assert "RECORDED=TWIN" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["tf", str(recorded["h5"]), "--exc-times", "POS:5:1"])
    assert "DOF:START:END" in capsys.readouterr().err

    rate = 2048.0
    t = np.arange(int(rate * 20)) / rate
    quiet = TimeSeriesDict()
    for point in ("EXC", "IN1", "IN2", "OUT"):
        name = f"C1:SUS-ETMX_SUSPOS_{point}_DQ"
        x = np.sin(2 * np.pi * 1.0 * t) if point == "EXC" else np.cos(t)
        quiet[name] = TimeSeries(x, t0=GPS, sample_rate=rate, name=name, channel=name)
    quiet.write(str(tmp_path / "sine.h5"))
    with pytest.raises(TFError, match="Hz sine after settling: 10 blocks of 2 cycles need"):
        from_session([tmp_path / "sine.h5"])
    with pytest.raises(TFError, match="no EXC channel of that DOF"):
        from_session([tmp_path / "sine.h5"], exc_times={"PIT": (GPS, GPS + 10)})
    for name in quiet:
        quiet[name] = quiet[name] * 0
    quiet.write(str(tmp_path / "zero.h5"), overwrite=True)
    with pytest.raises(TFError, match="no excitation found"):
        from_session([tmp_path / "zero.h5"])
