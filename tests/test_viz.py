"""twind.viz: MCAP sessions as Rerun recordings, and the live view, read back with Rerun's
own .rrd reader."""

from __future__ import annotations

import functools
import io
import json
import threading
import time
import warnings
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
import zenoh

from twind.bus.codec import SampleBlock
from twind.bus.keys import control_key, data_key
from twind.bus.session import free_port, zenoh_config
from twind.cli import build_parser
from twind.config import load_config
from twind.errors import TwindError
from twind.recording.reader import read_session
from twind.recording.session import TruncatedRecordingWarning
from twind.recording.writer import SessionWriter
from twind.simulation.engine import Engine
from twind.viz import live
from twind.cli.view import cmd_rrd, cmd_view
from twind.viz.decimate import NS, Decimator
from twind.viz.entities import entity_path, matcher
from twind.viz.rerun_export import mcap_to_rrd

GPS0 = 1_400_000_000.0
F_EXC, AMP = 3.0, 0.5  # Hz, um at ETMX POS EXC
EXC_FROM, EXC_TO, DURATION = 2, 10, 12  # s


def read_rrd(path: Path) -> dict[str, list]:
    """Every chunk of the .rrd's recording, by entity path, as (timelines, record batch)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    assert len(reader.recordings()) == 1
    chunks: dict[str, list] = {}
    for chunk in reader.stream():
        chunks.setdefault(chunk.entity_path, []).append(chunk)
    return chunks


def column(chunks: list, name: str, static: bool = False) -> list:
    """One column of an entity's chunks; time columns as integer nanoseconds."""
    import pyarrow as pa

    out: list = []
    for chunk in chunks:
        batch = chunk.to_record_batch()
        if chunk.is_static != static or name not in batch.schema.names:
            continue
        col = batch.column(name)
        if pa.types.is_duration(col.type) or pa.types.is_timestamp(col.type):
            col = col.cast(pa.int64())
        out += col.to_pylist()
    return out


def since_gps0(ns: list) -> np.ndarray:
    """Seconds after GPS0 of a ``gps`` column."""
    return (np.array(ns, dtype=np.int64) - int(GPS0) * NS) / NS


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 s of ETMX with a 3 Hz sine on POS EXC from 2 s to 10 s, and its two events."""
    path = tmp_path_factory.mktemp("viz") / "session.mcap"
    twin = load_config(None, "ETMX")
    optics = twin.select("ETMX")
    rate = optics[0].sus.sample_rate_hz
    engine = Engine([o.loop() for o in optics], {o.name: o.noise for o in optics}, seed=5,
                    rate_hz=rate)
    n = int(rate)
    request = {"channel": "C1:SUS-ETMX_SUSPOS_EXC", "waveform": "sine", "freq": F_EXC,
               "amp": AMP, "duration": EXC_TO - EXC_FROM}
    with SessionWriter(path, twin.ifo, GPS0) as writer:
        writer.write_event({"event": "start", "id": "exc-1", "gps": GPS0 + 1.9,
                            "start_gps": GPS0 + EXC_FROM, "channel": request["channel"],
                            "request": request})
        for k in range(DURATION):
            exc = None
            if EXC_FROM <= k < EXC_TO:
                t = (k * n + np.arange(n)) / rate
                exc = np.zeros((1, 4, n))
                exc[0, 0] = AMP * np.sin(2 * np.pi * F_EXC * t)
            writer.write_block(engine.step(n, exc=exc))
        writer.write_event({"event": "end", "id": "exc-1", "gps": GPS0 + EXC_TO,
                            "start_gps": GPS0 + EXC_FROM, "channel": request["channel"],
                            "request": request})
    return path


def test_mcap_to_rrd_series_events_and_bode(session: Path, tmp_path: Path) -> None:
    rrd = tmp_path / "session.rrd"
    summary = mcap_to_rrd(session, rrd)
    assert summary.rate_hz == 256 and summary.events == 2
    assert summary.bode == ["bode/ETMX/POS/exc-1/IN1_EXC", "bode/ETMX/POS/exc-1/IN2_EXC"]
    chunks = read_rrd(rrd)

    series = {e for e in chunks if e.startswith("/sus/")}
    assert len(series) == 21  # 4 DOFs x EXC, IN1, IN2, OUT, and 5 OSEMs
    assert {"/sus/ETMX/POS/IN1", "/sus/ETMX/SIDE/OUT", "/sus/ETMX/OSEM/UL"} <= series
    for entity in series:
        values = column(chunks[entity], "Scalars:scalars")
        assert len(values) == DURATION * 256, entity
        assert summary.series[entity.lstrip("/")] == DURATION * 256
        assert all(c.timeline_names == ["gps", "utc"] for c in chunks[entity] if not c.is_static)
    names = column(chunks["/sus/ETMX/POS/IN1"], "SeriesLines:names", static=True)
    assert names == [["C1:SUS-ETMX_SUSPOS_IN1 [um]"]]

    # the decimated EXC is the sine, on GPS times corrected for the filter's delay
    t = since_gps0(column(chunks["/sus/ETMX/POS/EXC"], "gps"))
    exc = np.array(column(chunks["/sus/ETMX/POS/EXC"], "Scalars:scalars")).ravel()
    assert np.allclose(np.diff(t), 1 / 256, atol=1e-6)
    assert abs(t[0]) < 0.02
    utc = np.array(column(chunks["/sus/ETMX/POS/EXC"], "utc"), dtype=np.int64)
    gps_ns = np.array(column(chunks["/sus/ETMX/POS/EXC"], "gps"), dtype=np.int64)
    assert np.all(utc - gps_ns == (315964800 - 18) * NS)  # GPS epoch, leap seconds
    inside = (t > EXC_FROM + 0.5) & (t < EXC_TO - 0.5)
    expected = AMP * np.sin(2 * np.pi * F_EXC * t[inside])
    assert np.max(np.abs(exc[inside] - expected)) < 0.02 * AMP
    assert np.max(np.abs(exc[t < EXC_FROM - 0.2])) < 1e-12

    # events: the start and end of the excitation, and where its transfer functions are
    texts = column(chunks["/events"], "TextLog:text")
    assert len(texts) == 3
    assert any("start exc-1: sine on C1:SUS-ETMX_SUSPOS_EXC (freq 3.0 Hz" in t[0] for t in texts)
    assert any(t[0].startswith("end exc-1") for t in texts)
    assert any("bode/ETMX/POS/exc-1" in t[0] for t in texts)
    event_t = sorted(since_gps0(column(chunks["/events"], "gps")))
    assert event_t[0] == pytest.approx(EXC_FROM, abs=1e-6)

    # Bode: only POS was excited; at 3 Hz the measurement is the model's closed loop
    bode = {e for e in chunks if e.startswith("/bode/")}
    assert bode == {f"/bode/ETMX/POS/exc-1/{tf}/{leaf}" for tf in ("IN1_EXC", "IN2_EXC")
                    for leaf in ("magnitude_db", "phase_deg", "coherence")}
    model = load_config(None, "ETMX").select("ETMX")[0].loop().responses(np.array([F_EXC]))
    for tf, key in (("IN1_EXC", "closed_loop_IN1_per_EXC"), ("IN2_EXC", "closed_loop_IN2_per_EXC")):
        h = model[key][0, 0, 0]
        base = chunks[f"/bode/ETMX/POS/exc-1/{tf}/magnitude_db"]
        freqs = np.array([f / NS for f in column(base, "frequency_hz")])
        assert np.all((freqs > 0) & (freqs < 10))
        i = int(np.argmin(np.abs(freqs - F_EXC)))
        assert freqs[i] == pytest.approx(F_EXC, abs=1e-3)  # a bin on the tone
        mag = column(base, "Scalars:scalars")[i][0]
        phase = column(chunks[f"/bode/ETMX/POS/exc-1/{tf}/phase_deg"], "Scalars:scalars")[i][0]
        coh = column(chunks[f"/bode/ETMX/POS/exc-1/{tf}/coherence"], "Scalars:scalars")[i][0]
        assert mag == pytest.approx(20 * np.log10(abs(h)), abs=0.3), tf
        assert phase == pytest.approx(np.degrees(np.angle(h)), abs=2.0), tf
        assert coh > 0.99
    from rerun.chunk import RrdReader

    assert len(RrdReader(rrd).blueprints()) == 1  # the layout: a tab per optic, one of Bode


def test_rrd_command_selects_channels_and_never_overwrites(session: Path, tmp_path: Path) -> None:
    out = tmp_path / "pos.rrd"
    args = build_parser().parse_args(["rrd", str(session), "-o", str(out), "--channels",
                                      "C1:SUS-ETMX_SUSPOS_IN*,*_ULSEN_OUT", "--rate", "64",
                                      "--no-bode"])
    text = io.StringIO()
    with redirect_stdout(text):
        assert cmd_rrd(args) == 0
    assert f"wrote {out}: 3 channels at 64 Hz ({3 * DURATION * 64} points), 2 events, 0 " \
           "transfer functions" in text.getvalue()
    chunks = read_rrd(out)
    assert {e for e in chunks if e.startswith("/sus/")} == {
        "/sus/ETMX/POS/IN1", "/sus/ETMX/POS/IN2", "/sus/ETMX/OSEM/UL"}
    assert not any(e.startswith("/bode/") for e in chunks)
    with pytest.raises(TwindError, match="does not overwrite"):
        cmd_rrd(args)
    with pytest.raises(TwindError, match="no such file"):
        mcap_to_rrd(tmp_path / "missing.mcap", tmp_path / "x.rrd")


def test_decimator_is_continuous_across_blocks_and_restarts_on_gaps() -> None:
    rate = 16384.0
    x = np.random.default_rng(1).standard_normal(16384)
    whole = Decimator(rate, 256).feed(GPS0, x)
    pieces = Decimator(rate, 256)
    parts = [pieces.feed(GPS0 + a / rate, x[a:a + 1000]) for a in range(0, x.size, 1000)]
    assert np.allclose(np.concatenate([p.values for p in parts]), whole.values, atol=1e-12)
    assert np.array_equal(np.concatenate([p.gps_ns for p in parts]), whole.gps_ns)
    assert all(p.values.base is None for p in parts)  # copies: a view would pin the block
    assert whole.values.size == 256 and np.all(np.diff(whole.gps_ns) == NS // 256)
    # a constant decimates to itself from the first sample (the filter starts settled)
    settled = Decimator(rate, 256).feed(GPS0, np.full(4096, 2.5))
    assert np.allclose(settled.values, 2.5, atol=1e-9)
    # a gap of a block restarts the times at the new block
    dec = Decimator(rate, 256)
    dec.feed(GPS0, np.ones(1024))
    later = dec.feed(GPS0 + 1.0, np.ones(1024))
    assert abs(later.gps_ns[0] - int((GPS0 + 1.0) * NS)) < NS // 100
    same = Decimator(256, 256).feed(GPS0, np.arange(4.0))
    assert np.array_equal(same.values, np.arange(4.0))


def test_entity_paths_and_channel_patterns() -> None:
    assert entity_path("C1:SUS-ETMX_SUSPOS_IN1") == "sus/ETMX/POS/IN1"
    assert entity_path("C1:SUS-MC2_SUSSIDE_EXC") == "sus/MC2/SIDE/EXC"
    assert entity_path("C1:SUS-ITMY_SIDESEN_OUT") == "sus/ITMY/OSEM/SIDE"
    assert entity_path("C1:LSC-DARM_IN1") == "channels/C1_LSC-DARM_IN1"
    pick = matcher("C1:SUS-ETMX_*, *_EXC")
    assert pick("C1:SUS-ETMX_SUSPIT_OUT") and pick("C1:SUS-BS_SUSPOS_EXC")
    assert not pick("C1:SUS-BS_SUSPOS_IN1")
    assert matcher(None)("anything") and matcher("")("anything")


def test_view_streams_the_live_channels_into_a_recording(tmp_path: Path) -> None:
    """``twind view --save``: blocks published on Zenoh, decimated, in the .rrd with an event."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    twin = zenoh.open(zenoh_config(listen=[endpoint]))
    stop = threading.Event()
    channels = ("C1:SUS-ETMX_SUSPOS_IN1", "C1:SUS-ETMX_SUSPIT_IN1", "C1:SUS-ETMX_SUSPOS_EXC")

    events = twin.declare_publisher(control_key("C1", "events"))

    def publish() -> None:
        seq = 0
        sent = False
        while not stop.wait(0.01):
            gps = GPS0 + seq * 1024 / 16384
            for ch in channels:
                x = np.full(1024, float(seq))
                twin.put(data_key(ch), SampleBlock(ch, gps, 16384.0, seq, x, "um").encode())
            # once the viewer has subscribed: on a loaded machine it starts after block 20
            if seq >= 20 and not sent and events.matching_status.matching:
                sent = True
                events.put(json.dumps(
                    {"event": "start", "id": "exc-7", "gps": gps, "start_gps": gps + 0.0625,
                     "channel": channels[2], "request": {"waveform": "sine", "freq": 2.0}}))
            seq += 1

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    out = tmp_path / "live.rrd"
    args = build_parser().parse_args(["view", "--connect", endpoint, "--channels", "*_SUSPOS_*",
                                      "--rate", "64", "--duration", "2.5", "--save", str(out)])
    try:
        with redirect_stdout(io.StringIO()):
            assert cmd_view(args) == 0
    finally:
        stop.set()
        thread.join()
        twin.close()
    chunks = read_rrd(out)
    assert {e for e in chunks if e.startswith("/sus/")} == {"/sus/ETMX/POS/IN1",
                                                           "/sus/ETMX/POS/EXC"}
    values = np.array(column(chunks["/sus/ETMX/POS/IN1"], "Scalars:scalars")).ravel()
    t = since_gps0(column(chunks["/sus/ETMX/POS/IN1"], "gps"))
    assert values.size >= 40 * 4  # 1024 samples a block at 64 Hz: 4 points a block
    assert np.allclose(np.diff(t), 1 / 64, atol=1e-6)  # no gap: every block arrived
    texts = column(chunks["/events"], "TextLog:text")
    assert texts == [["start exc-7: sine on C1:SUS-ETMX_SUSPOS_EXC (freq 2.0 Hz)"]]
    with pytest.raises(TwindError, match="does not overwrite"):
        cmd_view(args)


def test_view_explains_what_to_do_without_a_display(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    parser = build_parser()
    with pytest.raises(TwindError, match="--viewer URL .* --web .* --save FILE.rrd"):
        cmd_view(parser.parse_args(["view", "--connect", "tcp/127.0.0.1:1"]))
    with pytest.raises(SystemExit):  # one sink at a time
        with redirect_stdout(io.StringIO()), pytest.MonkeyPatch.context() as m:
            m.setattr("sys.stderr", io.StringIO())
            parser.parse_args(["view", "--save", "a.rrd", "--web"])


def _events_on_disk(folder: Path) -> int:
    """Injection events a reader finds in the recording being written in `folder`."""
    files = sorted(folder.glob("*.mcap"))
    if not files:
        return 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TruncatedRecordingWarning)
        return len(read_session(files[0]).events)


def test_served_twin_viewed_live_and_its_recording_converted(tmp_path: Path) -> None:
    """``twind serve --record`` with ``twind view --save`` watching and an operator's sine:
    the live view has the channels and the event; the recording's .rrd has the Bode of the
    excitation, equal to the model's closed loop."""
    from servicekit import serving

    from twind.client import TwinClient

    folder = tmp_path / "rec"
    live_rrd = tmp_path / "live.rrd"
    with serving("--optics", "ETMX", "--speed", "4", "--record", str(folder)) as endpoint:
        args = build_parser().parse_args(["view", "--connect", endpoint, "--channels",
                                          "C1:SUS-ETMX_SUSPOS_*", "--duration", "3.5",
                                          "--save", str(live_rrd)])
        codes: list[int] = []
        subscribed = threading.Event()
        viewing = functools.partial(live.stream, subscribed=subscribed)
        with pytest.MonkeyPatch.context() as m:
            m.setattr("twind.cli.view.stream", viewing)
            viewer = threading.Thread(target=lambda: codes.append(cmd_view(args)))
            viewer.start()
            assert subscribed.wait(60), "the viewer never subscribed"
        with TwinClient(connect=[endpoint]) as twin:
            exc = twin.inject("C1:SUS-ETMX_SUSPOS_EXC", "sine", freq=F_EXC, amp=1.0, duration=8.0)
        viewer.join()
        assert codes == [0]
        with TwinClient(connect=[endpoint]) as twin:
            while any(e.id == exc for e in twin.status().excitations):
                time.sleep(0.2)
        deadline = time.monotonic() + 60  # a bound on a stuck test, not on the recorder
        while _events_on_disk(folder) < 2:  # the end event, on its way to the recorder
            assert time.monotonic() < deadline, "the recorder never wrote the end event"
            time.sleep(0.1)
    chunks = read_rrd(live_rrd)
    assert {e for e in chunks if e.startswith("/sus/")} == {
        f"/sus/ETMX/POS/{p}" for p in ("EXC", "IN1", "IN2", "OUT")}
    texts = [t[0] for t in column(chunks["/events"], "TextLog:text")]
    assert any(t.startswith(f"start {exc}: sine on C1:SUS-ETMX_SUSPOS_EXC") for t in texts)

    recording = sorted(folder.glob("*.mcap"))[0]
    summary = mcap_to_rrd(recording, tmp_path / "recorded.rrd", channels="*_SUSPOS_*")
    assert summary.events >= 2  # start and end
    assert f"bode/ETMX/POS/{exc}/IN1_EXC" in summary.bode
    chunks = read_rrd(tmp_path / "recorded.rrd")
    h = load_config(None, "ETMX").select("ETMX")[0].loop().responses(
        np.array([F_EXC]))["closed_loop_IN1_per_EXC"][0, 0, 0]
    base = chunks[f"/bode/ETMX/POS/{exc}/IN1_EXC/magnitude_db"]
    freqs = np.array([f / NS for f in column(base, "frequency_hz")])
    i = int(np.argmin(np.abs(freqs - F_EXC)))
    assert freqs[i] == pytest.approx(F_EXC, abs=1e-3)
    mag = column(base, "Scalars:scalars")[i][0]
    assert mag == pytest.approx(20 * np.log10(abs(h)), abs=0.5)
