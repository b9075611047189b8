"""Recording, reading, exporting and replaying sessions (MCAP), all on loopback.

Every test that uses Zenoh picks a free TCP port; the test's session listens on it and the
recorder or replayer connects, with multicast scouting off.
"""

from __future__ import annotations

import json
import math
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory
from mcap_reference import reference_session
from servicekit import free_port

from twind.bus.codec import SampleBlock
from twind.bus.keys import control_key
from twind.bus.session import zenoh_config
from twind.channels import block_channels
from twind.cli import build_parser, main
from twind.cli.recording import cmd_export
from twind.recording.export import export
from twind.recording.fastread import read_channels
from twind.recording.mcapfile import JsonDecoderFactory
from twind.recording.reader import getdata, read_session
from twind.recording.recorder import Recorder, synthetic_block
from twind.recording.replay import replay
from twind.recording.sources import Roster, UnservedWarning
from twind.recording.session import (
    DamagedRecordingWarning,
    GapWarning,
    RecordingError,
    TruncatedRecordingWarning,
)
from twind.recording import writer as writer_module
from twind.recording.writer import (
    CHUNK_BYTES,
    CHUNK_SECONDS,
    CONFIG_METADATA,
    SESSION_METADATA,
    McapSession,
    SessionWriter,
    scan_block,
)
from twind.timeutil import gps_to_unix_ns

GPS0 = 1_400_000_000.0
ROOT = Path(__file__).resolve().parents[1]
SYNTH = ["C1:SUS-ETMX_SUSPOS_IN1", "C1:SUS-ETMX_SUSPIT_IN1", "C1:SUS-ETMX_ULSEN_OUT"]
TWIN = "synth/1/abcdef"
"""The twin the synthetic blocks name; :func:`_answer_as_twin` answers its status."""


def _expected(channel: str, seqs) -> np.ndarray:  # noqa: ANN001
    return np.concatenate([SampleBlock.decode(synthetic_block(channel, k)).samples
                           for k in seqs])


# --- files written by SessionWriter (twind simulate --record) ----------------------------


@pytest.fixture(scope="module")
def engine_session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """A session of ETMX and ITMX written by SessionWriter, and the engine's samples."""
    from twind.config import load_config
    from twind.simulation.engine import Engine

    twin = load_config(None, "ETMX,ITMX")
    optics = twin.select("ETMX,ITMX")
    engine = Engine([o.loop() for o in optics], {o.name: o.noise for o in optics}, seed=7)
    path = tmp_path_factory.mktemp("engine") / "session.mcap"
    expected: dict[str, list[np.ndarray]] = {}
    with SessionWriter(path, twin.ifo, GPS0) as writer:
        for _ in range(5):
            block = engine.step(4096)
            writer.write_block(block)
            for name, _, x in block_channels(twin.ifo, block):
                expected.setdefault(name, []).append(x.copy())
    return path, {k: np.concatenate(v) for k, v in expected.items()}


@pytest.mark.slow
def test_session_writer_roundtrip(engine_session: tuple[Path, dict]) -> None:
    path, expected = engine_session
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        session = read_session(path)
    assert session.complete and not session.problems and not session.gaps
    # each optic has 24 channels: 4 DOFs x 4 points, 3 drives past the filters, 5 OSEMs
    assert set(session.channels) == set(expected) and len(expected) == 48
    for name, x in expected.items():
        ch = session[name]
        assert np.array_equal(ch.samples, x), name  # bit for bit
        assert ch.t0 == GPS0 and ch.rate == 16384.0
        assert list(ch.sequences) == [0, 1, 2, 3, 4]
        assert np.allclose(np.diff(ch.gps_starts), 0.25)
    assert session["C1:SUS-ETMX_SUSPOS_IN1"].unit == "um"
    assert session.config["ifo"] == "C1" and session.config["gps"] == GPS0
    assert session.events == []
    with pytest.raises(RecordingError, match="not in the recording"):
        session["C1:SUS-ETMZ_SUSPOS_IN1"]

    # the standard reader: one schema, registered once, decodable by mcap-protobuf
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        protobuf = [s for s in summary.schemas.values() if s.encoding == "protobuf"]
        assert [s.name for s in protobuf] == ["twind.v1.SampleBlock"]
        assert summary.statistics.message_count == 48 * 5
        assert all(c.compression == "zstd" for c in summary.chunk_indexes)
        assert max(c.uncompressed_size for c in summary.chunk_indexes) < 300_000
        n = 0
        for _, channel, message, proto in reader.iter_decoded_messages():
            assert channel.topic == f"twin/{proto.channel}"
            assert message.sequence == proto.sequence
            assert message.log_time == message.publish_time == gps_to_unix_ns(proto.gps_start)
            n += 1
        assert n == 48 * 5


def test_export_npz_and_hdf5(engine_session: tuple[Path, dict], tmp_path: Path) -> None:
    path, expected = engine_session
    result = export(path, tmp_path / "all.npz")
    assert result.format == "npz" and not result.gaps and len(result.channels) == 48
    with np.load(tmp_path / "all.npz") as npz:
        assert set(npz.files) == {f"{c}{s}" for c in expected for s in ("", ":t0", ":rate")}
        for name, x in expected.items():
            assert npz[name].dtype == np.float64 and np.array_equal(npz[name], x)
            assert npz[f"{name}:t0"] == GPS0 and npz[f"{name}:rate"] == 16384.0

    some = ["C1:SUS-ITMX_SUSYAW_OUT", "C1:SUS-ETMX_LRSEN_OUT"]
    result = export(path, tmp_path / "some.h5", channels=some)
    assert result.format == "hdf5" and result.channels == some
    with h5py.File(tmp_path / "some.h5", "r") as f:
        assert sorted(f.keys()) == sorted(some)
        for name in some:
            assert np.array_equal(f[name][()], expected[name])
            assert f[name].attrs["t0"] == GPS0 and f[name].attrs["rate"] == 16384.0

    # never overwrite; refuse unknown formats and channels, before writing anything
    before = (tmp_path / "some.h5").read_bytes()
    with pytest.raises(RecordingError, match="does not overwrite"):
        export(path, tmp_path / "some.h5")
    assert (tmp_path / "some.h5").read_bytes() == before
    with pytest.raises(RecordingError, match=r"\.npz, \.h5 or \.hdf5"):
        export(path, tmp_path / "x.csv")
    with pytest.raises(RecordingError, match="C1:SUS-ETMZ"):
        export(path, tmp_path / "x.npz", channels=["C1:SUS-ETMZ_SUSPOS_IN1"])
    assert not (tmp_path / "x.npz").exists()

    # the command line's half: twind export FILE -o OUT --channels a,b
    out = tmp_path / "cli.hdf5"
    args = build_parser().parse_args(["export", str(path), "-o", str(out), "--channels",
                                      ",".join(some)])
    assert cmd_export(args) == 0
    with h5py.File(out, "r") as f:
        assert sorted(f.keys()) == sorted(some)


def _plain(x: object) -> float:
    """A gwpy quantity's value, or a plain number."""
    return float(getattr(x, "value", x))


@pytest.mark.parametrize("gwpy", [True, False])
def test_getdata_from_a_recording(engine_session: tuple[Path, dict], gwpy: bool,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    if not gwpy:  # as installed without twind[frames]: twind's own Series
        monkeypatch.setitem(sys.modules, "gwpy.timeseries", None)
    path, expected = engine_session
    name = "C1:SUS-ETMX_SUSPOS_IN1"
    data = getdata([name, "C1:SUS-ITMX_ULSEN_OUT"], 0.5, start=GPS0 + 0.125, source=path)
    ts = data[name]
    assert type(ts).__name__ == ("TimeSeries" if gwpy else "Series")
    assert _plain(ts.t0) == GPS0 + 0.125 and _plain(ts.sample_rate) == 16384.0
    assert len(ts.value) == 8192
    assert np.array_equal(ts.value, expected[name][2048:2048 + 8192])
    with pytest.raises(RecordingError, match="cover GPS"):
        getdata(name, 2.0, start=GPS0, source=path)  # 1.25 s recorded


# --- synthetic files: gaps and truncation ---------------------------------------------------


def _synthetic_file(path: Path, seqs: dict[str, list[int]], chunk_bytes: int = 32 * 1024,
                    events: int = 0) -> None:
    with McapSession(path, "C1", {"optics": ["ETMX"]}, chunk_bytes=chunk_bytes) as f:
        for k in range(max(max(s) for s in seqs.values()) + 1):
            for name, s in seqs.items():
                if k in s:
                    f.write_block(synthetic_block(name, k))
            if k < events:
                f.write_event({"event": "start", "id": k, "gps": GPS0 + k / 16})


def test_gaps_are_reported_and_nan_filled(tmp_path: Path) -> None:
    path = tmp_path / "gappy.mcap"
    full, gappy = list(range(8)), [0, 1, 2, 5, 6, 7]
    _synthetic_file(path, {SYNTH[0]: full, SYNTH[1]: gappy})
    with pytest.warns(GapWarning, match="2 block"):
        result = export(path, tmp_path / "gappy.npz")
    assert list(result.gaps) == [SYNTH[1]]
    gap = result.gaps[SYNTH[1]][0]
    assert (gap.after_sequence, gap.before_sequence, gap.n_samples) == (2, 5, 2048)
    with np.load(tmp_path / "gappy.npz") as npz:
        x = npz[SYNTH[1]]
        assert len(x) == 8 * 1024 and np.isnan(x[3072:5120]).all()
        assert np.array_equal(x[:3072], _expected(SYNTH[1], [0, 1, 2]))
        assert np.array_equal(x[5120:], _expected(SYNTH[1], [5, 6, 7]))
        assert np.allclose(npz[f"{SYNTH[1]}:gaps"], [[GPS0 + 3 / 16, GPS0 + 5 / 16]])
        assert f"{SYNTH[0]}:gaps" not in npz.files
        assert np.array_equal(npz[SYNTH[0]], _expected(SYNTH[0], full))


def test_truncated_file_reads_up_to_the_last_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    _synthetic_file(path, {c: list(range(40)) for c in SYNTH[:2]}, events=3)
    data = path.read_bytes()
    counts = []
    for cut in (400, len(data) // 3, len(data) // 2, len(data) - 200, len(data) - 1):
        part = tmp_path / f"cut{cut}.mcap"
        part.write_bytes(data[:cut])
        with pytest.warns(TruncatedRecordingWarning, match="without its summary and footer"):
            session = read_session(part)  # never raises
        assert not session.complete
        n = [len(session[c].sequences) if c in session else 0 for c in SYNTH[:2]]
        for c in SYNTH[:2]:
            if c in session:  # a prefix of the blocks, exactly
                seqs = list(session[c].sequences)
                assert seqs == list(range(len(seqs)))
                assert np.array_equal(session[c].samples, _expected(c, seqs))
        counts.append(min(n))
    assert counts[0] == 0 and counts == sorted(counts) and counts[-1] == 40
    assert 0 < counts[1] < counts[2] < 40


@pytest.mark.parametrize("batch_bytes", [1, 1 << 13, None])
def test_fast_reader_reads_cut_gappy_and_foreign_files_as_read_session(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, batch_bytes: int | None) -> None:
    """read_channels (a memory map, chunks decoded on workers, a batch at a time) reads as
    mcap's own reader does, message by message (tests/mcap_reference.py): a file cut anywhere gives the same prefix of blocks and one
    truncation warning, gaps the same NaN-filled samples, a file that is not MCAP a
    RecordingError; whatever the number of chunks decoded together."""
    from twind.recording import fastread
    batches = []
    if batch_bytes is not None:
        monkeypatch.setattr(fastread, "_BATCH_BYTES", batch_bytes)
    decode = fastread._decode_batch
    monkeypatch.setattr(fastread, "_decode_batch",
                        lambda chunks, m: (batches.append(len(chunks)), decode(chunks, m))[1])

    path = tmp_path / "full.mcap"
    _synthetic_file(path, {SYNTH[0]: list(range(40)), SYNTH[1]: [*range(10), *range(12, 40)]},
                    events=3)
    data = path.read_bytes()
    for cut in (5, 400, len(data) // 3, len(data) - 200, len(data) - 1, len(data)):
        part = tmp_path / f"cut{cut}.mcap"
        part.write_bytes(data[:cut])
        with warnings.catch_warnings(record=True) as slow_warned:
            warnings.simplefilter("always")
            slow = reference_session(part)
        with warnings.catch_warnings(record=True) as fast_warned:
            warnings.simplefilter("always")
            fast = read_channels(part, lambda name: True)
        assert [type(w.message) for w in fast_warned] == [type(w.message) for w in slow_warned]
        assert (fast.complete, len(fast.problems)) == (slow.complete, len(slow.problems))
        assert fast.events == slow.events and list(fast.channels) == list(slow.channels)
        for c in slow:
            np.testing.assert_array_equal(fast[c].samples, slow[c].samples)
            np.testing.assert_array_equal(fast[c].sequences, slow[c].sequences)
            assert fast[c].gaps == slow[c].gaps
    assert slow[SYNTH[1]].gaps  # the last, whole file had its gap
    assert max(batches) == 1 if batch_bytes == 1 else max(batches) > 1
    foreign = tmp_path / "notes.mcap"
    foreign.write_bytes(b"not a recording at all")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        read_channels(foreign, lambda name: True)


# --- the recorder -----------------------------------------------------------------------------


class _Lines:
    """The lines a subprocess writes to a pipe, readable with a timeout."""

    def __init__(self, pipe) -> None:  # noqa: ANN001
        self.q: queue.SimpleQueue[str] = queue.SimpleQueue()
        self.all: list[str] = []
        threading.Thread(target=self._pump, args=(pipe,), daemon=True).start()

    def _pump(self, pipe) -> None:  # noqa: ANN001
        for line in pipe:
            self.all.append(line)
            self.q.put(line)

    def wait_for(self, text: str, timeout: float = 20.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.q.get(timeout=0.1)
            except queue.Empty:
                continue
            if text in line:
                return line
        msg = f"no {text!r} within {timeout} s; got {self.all}"
        raise AssertionError(msg)


def _start_recorder(out: Path, port: int, *extra: str) -> tuple[subprocess.Popen, _Lines]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "twind", "record", "twin/**", "-o", str(out),
         "--connect", f"tcp/127.0.0.1:{port}", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    lines = _Lines(proc.stderr)
    try:
        lines.wait_for("twind record: recording ")
    except AssertionError:
        proc.kill()
        raise
    return proc, lines


def _publish_synthetic(pubs: dict, n: int, first: int = 0) -> None:
    """Blocks ``first .. n-1`` of every channel of `pubs`, block by block, from :data:`TWIN`."""
    for k in range(first, n):
        for c, pub in pubs.items():
            pub.put(synthetic_block(c, k, twin=TWIN))


def _answer_as_twin(session: zenoh.Session, status: dict | None = None):  # noqa: ANN202
    """Answer status queries as :data:`TWIN`, serving ETMX (its queryable, to keep)."""
    reply = json.dumps(status or {"ok": True, "twin": TWIN, "ifo": "C1", "optics": ["ETMX"]})
    return session.declare_queryable("twin/@/C1/status", lambda q: q.reply(q.key_expr, reply))


def _publishers(session: zenoh.Session, channels: list[str]) -> dict:
    pubs = {c: session.declare_publisher(f"twin/{c}",
                                         congestion_control=zenoh.CongestionControl.BLOCK)
            for c in channels}
    deadline = time.monotonic() + 10
    while not all(_matching(p) for p in pubs.values()):  # the recorder's subscription
        assert time.monotonic() < deadline, "the recorder never subscribed"
        time.sleep(0.01)
    return pubs


def _matching(pub) -> bool:  # noqa: ANN001
    status = pub.matching_status
    return bool(getattr(status, "matching", status))


def test_recorder_sigterm_writes_a_complete_file(tmp_path: Path) -> None:
    port = free_port()
    out = tmp_path / "rec.mcap"
    status = {"twin": TWIN, "ifo": "C1", "optics": ["ETMX"], "model_rate_hz": 16384}
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        queryable = _answer_as_twin(session, status)
        proc, lines = _start_recorder(out, port)
        try:
            pubs = _publishers(session, SYNTH)
            events = session.declare_publisher("twin/@/C1/events")
            for k in range(20):
                for c in SYNTH:
                    pubs[c].put(synthetic_block(c, k, twin=TWIN))
                if k == 10:
                    events.put(json.dumps({"event": "start", "id": "inj-1", "gps": GPS0 + 0.6,
                                           "request": {"optic": "ETMX", "dof": "POS"}}))
            time.sleep(0.5)  # in flight, then written
            proc.send_signal(signal.SIGTERM)
            stdout, _ = proc.communicate(timeout=20)
        finally:
            proc.kill()
        queryable.undeclare()
    assert proc.returncode == 0, "".join(lines.all)
    assert "recorded 60 blocks of 3 channel(s)" in stdout and "1 event" in stdout

    # complete: summary and footer, readable by the standard reader
    with open(out, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory(), JsonDecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 60 + 1 + 1
        topics = {c.topic for c in summary.channels.values()}
        assert topics == {f"twin/{c}" for c in SYNTH} | {"twin/@events", "twin/@config"}
        decoded = list(reader.iter_decoded_messages(log_time_order=False))
    assert decoded[0].channel.topic == "twin/@config"
    assert decoded[0].decoded_message["status"] == status
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        session_read = read_session(out)
    assert session_read.complete and session_read.config["status"] == status
    assert [e["id"] for e in session_read.events] == ["inj-1"]
    for c in SYNTH:
        assert list(session_read[c].sequences) == list(range(20))
        assert np.array_equal(session_read[c].samples, _expected(c, range(20)))


def test_recorder_sigkill_leaves_a_readable_file(tmp_path: Path) -> None:
    port = free_port()
    out = tmp_path / "killed.mcap"
    n = 150  # 3 x 150 blocks of 8.3 kB: about 15 chunks
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        proc, _ = _start_recorder(out, port)
        try:
            _publish_synthetic(_publishers(session, SYNTH), n)
            deadline = time.monotonic() + 10
            while out.stat().st_size < 2_000_000 and time.monotonic() < deadline:
                time.sleep(0.02)
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            proc.kill()
    with pytest.warns(TruncatedRecordingWarning):
        session_read = read_session(out)
    assert not session_read.complete
    lengths = []
    for c in SYNTH:
        seqs = list(session_read[c].sequences)
        assert seqs == list(range(len(seqs)))  # what is there is whole and in order
        assert np.array_equal(session_read[c].samples, _expected(c, seqs))
        lengths.append(len(seqs))
    assert min(lengths) >= 50, lengths
    assert session_read.config["status"] is None and "no twin service" in \
        session_read.config["status_problem"]
    # the killed file recovered: any MCAP reader takes it, with everything twind read
    fixed = tmp_path / "fixed.mcap"
    assert main(["recover", str(out), "-o", str(fixed)]) == 0
    with open(fixed, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        topics = {c.topic for c in summary.channels.values()}
        counts = summary.statistics.channel_message_counts
        by_topic = {summary.channels[k].topic: v for k, v in counts.items()}
    assert set(SYNTH) <= {t.removeprefix("twin/") for t in topics}
    assert sorted(n for t, n in by_topic.items() if "SUS" in t or "SEN" in t) == sorted(lengths)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # complete now
        again = read_session(fixed)
    assert again.complete and again.config == session_read.config
    for c in SYNTH:
        assert np.array_equal(again[c].samples, session_read[c].samples)
    assert main(["recover", str(out), "-o", str(fixed)]) == 2  # never overwritten


def _blocks_on_disk(path: Path, channel: str) -> int:
    """Blocks of `channel` a reader finds in a file being written (0 before its first)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TruncatedRecordingWarning)
            return len(read_session(path)[channel].sequences)
    except RecordingError:  # the channel not there yet
        return 0


def test_an_open_chunk_reaches_the_file_chunk_seconds_after_its_first_message(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The loss bound: a chunk that never fills is closed :data:`CHUNK_SECONDS` after its
    first message, on the writer's own clock (made a test's here)."""
    clock = [1000.0]
    monkeypatch.setattr(writer_module.time, "monotonic", lambda: clock[0])
    path, channel = tmp_path / "slow.mcap", SYNTH[0]
    with McapSession(path, "C1") as f:
        f.write_block(synthetic_block(channel, 0))
        clock[0] += 0.5 * CHUNK_SECONDS
        f.write_block(synthetic_block(channel, 1))
        clock[0] += 0.49 * CHUNK_SECONDS
        f.maybe_flush()
        assert _blocks_on_disk(path, channel) == 0  # both still in the open chunk
        clock[0] += 0.02 * CHUNK_SECONDS
        f.maybe_flush()
        assert _blocks_on_disk(path, channel) == 2


def test_a_slow_recording_killed_keeps_all_but_its_last_second(tmp_path: Path) -> None:
    """Four blocks a second of one channel never fill a chunk (8 kB each, chunks of
    :data:`CHUNK_BYTES`): only the recorder's time-based close puts them on disk, while
    blocks keep arriving and after they stop. Waited for on the file, then SIGKILL."""
    port, out, channel = free_port(), tmp_path / "slow.mcap", SYNTH[0]
    assert 12 * len(synthetic_block(channel, 0)) < CHUNK_BYTES
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        proc, _ = _start_recorder(out, port)
        try:
            pub = _publishers(session, [channel])[channel]
            on_disk_while_arriving = 0
            for k in range(12):
                pub.put(synthetic_block(channel, k))
                time.sleep(0.25)
                on_disk_while_arriving = _blocks_on_disk(out, channel)
            deadline = time.monotonic() + 30  # a bound on a stuck test, not on the recorder
            while _blocks_on_disk(out, channel) < 12:
                assert time.monotonic() < deadline, "the open chunk never reached the file"
                time.sleep(0.05)
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            proc.kill()
    assert on_disk_while_arriving > 0  # chunks closed by age while blocks still came
    with pytest.warns(TruncatedRecordingWarning):
        session_read = read_session(out)
    assert list(session_read[channel].sequences) == list(range(12))
    assert np.array_equal(session_read[channel].samples, _expected(channel, range(12)))


@pytest.mark.parametrize("rotate", [{"rotate_bytes": 800_000}, {"rotate_seconds": 2.0}])
def test_rotation_reads_back_seamlessly(tmp_path: Path, rotate: dict) -> None:
    port = free_port()
    out = tmp_path / "rot.mcap"
    n = 120  # 3 MB of blocks, 7.5 s of data
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        twin = _answer_as_twin(session)  # noqa: F841 - answering while it lives
        rec = Recorder(zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]), out, **rotate,
                       status_timeout=0.2, log=lambda line: None)
        rec.start()
        try:
            _publish_synthetic(_publishers(session, SYNTH), n)
            deadline = time.monotonic() + 10
            while rec.stats.blocks < 3 * n and time.monotonic() < deadline:
                time.sleep(0.02)
        finally:
            stats = rec.stop()
    files = sorted(tmp_path.glob("rot-*.mcap"))
    assert not out.exists() and files == stats.files and len(files) >= 3
    assert [f.name for f in files[:2]] == ["rot-0001.mcap", "rot-0002.mcap"]
    for i, f in enumerate(files):  # each one complete, and no bigger or longer than asked
        with open(f, "rb") as fh:
            summary = make_reader(fh).get_summary()
        assert summary.statistics.message_count > 1
        if "rotate_bytes" in rotate:
            assert f.stat().st_size <= 800_000 + 300_000
        else:  # 32 blocks a file (24 in the last): GPS0 + 2 i ... GPS0 + 2 i + 31/16
            starts = read_session(f)[SYNTH[0]].gps_starts
            assert starts[0] == GPS0 + 2 * i and len(starts) == (24 if i == 3 else 32)
    if "rotate_seconds" in rotate:
        assert len(files) == 4
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        whole = read_session(out)  # the set, by the name it was given
    assert whole.files == files and whole.complete and not whole.gaps
    assert len(whole.configs) == len(files)
    for c in SYNTH:
        assert list(whole[c].sequences) == list(range(n))
        assert np.array_equal(whole[c].samples, _expected(c, range(n)))


def test_recorder_refuses_to_overwrite(tmp_path: Path) -> None:
    (tmp_path / "a.mcap").write_bytes(b"")
    conf = zenoh_config()
    with pytest.raises(RecordingError, match="does not overwrite"):
        Recorder(conf, tmp_path / "a.mcap")
    (tmp_path / "b-0001.mcap").write_bytes(b"")
    with pytest.raises(RecordingError, match="b-0001.mcap exists"):
        Recorder(conf, tmp_path / "b.mcap", rotate_seconds=10)
    with pytest.raises(RecordingError, match="rotate_bytes must be positive"):
        Recorder(conf, tmp_path / "c.mcap", rotate_bytes=0)


def test_getdata_from_the_bus(tmp_path: Path) -> None:
    port = free_port()
    names = SYNTH[:2]
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        def publish() -> None:
            pubs = _publishers(session, names)
            for k in range(12):
                for c in names:
                    pubs[c].put(synthetic_block(c, k))
                time.sleep(0.01)

        publisher = threading.Thread(target=publish, daemon=True)
        publisher.start()
        data = getdata(names, 0.5, start=GPS0 + 0.125,
                       source=zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]), timeout=10)
        publisher.join(timeout=10)
    for c in names:
        assert _plain(data[c].t0) == GPS0 + 0.125 and _plain(data[c].sample_rate) == 16384.0
        assert np.array_equal(data[c].value, _expected(c, range(12))[2048:2048 + 8192])


# --- replay ------------------------------------------------------------------------------------


class _CountedWaits(threading.Event):
    """A replay's stop event that keeps the waits asked of it (the pacing)."""

    def __init__(self) -> None:
        super().__init__()
        self.waits: list[float] = []

    def wait(self, timeout: float | None = None) -> bool:
        if timeout is not None:
            self.waits.append(timeout)
        return super().wait(timeout)


def test_replay_same_bytes_in_order_and_paced(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    _synthetic_file(path, {c: list(range(40)) for c in SYNTH[:2]}, events=1)
    span = 39 / 16  # s between the first and last block
    expected = [(f"twin/{h.channel}", d) for d in
                (synthetic_block(c, k) for k in range(40) for c in SYNTH[:2])
                for h in [scan_block(d)]]
    port = free_port()
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        got: queue.SimpleQueue = queue.SimpleQueue()
        subs = [session.declare_subscriber(
            key, lambda s: got.put((str(s.key_expr), s.payload.to_bytes())))
            for key in ("twin/**", "twin/@/C1/events")]
        conf = zenoh_config(connect=[f"tcp/127.0.0.1:{port}"])
        timings, waits = {}, {}
        for rate in (10.0, float("inf")):
            stop = _CountedWaits()
            stats = replay(path, conf, rate=rate, stop=stop)
            waits[rate] = stop.waits
            received = [got.get(timeout=30) for _ in range(stats.messages)]
            data = [r for r in received if not r[0].startswith("twin/@")]
            assert data == expected, rate  # the same bytes, in order
            events = [json.loads(r[1]) for r in received if r[0] == "twin/@/C1/events"]
            assert events == [{"event": "start", "id": 0, "gps": GPS0}]
            assert stats.messages == 81 and stats.recorded_span_s == pytest.approx(span)
            timings[rate] = stats.elapsed_s
        for s in subs:
            s.undeclare()
    # paced: the waits it asked for add up to the recording's span over the rate, and no
    # message left before its time; unpaced at an infinite rate
    assert 0 < sum(waits[10.0]) <= span / 10 <= timings[10.0], (waits, timings)
    assert waits[float("inf")] == [], waits
    with pytest.raises(RecordingError, match="rate must be >= 0"):
        replay(path, conf, rate=-1)


def test_replay_loop_and_stop(tmp_path: Path) -> None:
    path = tmp_path / "short.mcap"
    _synthetic_file(path, {SYNTH[0]: list(range(4))})  # 4 blocks: 0.25 s a pass
    port = free_port()
    stop = threading.Event()
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        got: list[int] = []
        sub = session.declare_subscriber(
            "twin/**", lambda s: got.append(scan_block(s.payload.to_bytes()).sequence))
        threading.Timer(1.5, stop.set).start()
        stats = replay(path, zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]), rate=2.0,
                       loop=True, stop=stop)
        time.sleep(0.1)
        sub.undeclare()
    # 0.125 s a pass at 2x: about 10 passes in 1.5 s, each 0, 1, 2, 3
    assert 6 <= stats.loops <= 14, stats
    assert got[:8] == [0, 1, 2, 3, 0, 1, 2, 3]
    assert len(got) == stats.messages


def test_cli_entry_points_report_errors(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for command, args, text in [
        ("export", [str(tmp_path / "none.mcap"), "-o", str(tmp_path / "x.npz")],
         "no such recording"),
        ("replay", [str(tmp_path / "none.mcap")], "no such recording"),
        ("record", ["-o", str(tmp_path / "no" / "x.mcap")], "no such directory"),
    ]:
        proc = subprocess.run([sys.executable, "-m", "twind", command, *args],
                              capture_output=True, text=True, env=env, cwd=ROOT, timeout=30,
                              check=False)
        assert proc.returncode == 2 and text in proc.stderr, (command, proc.stderr)
        assert "Traceback" not in proc.stderr
    shutil.rmtree(tmp_path, ignore_errors=True)


def test_the_recorder_marks_a_silent_twin_and_its_restart(tmp_path: Path) -> None:
    """Blocks 0..9, nothing for longer than ``silence_s``, then a restarted twin numbering
    from 0 again, later in GPS: the file holds a ``twin_silent`` and one ``twin_restart``
    event, the stats count them, and the reader reports the restart as one, not as a
    negative number of missing blocks."""
    port, out, lines = free_port(), tmp_path / "rs.mcap", []
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        rec = Recorder(zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]), out, silence_s=0.3,
                       status_timeout=0.2, log=lines.append)
        rec.start()
        try:
            pubs = _publishers(session, SYNTH)
            _publish_synthetic(pubs, 10)
            _until(lambda: rec.stats.silences == 1)
            for k in range(5):  # the new twin: its blocks from 0, a minute later
                for c, pub in pubs.items():
                    pub.put(synthetic_block(c, k, gps0=GPS0 + 60, twin="synth/2/fedcba"))
            _until(lambda: rec.stats.blocks == 15 * len(SYNTH))
        finally:
            stats = rec.stop()
    assert (stats.silences, stats.restarts) == (1, 1)
    assert "fell silent 1 time(s) and restarted 1 time(s)" in stats.summary()
    assert any("the twin restarted" in line for line in lines)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        session = read_session(out)
    kinds = [e["event"] for e in session.events]
    assert kinds.count("twin_silent") == 1 and kinds.count("twin_restart") == 1
    gap, = [g for g in session.gaps if g.channel == SYNTH[0]]
    assert gap.restarted and "the twin restarted between sequence 9 and 0" in str(gap)
    assert any("the twin restarted" in str(w.message) for w in caught)
    assert not any("missing between" in str(w.message) for w in caught)


def _until(done, timeout_s: float = 10.0) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not done():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def test_a_recorder_ends_cleanly_when_the_process_that_started_it_is_killed(
        tmp_path: Path) -> None:
    """As ``serve --record`` starts it (``--parent``): its parent SIGKILLed, the recorder
    closes a complete file instead of living on as an orphan."""
    out, pid_file = tmp_path / "orphan.mcap", tmp_path / "pid"
    launcher = subprocess.Popen([sys.executable, "-c", (
        "import os, subprocess, sys, time\n"
        f"p = subprocess.Popen([sys.executable, '-m', 'twind', 'record', '-o', {str(out)!r}, "
        f"'--connect', 'tcp/127.0.0.1:{free_port()}', '--parent', str(os.getpid())])\n"
        f"open({str(pid_file)!r}, 'w').write(str(p.pid))\n"
        "time.sleep(120)\n")], env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT)
    try:
        _until(lambda: out.exists(), 60)
        launcher.kill()
        launcher.wait()

        def complete() -> bool:
            with open(out, "rb") as fh:
                try:
                    return make_reader(fh).get_summary() is not None
                except Exception:  # noqa: BLE001 - still being written
                    return False

        _until(complete, 30)
    finally:
        launcher.kill()
        if pid_file.exists():
            try:
                os.kill(int(pid_file.read_text()), signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_damaged_chunk_inside_a_complete_file_costs_only_its_own_span(
        tmp_path: Path) -> None:
    """4 kB overwritten in the middle of a complete file: the reader goes on by the chunk
    index, says which GPS span was lost and why (not a killed writer), and keeps the rest;
    ``twind recover`` writes a file every MCAP reader takes, without that chunk."""
    path = tmp_path / "damaged.mcap"
    _synthetic_file(path, {c: list(range(80)) for c in SYNTH})
    raw = bytearray(path.read_bytes())
    middle = len(raw) // 2
    raw[middle : middle + 4096] = bytes(4096)
    path.write_bytes(bytes(raw))
    with pytest.warns(DamagedRecordingWarning, match=r"damaged .*GPS 14\d+\.\d+ to .*lost"):
        session = reference_session(path)
    assert not session.complete and not any("killed" in p for p in session.problems)
    kept = [len(session[c].sequences) for c in SYNTH]
    assert all(60 <= n < 80 for n in kept), kept  # one chunk lost, not everything after it
    assert all(session[c].sequences[-1] == 79 for c in SYNTH)
    with pytest.warns(DamagedRecordingWarning, match=r"damaged .*GPS 14\d+\.\d+ to .*lost"):
        fast = read_session(path)  # twind's reader, on its fast engine
    assert [len(fast[c].sequences) for c in SYNTH] == kept and not fast.complete
    assert main(["recover", str(path), "-o", str(tmp_path / "fixed.mcap")]) == 0
    with open(tmp_path / "fixed.mcap", "rb") as fh:
        counts = make_reader(fh).get_summary().statistics.channel_message_counts
    assert sorted(counts.values())[-len(SYNTH):] == sorted(kept)


def test_a_recovered_file_has_the_summary_chunk_index_and_metadata_mcap_promises(
        tmp_path: Path) -> None:
    """A file cut two thirds in, recovered: its summary indexes every chunk it holds (one
    chunk index per Chunk record, as its statistics count them, and a seeking reader reads
    every message through them), its messages are every block twind read from the cut file,
    and its metadata (session and configuration) is the original's, found through the
    summary's metadata index as a seeking reader finds it."""
    full, cut, fixed = (tmp_path / n for n in ("full.mcap", "cut.mcap", "fixed.mcap"))
    _synthetic_file(full, {c: list(range(40)) for c in SYNTH})
    data = full.read_bytes()
    cut.write_bytes(data[: 2 * len(data) // 3])
    with pytest.warns(TruncatedRecordingWarning):
        kept = {c: len(read_session(cut)[c].sequences) for c in SYNTH}
    assert all(0 < n < 40 for n in kept.values()), kept
    assert main(["recover", str(cut), "-o", str(fixed)]) == 0
    with open(fixed, "rb") as fh:
        records = StreamReader(fh, emit_chunks=True, validate_crcs=True).records
        chunks = sum(isinstance(r, Chunk) for r in records)
    with open(fixed, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert len(summary.chunk_indexes) == summary.statistics.chunk_count == chunks > 0
        # read through them: every message the statistics count
        assert sum(1 for _ in reader.iter_messages()) == summary.statistics.message_count
        counts = {summary.channels[k].topic.removeprefix("twin/"): n
                  for k, n in summary.statistics.channel_message_counts.items()}
        assert {c: counts[c] for c in SYNTH} == kept
        assert {m.name for m in summary.metadata_indexes} == {SESSION_METADATA,
                                                              CONFIG_METADATA}
        recovered = {m.name: m.metadata for m in reader.iter_metadata()}
    with open(full, "rb") as fh:
        assert recovered == {m.name: m.metadata for m in make_reader(fh).iter_metadata()}


def test_the_recorder_skips_what_no_twin_sends_and_its_file_stays_whole(tmp_path: Path) -> None:
    """Forged blocks (GPS NaN, negative or far off, rate 0, a sequence beyond MCAP's 32 bits,
    a block on another channel's key, the same block twice, one inside the block before it)
    and forged events (a time of 1e300, a channel that is a number, not JSON) are skipped
    and counted; the recording goes on and reads back whole, by twind and by mcap."""
    port, out, lines = free_port(), tmp_path / "forged.mcap", []
    ch, other = SYNTH[0], SYNTH[1]

    def block(**change: object) -> bytes:
        fields = {"channel": ch, "gps_start": GPS0 + 1e4, "rate_hz": 16384.0, "sequence": 50,
                  "samples": np.ones(1024), "unit": "um", **change}
        return SampleBlock(**fields).encode()

    forged_blocks = [block(gps_start=math.nan), block(gps_start=-1.0),
                     block(gps_start=1e300), block(rate_hz=0.0), block(rate_hz=math.inf),
                     block(sequence=2**32), block(channel=other), block(samples=np.ones(0))]
    events = control_key("C1", "events")
    forged_events = [b'{"event": "start", "gps": 1e300}', b"not json",
                     json.dumps({"event": "start", "gps": GPS0, "id": "x", "channel": 5}).encode()]
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        twin = _answer_as_twin(session)  # noqa: F841 - answering while it lives
        rec = Recorder(zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]), out,
                       status_timeout=0.2, log=lines.append)
        rec.start()
        try:
            pubs = _publishers(session, [ch])
            _publish_synthetic(pubs, 5)
            for data in forged_blocks:
                pubs[ch].put(data)
            pubs[ch].put(synthetic_block(ch, 4, twin=TWIN))  # the same block twice
            inside = SampleBlock.decode(synthetic_block(ch, 5, twin=TWIN))
            pubs[ch].put(replace(inside, gps_start=inside.gps_start - 0.01).encode())
            for data in forged_events:
                session.put(events, data)
            _publish_synthetic(pubs, 10, first=5)
            _until(lambda: rec.stats.blocks == 10 and rec.stats.invalid + rec.stats.undecodable
                   == len(forged_blocks) + 2 + len(forged_events))
        finally:
            stats = rec.stop()
    assert (stats.invalid, stats.undecodable, stats.restarts) == (12, 1, 0)
    assert "skipped 12 blocks or events no twin sends" in stats.summary()
    assert any("at GPS nan, not a time" in line for line in lines)  # once a key
    session = read_session(out)
    np.testing.assert_array_equal(session.channels[ch].samples, _expected(ch, range(10)))
    assert not session.events and not session.gaps
    with open(out, "rb") as fh:  # the standard reader reads every message
        topics = [channel.topic for _, channel, _ in make_reader(fh).iter_messages()]
    assert topics.count(f"twin/{ch}") == 10 and not any("events" in t for t in topics)


def test_a_lower_sequence_from_the_same_twin_is_not_a_restart(tmp_path: Path) -> None:
    """A forged block numbered below the last one of the twin that publishes the channel (or
    naming no twin) wrote a false ``twin_restart``: it is skipped. A twin started again (a
    new identity, numbering from 0) is one restart, marked once for its channels and not for
    another twin's."""
    port, out = free_port(), tmp_path / "restart.mcap"
    mine, theirs = SYNTH[:2], SYNTH[2]
    a, b, a_again = "host1/100/aaaaaa", "host2/200/bbbbbb", "host1/300/cccccc"
    later = GPS0 + 100.0
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        rec = Recorder(zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]), out,
                       status_timeout=0.2, log=lambda _: None)
        rec.start()
        try:
            pubs = _publishers(session, SYNTH)
            for k in range(6):
                for c in mine:
                    pubs[c].put(synthetic_block(c, k, GPS0, twin=a))
                pubs[theirs].put(synthetic_block(theirs, k, GPS0, twin=b))
            pubs[mine[0]].put(synthetic_block(mine[0], 2, GPS0, twin=a))  # lower, same twin
            pubs[mine[0]].put(synthetic_block(mine[0], 1, later))  # lower, naming no twin
            pubs[theirs].put(synthetic_block(theirs, 9, GPS0, twin=a))  # the other's channel
            for k in range(3):
                for c in mine:
                    pubs[c].put(synthetic_block(c, k, later, twin=a_again))
                pubs[theirs].put(synthetic_block(theirs, 6 + k, GPS0, twin=b))
            _until(lambda: rec.stats.blocks == 27)
        finally:
            stats = rec.stop()
    assert (stats.invalid, stats.restarts) == (3, 1)
    session = read_session(out)
    restarts = [e for e in session.events if e["event"] == "twin_restart"]
    assert len(restarts) == 1 and (restarts[0]["after_twin"], restarts[0]["twin"]) == (a, a_again)
    assert sorted(g.channel for g in session.gaps) == sorted(mine)
    assert all(g.restarted for g in session.gaps)
    np.testing.assert_array_equal(session.channels[theirs].samples,
                                  _expected(theirs, range(9)))


def test_blocks_of_an_optic_no_twin_serves_are_marked_and_warned(tmp_path: Path) -> None:
    """Blocks of an optic nobody serves read back without a warning: a channel whose blocks
    come from a twin serving another optic, or name no twin, is marked once by an
    ``unserved`` event, and reading it warns; a served channel read alone does not."""
    port, out = free_port(), tmp_path / "unserved.mcap"
    served, elsewhere, nameless = SYNTH[0], "C1:SUS-ITMY_SUSPOS_IN1", "C1:SUS-ETMX_SUSYAW_IN1"
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        twin = _answer_as_twin(session)  # noqa: F841 - answering while it lives
        rec = Recorder(zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]), out,
                       status_timeout=0.2, log=lambda _: None)
        rec.start()
        try:
            pubs = _publishers(session, [served, elsewhere, nameless])
            for k in range(200):  # until the twin has answered
                pubs[served].put(synthetic_block(served, k, twin=TWIN))
                pubs[elsewhere].put(synthetic_block(elsewhere, k, twin=TWIN))
                pubs[nameless].put(synthetic_block(nameless, k))
                if rec.stats.unserved == 2:
                    break
                time.sleep(0.02)
        finally:
            stats = rec.stop()
    assert stats.unserved == 2 and "2 channel(s) came from no twin" in stats.summary()
    with pytest.warns(UnservedWarning, match="2 channel"):
        whole = read_session(out)
    why = {e["channel"]: e["why"] for e in whole.events if e["event"] == "unserved"}
    assert sorted(why) == sorted([elsewhere, nameless])
    assert "serves ETMX, not ITMY" in why[elsewhere] and "name no twin" in why[nameless]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_session(out, [served]).channels[served].samples.size > 0


def test_a_twin_is_called_silent_only_while_others_answer() -> None:
    """A twin that does not answer its status is named so after :data:`ASKS` queries that
    other twins answered; while no twin answers (the router away) nothing is concluded."""
    port = free_port()
    with zenoh.open(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"])) as session, \
            zenoh.open(zenoh_config(connect=[f"tcp/127.0.0.1:{port}"])) as asker:
        roster = Roster(asker, "C1", timeout=0.1, pace_s=0.1)
        try:
            for _ in range(10):  # nobody answers: the bus may be away
                assert roster.verdict("gone/9/999999", SYNTH[0]) == (False, None)
                time.sleep(0.12)
            twin = _answer_as_twin(session)  # noqa: F841 - answering while it lives
            _until(lambda: roster.verdict("gone/9/999999", SYNTH[0])[0], 5.0)
            assert "does not answer" in roster.verdict("gone/9/999999", SYNTH[0])[1]
            assert roster.verdict(TWIN, SYNTH[0]) == (True, None)
        finally:
            roster.close()
