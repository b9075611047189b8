"""Benchmark of ``twind tf`` on an MCAP session: the issue's target is one hour of 12 channels
at 16384 Hz in under 20 s, end to end (reading the MCAP file, Welch estimates, the plant).

The session is written first (not timed) in the layout of a twin recording: one
``twind.v1.SampleBlock`` message per channel per 1/16 s block, encoded as the service
encodes them, zstd chunks, and the injection events the service publishes (``start`` with
its request, ``end``). Its 12 channels are what ``twind tf`` reads to recover the 3 x 3 plant
of the DOFs a damping-loop measurement excites: EXC, IN1, IN2 and OUT of POS, PIT and YAW
(SIDE is left out: it is neither excited nor needed by the plant). The three DOFs are
excited one after the other, a third of the session each, with broadband noise; each
response is the excitations through a fixed stable IIR filter plus independent noise, cheap
to generate and with the cross-couplings a real recording has. After a 30 s session that
has numba compile (or load) twind's kernels, ``from_session`` is timed in this process (the Welch sums taken while the file is read), beside its fallback
that reads the test points whole first, and ``twind tf`` as a separate process (interpreter
start-up and imports included).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import numpy as np
from scipy import signal

from twind.analysis.estimation import tf
from twind.analysis.estimation.tf import from_session
from twind.bus.codec import SampleBlock
from twind.channels import dof_channel
from twind.errors import TwindError
from twind.recording.writer import McapSession

TARGET_S = 20.0
"""The issue's target wall time for an hour of 12 channels."""
EXCITED = ("POS", "PIT", "YAW")
POINTS = ("EXC", "IN1", "IN2", "OUT")
BLOCK_SAMPLES = 1024  # 1/16 s at 16384 Hz: the service's block
GPS0 = 1_400_000_000.0


@dataclass(frozen=True)
class TFBenchmark:
    """Figures of one run of :func:`run_tf_benchmark`.

    Attributes
    ----------
    duration_s : float
        Seconds of data in the session.
    rate_hz : float
    channels : int
    file_bytes : int
        Size of the MCAP file.
    write_s : float
        Wall time to write it (not part of the target).
    in_process_s : float
        Wall time of :func:`twind.analysis.estimation.tf.from_session` in this process.
    cli_s : float or None
        Wall time of ``twind tf FILE`` as a subprocess, or None if not run.
    target_s : float
        The target for this duration: :data:`TARGET_S` scaled by ``duration_s / 3600``.
    """

    duration_s: float
    rate_hz: float
    channels: int
    file_bytes: int
    write_s: float
    in_process_s: float
    cli_s: float | None
    target_s: float


def session_channels(ifo: str = "C1", optic: str = "ETMX") -> list[str]:
    """The 12 channels of the benchmark session, EXC, IN1, IN2, OUT of POS, PIT, YAW.

    Parameters
    ----------
    ifo : str
        Channel-name prefix (``C1``).
    optic : str

    Returns
    -------
    list of str
        By DOF, then test point.
    """
    return [dof_channel(ifo, optic, d, p) for d in EXCITED for p in POINTS]


def write_session(path: str | Path, duration: float = 3600.0, rate: float = 16384.0,
                  ifo: str = "C1", optic: str = "ETMX", seed: int = 0) -> Path:
    """Write a synthetic excitation session as a twin would record it.

    Parameters
    ----------
    path : str or Path
        MCAP file to create (refused if it exists).
    duration : float
        Seconds; each of POS, PIT and YAW is excited for a third of it. A whole number of
        1024-sample blocks is written.
    rate : float
        Sample rate (Hz).
    ifo, optic : str
        Channel-name prefix and optic.
    seed : int
        Of the noise.

    Returns
    -------
    Path

    Raises
    ------
    TwindError
        If `duration` is too short to hold one block per excitation.
    """

    n_blocks = int(duration * rate) // BLOCK_SAMPLES
    per_dof = n_blocks // len(EXCITED)
    if per_dof < 1:
        msg = f"a benchmark session of {duration:g} s holds less than one block per excitation"
        raise TwindError(msg)
    rng = np.random.default_rng(seed)
    # responses: every EXC through one low-order IIR, with a DOF-dependent gain matrix so
    # that each response sees every excitation (as the loop's cross-couplings do)
    b, a = signal.butter(2, 0.05)
    coupling = np.array([[1.0, 0.1, 0.05], [0.2, 1.0, 0.1], [0.05, 0.3, 1.0]])
    zi = np.zeros((len(EXCITED), len(POINTS) - 1, max(len(a), len(b)) - 1))
    gains = np.array([1.0, -0.8, 0.5])  # IN1, IN2, OUT
    names = [[dof_channel(ifo, optic, d, p) for p in POINTS] for d in EXCITED]
    units = {"POS": "um", "PIT": "urad", "YAW": "urad"}
    chunk = 64  # blocks generated at a time: 4 s, so generation is vectorised
    path = Path(path)
    with McapSession(path, ifo, {"optics": [optic], "benchmark": "twind bench --suite tf"},
                     writer="twind bench") as f:
        for k, dof in enumerate(EXCITED):
            start = GPS0 + k * per_dof * BLOCK_SAMPLES / rate
            event = {"id": f"bench-{k}", "channel": names[k][0], "start_gps": start,
                     "request": {"channel": names[k][0], "waveform": "noise", "amp": 1.0,
                                 "duration": per_dof * BLOCK_SAMPLES / rate}}
            f.write_event({"event": "start", "gps": start, **event})
            for first in range(k * per_dof, (k + 1) * per_dof, chunk):
                m = min(chunk, (k + 1) * per_dof - first)
                exc = np.zeros((len(EXCITED), m * BLOCK_SAMPLES))
                exc[k] = rng.standard_normal(m * BLOCK_SAMPLES)
                drive = coupling @ exc
                data = {0: exc}
                for j in range(1, len(POINTS)):
                    y = np.empty_like(drive)
                    for i in range(len(EXCITED)):
                        y[i], zi[i, j - 1] = signal.lfilter(b, a, gains[j - 1] * drive[i],
                                                            zi=zi[i, j - 1])
                    data[j] = y + 0.1 * rng.standard_normal(y.shape)
                for s in range(m):
                    seq = first + s
                    gps = GPS0 + seq * BLOCK_SAMPLES / rate
                    cut = slice(s * BLOCK_SAMPLES, (s + 1) * BLOCK_SAMPLES)
                    for i, d in enumerate(EXCITED):
                        for j, p in enumerate(POINTS):
                            unit = "ct" if p == "OUT" else units[d]
                            f.write_block(SampleBlock(names[i][j], gps, rate, seq,
                                                      data[j][i, cut], unit).encode())
                f.maybe_flush()
            end = start + per_dof * BLOCK_SAMPLES / rate
            f.write_event({"event": "end", "gps": end, **event})
    return path


def time_from_session(path: str | Path, bw: float = 0.01) -> float:
    """Wall seconds of :func:`twind.analysis.estimation.tf.from_session` on `path` (in this
    process).

    Parameters
    ----------
    path : str or Path
        A benchmark session (:func:`write_session`).
    bw : float
        Welch resolution (Hz).

    Returns
    -------
    float

    Raises
    ------
    TwindError
        If the TFs found are not of POS, PIT and YAW excited.
    """

    t0 = time.perf_counter()
    tfs = from_session([path], bw=bw)
    elapsed = time.perf_counter() - t0
    if tfs.excited != list(EXCITED):
        msg = f"the benchmark session gave excited DOFs {tfs.excited}, not {list(EXCITED)}"
        raise TwindError(msg)
    return elapsed


def _warm_up(workdir: Path, rate: float) -> float:
    """Seconds to run ``from_session`` on a 30 s session: numba compiles twind's kernels on
    their first use after an install or an edit (cached on disk after), which is not the
    reading this benchmark times."""
    path = workdir / "warm-up.mcap"
    path.unlink(missing_ok=True)
    try:
        write_session(path, 30.0, rate)
        return time_from_session(path, bw=4 * len(EXCITED) / 30.0)
    finally:
        path.unlink(missing_ok=True)


def time_read_whole(path: str | Path, bw: float = 0.01) -> float:
    """Wall seconds of :func:`twind.analysis.estimation.tf.from_session` reading the test
    points whole before the Welch sums (its path for recordings with gaps or late events).

    Parameters
    ----------
    path : str or Path
        A benchmark session (:func:`write_session`).
    bw : float
        Welch resolution (Hz).

    Returns
    -------
    float
    """

    with mock.patch.object(tf, "_streamed", lambda *_a, **_k: None):
        return time_from_session(path, bw)


def time_cli(path: str | Path, bw: float = 0.01) -> float:
    """Wall seconds of ``twind tf PATH --bw BW`` in a new Python process.

    Parameters
    ----------
    path : str or Path
        A benchmark session (:func:`write_session`).
    bw : float
        Welch resolution (Hz).

    Returns
    -------
    float

    Raises
    ------
    TwindError
        If the command fails.
    """
    cmd = [sys.executable, "-m", "twind", "tf", str(path), "--bw", f"{bw:g}"]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    elapsed = time.perf_counter() - t0
    if done.returncode != 0:
        msg = f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr.strip()}"
        raise TwindError(msg)
    return elapsed


def run_tf_benchmark(duration: float = 3600.0, rate: float = 16384.0, bw: float | None = None,
                     workdir: str | Path | None = None, keep: bool = False,
                     cli: bool = True, echo: bool = True) -> TFBenchmark:
    """Write a session, time ``twind tf`` on it, print the figures.

    Parameters
    ----------
    duration : float
        Seconds of data (the target is for 3600).
    rate : float
        Sample rate (Hz).
    bw : float, optional
        Welch resolution (Hz); default ``twind tf``'s 0.01 Hz, coarser for a session too
        short for it (at least 4 segments per excitation).
    workdir : str or Path, optional
        Directory for the session file; default a new temporary directory.
    keep : bool
        Leave the file there (its path is printed) instead of removing it.
    cli : bool
        Also time ``twind tf`` as a subprocess.
    echo : bool
        Print the figures.

    Returns
    -------
    TFBenchmark
    """
    if bw is None:
        bw = max(0.01, 4 * len(EXCITED) / duration)
    made = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix="twind-bench-tf-") if made else workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    path = workdir / f"bench-tf-{int(duration)}s.mcap"
    say = print if echo else (lambda *_a, **_k: None)
    try:
        say(f"writing {duration:g} s of {len(session_channels())} channels at {rate:g} Hz "
            f"to {path} ...", flush=True)
        t0 = time.perf_counter()
        write_session(path, duration, rate)
        write_s = time.perf_counter() - t0
        size = path.stat().st_size
        say(f"  written in {write_s:.1f} s, {size / 1e9:.2f} GB (not timed); Welch at "
            f"{bw:g} Hz", flush=True)
        target = TARGET_S * duration / 3600.0
        say(f"  numba kernels compiled or loaded on a short session first: "
            f"{_warm_up(workdir, rate):.1f} s (not timed)", flush=True)
        in_process = time_from_session(path, bw)
        say(f"twind tf, in process (from_session):  {in_process:6.2f} s  "
            f"= {in_process / target:.2f} x the {target:.3g} s target", flush=True)
        whole_s = time_read_whole(path, bw)
        say(f"  read whole, then summed (fallback):  {whole_s:6.2f} s  "
            f"= {whole_s / in_process:.2f} x the streamed sums", flush=True)
        cli_s = None
        if cli:
            cli_s = time_cli(path, bw)
            say(f"twind tf, CLI subprocess (end to end): {cli_s:6.2f} s  "
                f"= {cli_s / target:.2f} x the {target:.3g} s target", flush=True)
        if keep:
            say(f"kept {path}")
        return TFBenchmark(duration, rate, len(session_channels()), size, write_s, in_process,
                           cli_s, target)
    finally:
        if not keep:
            path.unlink(missing_ok=True)
            if made:
                shutil.rmtree(workdir, ignore_errors=True)
