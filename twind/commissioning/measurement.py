"""A diaggui-style FFT measurement on the twin, without the bus: excite each DOF of an optic
in turn, record its test points, and estimate the transfer functions (:func:`measure_tfs`),
or write them to an MCAP session as the twin records one (:func:`record_measurement`).

The DOFs are measured simultaneously on independent copies of the optic (separate noise
streams), which is what measuring them one after the other on a stationary optic gives, in
a third of the time.  Used for calibrating fits (pull tests) and for designing excitations.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind import DOFS
from twind.analysis.estimation.tf import assemble, check_estimator, highpassed, lpm_column, with_lpm
from twind.analysis.estimation.tfset import POINTS, TFSet
from twind.analysis.estimation.welch import welch_tfs
from twind.channels import dof_channel
from twind.config import OpticConfig
from twind.model.plant import Plant
from twind.recording.writer import SessionWriter
from twind.simulation.engine import Engine

BLOCK = 1024
"""Samples per engine step of :func:`record_measurement`: the service's 1/16 s block."""
DRIFT = {"wire_length_m": 0.983, "b_m": 1.027, "R1_m": 0.975, "coil_N_per_ct": 0.968,
         "osem_lever_m": 1.012, "Q_POS": 0.87, "Q_PIT": 1.3, "Q_YAW": 1.1, "Q_SIDE": 0.8}
"""Factors of a "real" optic's parameters over the nominal ones: a few per cent in each, as
a real optic drifts (docs/model.md), for the pull test and the in-process campaign."""

SETTLE_S = 30.0
"""Seconds run before recording.  The slowest closed-loop pole of the 40m damping loops
(Q ~ 5 at 0.69 Hz) decays with tau = Q / (pi f) ~ 2.3 s; 30 s leaves 2e-6 of the switch-on
transient, below what a high-SNR periodic measurement resolves (10 s left 1e-2 and biased
the fitted Qs by sigmas)."""


def white_excitation(n: int, rate_hz: float, rms: float, f_max: float,
                     rng: np.random.Generator) -> NDArray[np.float64]:
    """Gaussian noise of `rms`, low-passed at `f_max` (4th-order Butterworth).

    Parameters
    ----------
    n : int
        Samples.
    rate_hz : float
        Sample rate (Hz).
    rms : float
        RMS of the result (EXC units: um or urad).
    f_max : float
        The low-pass corner (Hz).
    rng : numpy.random.Generator

    Returns
    -------
    ndarray
    """
    sos = signal.butter(4, f_max, fs=rate_hz, output="sos")
    x = signal.sosfilt(sos, rng.standard_normal(n))
    return x * (rms / np.std(x))


def measure_tfs(cfg: OpticConfig, dofs: Sequence[str] = ("POS", "PIT", "YAW"), *,
                bw: float = 0.05, averages: int = 10, overlap: float = 0.5,
                excitation: Mapping[str, NDArray[np.float64]] | None = None,
                rms: float = 1.0, f_max: float = 30.0, seed: int = 0, window: str = "hann",
                highpass_hz: float | None = None, plant: Plant | None = None,
                estimator: str = "welch",
                progress: Callable[[float], None] | None = None) -> TFSet:
    """Closed-loop transfer functions of `cfg`'s optic, measured on the twin.

    Parameters
    ----------
    cfg : OpticConfig
        The optic as it "really" is (its parameters are the truth of the measurement).
    dofs : sequence of str
        DOFs excited, one measurement each.
    bw, averages, overlap : float, int, float
        Welch resolution (Hz), number of averages, segment overlap.
    excitation : mapping of str to ndarray, optional
        EXC samples per DOF, from the start of the settling time (``SETTLE_S`` seconds before
        the recorded averages); default: white noise of `rms` up to `f_max` Hz.
    seed : int
        Seed of the twin's noise and of the default excitation.
    window : str
        Of the spectral estimate; ``"boxcar"`` (with overlap 0) for periodic excitations
        whose period is ``1 / bw``.
    plant : Plant, optional
        The plant the twin runs instead of `cfg`'s (physics the model leaves out).
    highpass_hz : float, optional
        High-pass EXC and responses alike, from the start (:func:`~twind.analysis.estimation.tf.highpassed`).
    estimator : str
        ``"welch"`` (diaggui's), or ``"lpm"``: the local polynomial method over the whole
        record of ``averages`` segments (:mod:`twind.analysis.estimation.lpm`), up to ``4 f_max``.
    progress : callable, optional
        Called with the fraction done.

    Returns
    -------
    TFSet
    """
    check_estimator(estimator)
    rate = cfg.sus.sample_rate_hz
    nperseg, n = _averaged(rate, bw, averages, overlap)
    settle = int(SETTLE_S * rate)
    rng = np.random.default_rng(seed)
    drives = []  # each copy's EXC of its DOF, on from the start, so the loop has
    for d in dofs:  # forgotten the excitation's switch-on as well
        x = (excitation or {}).get(d)
        if x is None:
            x = white_excitation(settle + n, rate, rms, f_max, rng)
        if len(x) < settle + n:
            msg = (f"the {d} excitation holds {len(x)} samples; the measurement needs "
                   f"{settle + n} ({SETTLE_S:g} s of settling, then {averages} averages)")
            raise ValueError(msg)
        drives.append(np.asarray(x, dtype=np.float64)[: settle + n])
    copies = [replace(cfg, name=f"{cfg.name}_{d}") for d in dofs]
    loops = [c.loop() for c in copies]
    for lp in loops:
        lp.plant = plant or lp.plant
    engine = Engine(loops, {c.name: c.noise for c in copies}, seed=seed, rate_hz=rate,
                    osems=False)
    keep = settle if highpass_hz else 0  # samples kept before the averages, for the filter
    points = POINTS if estimator == "lpm" else ("IN1", "OUT")  # Welch's IN2: _welch_column
    record = {p: np.zeros((len(dofs), len(DOFS), n + keep)) for p in points}
    chunk, done = int(rate), 0
    buf = engine.new_block(chunk)  # one block filled again and again: no fresh pages each step
    exc = np.zeros((len(dofs), len(DOFS), chunk))
    while done < settle + n:
        k = min(chunk, settle + n - done)
        for i, d in enumerate(dofs):
            exc[i, DOFS.index(d), :k] = drives[i][done:done + k]
        block = engine.step(k, exc=exc[:, :, :k], out=buf if k == chunk else None)
        a, b = max(done - settle + keep, 0), done + k - settle + keep
        if b > 0:
            for p in points:
                record[p][:, :, a:b] = getattr(block, p.lower())[:, :, k - (b - a):]
        done += k
        if progress:
            progress(done / (settle + n))
    columns, freq, navg, exc_psd, estimates = {}, None, averages, {}, {}
    for i, d in enumerate(dofs):
        x = drives[i][settle - keep:]
        ys = [record[p][i, j] for j in range(len(DOFS)) for p in points]
        if highpass_hz:
            x, *ys = highpassed([x, *ys], rate, highpass_hz, keep)
        if estimator == "lpm":
            keys = [(r, p) for r in DOFS for p in POINTS]
            est, columns[d] = lpm_column(x, ys, rate, keys, 4 * f_max)
            freq, navg, estimates[d] = est.frequency_hz, est.averages, est
            continue
        exc_psd[d] = np.empty(nperseg // 2 + 1)
        freq, h, g2, navg = welch_tfs(x, ys, rate, nperseg, overlap, window=window,
                                      psd=exc_psd[d])
        columns[d] = _welch_column(h, g2, d)
    if estimates:
        return with_lpm(assemble(cfg.name, freq, columns, navg), estimates)
    return assemble(cfg.name, freq, columns, navg, window=window, exc_psd=exc_psd)


def _welch_column(h: NDArray[np.complex128], g2: NDArray[np.float64], excited: str
                  ) -> dict[tuple[str, str], tuple[NDArray, NDArray]]:
    """One excited DOF's column of TFs and coherences from Welch's IN1 and OUT estimates
    (rows IN1, OUT of each DOF in turn), IN2's derived from IN1's.

    The engine's IN2 is IN1 + EXC, sample by sample, and windows, means and transforms are
    linear: IN2/EXC is IN1/EXC, plus 1 on the excited DOF, and its coherence follows from
    IN1's, ``|H + 1|^2 / (|H|^2 / g2 + 2 Re H + 1)`` (IN2's auto-spectrum over EXC's). Four
    transforms a segment of thirteen are saved, the estimates equal to rounding.
    """
    column = {}
    for j, dof in enumerate(DOFS):
        h1, c1 = h[2 * j], g2[2 * j]
        column[(dof, "IN1")] = (h1, c1)
        column[(dof, "OUT")] = (h[2 * j + 1], g2[2 * j + 1])
        if dof != excited:
            column[(dof, "IN2")] = (h1, c1)
            continue
        power = np.divide(np.abs(h1) ** 2, c1, out=np.full(c1.shape, np.inf), where=c1 > 0)
        column[(dof, "IN2")] = (h1 + 1.0, np.abs(h1 + 1.0) ** 2 / (power + 2 * h1.real + 1.0))
    return column


def _averaged(rate: float, bw: float, averages: int, overlap: float) -> tuple[int, int]:
    """Samples per Welch segment, and the samples `averages` overlapping segments span."""
    nperseg = int(round(rate / bw))
    return nperseg, nperseg + (averages - 1) * (nperseg - int(nperseg * overlap))


def record_measurement(cfg: OpticConfig, path: str | Path, dofs: Sequence[str] = ("POS", "PIT", "YAW"),
                       *, bw: float = 0.05, averages: int = 10, overlap: float = 0.5,
                       rms: float = 1.0, f_max: float = 30.0, seed: int = 0,
                       plant: Plant | None = None, ifo: str = "C1",
                       gps_start: float = 1.4e9, events: bool = True) -> Path:
    """The measurement :func:`measure_tfs` makes, recorded as a twin session: `cfg`'s optic
    excited on each DOF in turn (white noise, :data:`SETTLE_S` of settling then enough for
    `averages`), its test points written to an MCAP file with the injection events
    ``twind tf`` reads (``from_session(path, bw, settle_s=SETTLE_S)``).

    Parameters
    ----------
    cfg : OpticConfig
        The optic as it "really" is.
    path : str or Path
        MCAP file to create.
    dofs, bw, averages, overlap, rms, f_max, seed, plant
        As :func:`measure_tfs`.
    ifo : str
        Channel-name prefix.
    gps_start : float
        GPS time of the first sample.
    events : bool
        Whether the injection events are written (not: as the data system records, the
        excitations left to be found in EXC).

    Returns
    -------
    Path
    """

    rate = cfg.sus.sample_rate_hz
    needed = int(SETTLE_S * rate) + _averaged(rate, bw, averages, overlap)[1]
    n = int(np.ceil(needed / BLOCK)) * BLOCK  # whole engine blocks
    loop = cfg.loop()
    loop.plant = plant or loop.plant
    engine = Engine([loop], {cfg.name: cfg.noise}, seed=seed, rate_hz=rate)
    rng = np.random.default_rng(seed)
    points = {dof_channel(ifo, cfg.name, d, p) for d in DOFS for p in ("EXC", *POINTS)}
    with SessionWriter(path, ifo, gps_start, {"optics": [cfg.name]},
                       channels=points.__contains__) as w:
        for k, dof in enumerate(dofs):
            start = gps_start + k * n / rate
            event = {"id": f"exc-{k}", "channel": dof_channel(ifo, cfg.name, dof, "EXC"),
                     "start_gps": start, "request": {"waveform": "noise", "amp": rms,
                                                     "duration": n / rate}}
            if events:
                w.write_event({"event": "start", "gps": start, **event})
            exc = np.zeros((1, len(DOFS), n))
            exc[0, DOFS.index(dof)] = white_excitation(n, rate, rms, f_max, rng)
            for a in range(0, n, BLOCK):
                w.write_block(engine.step(BLOCK, exc=exc[:, :, a:a + BLOCK]))
            if events:
                w.write_event({"event": "end", "gps": start + n / rate, **event})
    return Path(path)
