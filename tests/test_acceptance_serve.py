"""The serve issue's acceptance run, on loopback: serve and record 20 s, inject a 3 Hz sine,
refuse bad requests while serving, then find it all in the exported recording."""

from __future__ import annotations

import io
import math
import os
import signal
import subprocess
import sys
import time
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
from servicekit import free_port

from twind.cli import main
from twind.client import InjectionRefused, TwinClient
from twind.recording.reader import read_session

POS = "C1:SUS-ETMX_SUSPOS"
RATE = 16384


def _serve_recording(tmp_path: Path, speed: float, duration: float
                     ) -> tuple[str, Path, subprocess.Popen]:
    """``twind serve`` of ETMX recording to ``tmp_path/rec``: its endpoint, folder, process."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rec = tmp_path / "rec"
    proc = subprocess.Popen([sys.executable, "-m", "twind", "serve", "--optics", "ETMX",
                             "--listen", endpoint, "--speed", str(speed), "--duration",
                             str(duration), "--record", str(rec)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    return endpoint, rec, proc


@pytest.mark.slow
def test_serve_record_inject_export(tmp_path: Path) -> None:
    endpoint, rec, proc = _serve_recording(tmp_path, speed=4, duration=24)
    with TwinClient.wait([endpoint], alive=lambda: proc.poll() is None) as twin:
        exc_id = twin.inject(f"{POS}_EXC", "sine", freq=3.0, amp=0.1, duration=20.0)
        for bad in ({"freq": -3.0, "amp": 0.1}, {"freq": 3.0, "amp": math.nan}):
            with pytest.raises(InjectionRefused):
                twin.inject(f"{POS}_EXC", "sine", duration=5.0, **bad)
        assert twin.status().excitations[0].id == exc_id  # still serving
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err

    files = sorted(rec.glob("*.mcap"))
    out = tmp_path / "session.npz"
    with redirect_stdout(io.StringIO()):
        assert main(["export", *map(str, files), "-o", str(out)]) == 0
    data = np.load(out)
    exc, in1, in2 = (data[f"{POS}_{p}"] for p in ("EXC", "IN1", "IN2"))
    assert data[f"{POS}_EXC:rate"] == RATE
    assert data[f"{POS}_IN1:t0"] == data[f"{POS}_EXC:t0"]
    assert np.array_equal(in2 - in1, exc) or np.max(np.abs(in2 - in1 - exc)) < 1e-12
    on = np.flatnonzero(exc)
    sine = exc[on[0]:on[-1] + 1]
    assert sine.size == pytest.approx(20 * RATE, abs=2)
    t = np.arange(sine.size) / RATE
    coef, *_ = np.linalg.lstsq(np.column_stack([np.sin(2 * np.pi * 3 * t),
                                                np.cos(2 * np.pi * 3 * t)]), sine, rcond=None)
    assert np.hypot(*coef) == pytest.approx(0.1, rel=1e-9)
    spectrum = np.abs(np.fft.rfft(sine[: 16 * RATE]))
    assert np.fft.rfftfreq(16 * RATE, 1 / RATE)[np.argmax(spectrum)] == pytest.approx(3.0)

    session = read_session(files)
    assert session.gaps == []
    seqs = session[f"{POS}_EXC"].sequences
    assert list(seqs) == list(range(seqs[0], seqs[0] + len(seqs)))
    events = [e["event"] for e in session.events]
    assert "start" in events and events.count("refused") == 2


@pytest.mark.slow
def test_serve_starts_again_a_recorder_that_ends_and_says_so(tmp_path: Path) -> None:
    """The recorder of ``serve --record`` killed while the twin serves: serve says so, starts
    another (a file of its own) and the twin's status tells both; the gap is the outage."""
    endpoint, rec, proc = _serve_recording(tmp_path, speed=2, duration=40)
    with TwinClient.wait([endpoint], alive=lambda: proc.poll() is None) as twin:
        assert twin.status().recorder == {"folder": str(rec), "recording": True,
                                             "restarts": 0, "last_exit": None}
        assert subprocess.run(["pkill", "-KILL", "-f", f"record -o {rec}"]).returncode == 0
        deadline = time.monotonic() + 60
        while (state := twin.status().recorder)["restarts"] < 1 or not state["recording"]:
            assert time.monotonic() < deadline, state
            time.sleep(0.2)
        assert state["last_exit"] == -9
    out = io.StringIO()
    with redirect_stdout(out):
        assert main(["status", "--connect", endpoint]) == 0
    assert f"recorder: recording to {rec}, restarted 1 time(s)" in out.getvalue()
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert f"the recorder for {rec} ended (exit -9)" in err and "starting another" in err
    starts = {p.name.rsplit("-", 1)[0] for p in rec.glob("*.mcap")}
    assert len(starts) == 2  # two recordings, one before the outage and one after
    assert read_session(sorted(rec.glob("*.mcap"))[-1]).channels


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a small filesystem needs root")
@pytest.mark.slow
def test_a_full_disk_is_said_and_what_was_recorded_reads(tmp_path: Path) -> None:
    """``serve --record`` onto a 4 MB filesystem: the recorder fails when it fills, serve
    says so and starts another, which fails at once and is not started again; status says
    NOT RECORDING, the twin serves on, and the file holds what fitted, readable."""
    disk = tmp_path / "disk"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(disk)], check=True)
    try:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        proc = subprocess.Popen([sys.executable, "-m", "twind", "serve", "--optics", "ETMX",
                                 "--listen", endpoint, "--speed", "4", "--duration", "200",
                                 "--record", str(disk)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        with TwinClient.wait([endpoint], alive=lambda: proc.poll() is None) as twin:
            deadline = time.monotonic() + 120
            while (state := twin.status().recorder)["recording"] or not state["restarts"]:
                assert time.monotonic() < deadline, state
                time.sleep(0.5)
            time.sleep(3.0)  # the watch looks every second: no more restarts
            status = twin.status()
            assert status.recorder["restarts"] == 1 and status.blocks > 0  # serves on
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        assert "starting another" in err and "not started again, it ended again at once" \
            in err and "No space left on device" in err, err[-2000:]
        files = sorted(disk.glob("*.mcap"))
        assert files
        with pytest.warns(Warning):  # a file cut short by the full disk says so
            session = read_session(files[0])
        assert session.channels and len(session[f"{POS}_IN1"].sequences) > 0
    finally:
        subprocess.run(["umount", str(disk)], check=False)
