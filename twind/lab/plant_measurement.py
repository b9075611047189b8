"""A virtual measurement of a state-space optic: its engine excited as diaggui excites a test
point, Welch's transfer functions written as diaggui saves them, in the site's names.

This is what proves the diagnosis of a plant known by its matrices: the data come from the
time-domain engine (:class:`~twind.simulation.statespace.StateSpaceEngine`) and Welch's
estimate (scipy.signal), never from the frequency-domain model the diagnosis fits, and a
change hidden in them is made to the model's own matrices (:func:`moved`, Brauer's update),
not to its modal form.

:func:`measure_chain` adds what lies between a real suspension and diaggui's numbers
(:class:`Chain`), applied to the readbacks' series before Welch's estimate: each readback's
coupling to another, sensor noise and coherence holes, a calibration and sign, a delay and a
first-order low-pass common to all, and a drive's electronic crosstalk.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import signal, special
from scipy.optimize import least_squares

from twind.analysis.estimation.diaggui import write_fft_measurement
from twind.config.statespace import StateSpaceOptic
from twind.model.statespace import StateSpace

BW_HZ = 1 / 128
"""diaggui's resolution in KAGRA's SRM measurement (its 0.01 Hz asked, rounded to 2^-7)."""


def moved(model: StateSpace, f_hz: float, factor: float, q: float | None = None
          ) -> tuple[StateSpace, float]:
    """`model` with the pole pair nearest `f_hz` moved to `factor` times its frequency (and
    to quality factor `q`, if given), every other pole where it was.

    Brauer's theorem: for a right eigenvector ``v`` of ``A`` (eigenvalue ``l``) and a left
    one ``u``, ``A + (l' - l) v u^T / (u^T v)`` has ``l'`` in place of ``l`` and the same
    other eigenvalues; with the conjugate pair's update added the matrix stays real. The
    mode's residues keep their shapes (its numerator changes with it, unlike the modal
    refit the diagnosis makes).

    Returns
    -------
    StateSpace
    float
        The mode's new frequency (Hz).
    """
    w, vr = np.linalg.eig(model.a)
    wl, vl = np.linalg.eig(model.a.T)
    k = int(np.argmin(np.abs(np.abs(w) / (2 * math.pi) - f_hz) + (w.imag <= 0)))
    lam = w[k]
    u = vl[:, int(np.argmin(np.abs(wl - lam)))]
    wn = abs(lam) * factor
    qn = q if q is not None else abs(lam) / (-2 * lam.real)
    new = -wn / (2 * qn) + 1j * wn * math.sqrt(max(1 - 1 / (4 * qn * qn), 0.0))
    update = (new - lam) * np.outer(vr[:, k], u) / (u @ vr[:, k])
    return replace(model, a=model.a + 2 * update.real), float(wn / (2 * math.pi))


def measure(optic: StateSpaceOptic, drive: str, path: str | Path, *,
            model: StateSpace | None = None, averages: int = 5, bw_hz: float = BW_HZ,
            rate_hz: float = 512.0, amplitude: float = 1.0, noise: float = 1e-4,
            closed: Sequence[str] | None = (), stop_hz: float = 100.0, seed: int = 0) -> Path:
    """Excite `drive` of `optic` with white noise and write diaggui's FFT measurement.

    Parameters
    ----------
    optic : StateSpaceOptic
    drive : str
        A TEST point (``TM_TEST_P``) or a damping loop (``IM_DAMP_L``): its EXC is channel A.
    path : path
        The XML to write (never overwritten).
    model : StateSpace, optional
        The plant the engine integrates instead of the optic's (a changed one, the truth).
    averages : int
        Welch averages (segments of ``1 / bw_hz``, half overlapped).
    bw_hz : float
        Resolution.
    rate_hz : float
        The engine's rate (its zero-order hold is a delay of half a cycle).
    amplitude : float
        The excitation's RMS (model units).
    noise : float
        Each readback's white noise ASD over the excitation's (per rtHz).
    closed : sequence of str or None
        Damping loops closed (None: every loop with a controller).
    stop_hz : float
        The last frequency written (diaggui's StopFrequency).
    seed : int

    Returns
    -------
    Path
    """
    truth = replace(optic, model=model) if model is not None else optic
    exc_asd = amplitude / math.sqrt(rate_hz / 2)
    engine = truth.engine(rate_hz=rate_hz, noise={r: noise * exc_asd for r in optic.readbacks},
                          seed=seed, closed=closed)
    nper = int(round(rate_hz / bw_hz))
    n = nper * (averages + 1) // 2
    rng = np.random.default_rng(seed + 1)
    settle = int(rate_hz * 100)  # the loops' and the pendulums' transients: 100 s
    x = amplitude * rng.standard_normal(settle + n)
    block = engine.step(settle + n, {f"{drive}_EXC": x})
    names = [c for c in block.channels if c != f"{drive}_EXC" and not c.endswith("_EXC")]
    if drive not in optic.loops:
        names = [c for c in names if c in optic.readbacks]
    exc = block.channels[f"{drive}_EXC"][settle:]
    f, pxx, tfs, cohs = scipy_transfers(exc, [block.channels[c][settle:] for c in names],
                                        rate_hz, nper)
    keep = f <= stop_hz
    return write_fft_measurement(path, optic.channel(f"{drive}_EXC"),
                                 [optic.channel(c) for c in names], f[keep], pxx[keep],
                                 tfs[:, keep], cohs[:, keep], averages, rate_hz)


def peak(f_hz: NDArray[np.float64], h: NDArray[np.complex128], near_hz: float,
         width: float = 0.1) -> float:
    """An independent fit of a resonance's frequency: a second-order section plus a constant
    and a slope, fitted by least squares to ``h`` within ``width`` (relative) of
    `near_hz`, started at the largest magnitude there and kept inside that window. Knows
    nothing of any model.

    Returns
    -------
    float
        The section's frequency (Hz).
    """
    sel = (f_hz > near_hz * (1 - width)) & (f_hz < near_hz * (1 + width)) & np.isfinite(h)
    f, y = f_hz[sel], h[sel]
    f0 = float(f[np.argmax(np.abs(y))])

    def model(p: NDArray) -> NDArray:
        s = 2j * np.pi * f
        w = 2 * np.pi * p[0]
        return ((p[2] + 1j * p[3]) / (s * s + s * w / p[1] + w * w) + p[4] + 1j * p[5]
                + (p[6] + 1j * p[7]) * (f - f0))

    def res(p: NDArray) -> NDArray:
        r = (model(p) - y) / np.abs(y).max()
        return np.concatenate([r.real, r.imag])

    w0 = 2 * np.pi * f0
    a0 = y[np.argmax(np.abs(y))] * 1j * w0 * w0 / 50
    lo = [f[0], 0.5, -np.inf, -np.inf, -np.inf, -np.inf, -np.inf, -np.inf]
    hi = [f[-1], 1e7, np.inf, np.inf, np.inf, np.inf, np.inf, np.inf]
    sol = least_squares(res, [f0, 50.0, a0.real, a0.imag, 0, 0, 0, 0], bounds=(lo, hi),
                        x_scale="jac")
    return float(sol.x[0])


# ------------------------------------------------------------------------ the measurement chain
DELAY_TAPS = 32
"""Half the length of the fractional delay's windowed sinc (a Kaiser window): the delay's
response within 3e-5 of ``exp(-i w tau)`` below a fifth of the rate."""
KAISER_BETA = 8.0


@dataclass(frozen=True)
class Coupling:
    """A readback that also reads another (its sensor sees that DOF): ``readback += eps x
    source``, in the model's units, before the calibration."""

    readback: str
    source: str
    eps: float


@dataclass(frozen=True)
class Crosstalk:
    """A drive's electronics in a readback: ``readback += c x EXC`` (counts per unit of the
    excitation), flat and in phase with the drive, after the calibration and the filters."""

    drive: str
    readback: str
    c: float


@dataclass(frozen=True)
class Hole:
    """Band-limited noise on a readback (a fourth-order Butterworth band-pass of white noise
    of this ASD, in the model's units per rtHz): no coherence there."""

    readback: str
    lo_hz: float
    hi_hz: float
    asd: float


@dataclass(frozen=True)
class Chain:
    """What lies between a suspension's outputs and diaggui's numbers.

    In the order a readback meets them (:meth:`apply`): the other readbacks it also reads,
    its sensor's noise and any band of extra noise, its calibration, the common delay and
    low-pass, and a drive's crosstalk. A readback's measured response is so
    ``g (H + eps H') F + c``, with ``F`` :meth:`common`'s.

    Attributes
    ----------
    calibration : mapping of str to float
        Each readback's counts per model unit (signed; 1 where not given).
    delay_s : float
        A delay common to every readback (a windowed-sinc FIR, fractional samples).
    lowpass_hz : float or None
        A first-order low-pass common to every readback, ``1 / (1 + s / w_c)`` discretised
        by the bilinear transform at the rate, not prewarped: the analogue response at a
        frequency warped by ``tan``, 0.26 % higher at 20 Hz for a rate of 512 Hz.
    noise : mapping of str to float
        Each readback's white sensor noise (model units per rtHz).
    couplings, crosstalk, holes : tuple
        See :class:`Coupling`, :class:`Crosstalk`, :class:`Hole`.
    """

    calibration: Mapping[str, float] = field(default_factory=dict)
    delay_s: float = 0.0
    lowpass_hz: float | None = None
    noise: Mapping[str, float] = field(default_factory=dict)
    couplings: tuple[Coupling, ...] = ()
    crosstalk: tuple[Crosstalk, ...] = ()
    holes: tuple[Hole, ...] = ()

    def lowpass(self, rate_hz: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The low-pass's digital filter ``(b, a)`` at `rate_hz` (``b = a = [1]``: none)."""
        if self.lowpass_hz is None:
            return np.array([1.0]), np.array([1.0])
        wc = 2 * math.pi * self.lowpass_hz
        b, a = signal.bilinear([wc], [1.0, wc], fs=rate_hz)
        return np.atleast_1d(b), np.atleast_1d(a)

    def common(self, f_hz: NDArray[np.float64], rate_hz: float) -> NDArray[np.complex128]:
        """What every readback's response is multiplied by at `f_hz`: the delay, the
        low-pass and the engine's hold of the drive over a cycle (half a cycle's delay)."""
        b, a = self.lowpass(rate_hz)
        _, lp = signal.freqz(b, a, worN=np.asarray(f_hz, dtype=float), fs=rate_hz)
        return lp * np.exp(-2j * math.pi * np.asarray(f_hz) * (self.delay_s + 0.5 / rate_hz))

    def to_json(self) -> dict:
        """Every term, by channel suffix."""
        return {"calibration": dict(self.calibration), "delay_s": self.delay_s,
                "lowpass_hz": self.lowpass_hz, "noise_asd": dict(self.noise),
                "couplings": [vars(c) for c in self.couplings],
                "crosstalk": [vars(c) for c in self.crosstalk],
                "holes": [vars(h) for h in self.holes]}

    def apply(self, drive: str, exc: NDArray[np.float64],
              outputs: Mapping[str, NDArray[np.float64]], rate_hz: float,
              rng: np.random.Generator) -> dict[str, NDArray[np.float64]]:
        """The readbacks as recorded, from the suspension's noiseless `outputs` (model units,
        by channel suffix) when `drive`'s `exc` drove it, each term in the class's order."""
        out = {r: y.copy() for r, y in outputs.items()}
        for c in self.couplings:
            out[c.readback] += c.eps * outputs[c.source]
        for r in out:
            out[r] += self.noise.get(r, 0.0) * math.sqrt(rate_hz / 2) * \
                rng.standard_normal(exc.size)
        for h in self.holes:
            sos = signal.butter(4, [h.lo_hz, h.hi_hz], btype="bandpass", fs=rate_hz,
                                output="sos")
            out[h.readback] += signal.sosfilt(
                sos, h.asd * math.sqrt(rate_hz / 2) * rng.standard_normal(exc.size))
        b, a = self.lowpass(rate_hz)
        for r in out:
            y = self.calibration.get(r, 1.0) * out[r]
            out[r] = signal.lfilter(b, a, delayed(y, self.delay_s * rate_hz))
        for c in self.crosstalk:
            if c.drive == drive:
                out[c.readback] += c.c * exc
        return out


def delayed(x: NDArray[np.float64], samples: float) -> NDArray[np.float64]:
    """`x` delayed by `samples` (fractional): a Kaiser-windowed sinc of
    2 x :data:`DELAY_TAPS` taps. The first ``samples + DELAY_TAPS`` outputs and the last
    :data:`DELAY_TAPS` are not exact (the record's ends)."""
    if samples == 0:
        return x.copy()
    centre = samples + DELAY_TAPS
    n = np.arange(int(math.floor(centre)) + DELAY_TAPS + 1)
    u = (n - centre) / (DELAY_TAPS + 1)
    window = np.where(np.abs(u) < 1, special.i0(KAISER_BETA * np.sqrt(
        np.clip(1 - u * u, 0, None))) / special.i0(KAISER_BETA), 0.0)
    taps = np.sinc(n - centre) * window
    return signal.oaconvolve(x, taps / taps.sum())[DELAY_TAPS:DELAY_TAPS + x.size]


def measure_chain(optic: StateSpaceOptic, drive: str, path: str | Path, chain: Chain, *,
                  model: StateSpace | None = None, averages: int = 5, bw_hz: float = BW_HZ,
                  rate_hz: float = 512.0, amplitude: float = 1.0, stop_hz: float = 20.0,
                  settle_s: float = 100.0, seed: int = 0) -> Path:
    """Excite `drive` of `optic` (open loop) with white noise, pass every readback through
    `chain` and write diaggui's FFT measurement of them all over the EXC.

    Parameters
    ----------
    optic : StateSpaceOptic
    drive : str
        A TEST point (``TM_TEST_P``).
    path : path
        The XML to write (never overwritten).
    chain : Chain
    model : StateSpace, optional
        The plant the engine integrates instead of the optic's (the truth).
    averages, bw_hz, rate_hz, amplitude, stop_hz : float
        As :func:`measure`'s.
    settle_s : float
        Integrated before the record (the pendulums' transients).
    seed : int

    Returns
    -------
    Path
    """
    nper = int(round(rate_hz / bw_hz))
    n = nper * (averages + 1) // 2
    settle = int(settle_s * rate_hz)
    exc, outputs = run_open_loop(optic, drive, settle + n + 2 * DELAY_TAPS, model=model,
                                 rate_hz=rate_hz, amplitude=amplitude, seed=seed)
    recorded = chain.apply(drive, exc, outputs, rate_hz, np.random.default_rng(seed + 2))
    keep = slice(settle, settle + n)
    f, pxx, tfs, cohs = scipy_transfers(exc[keep], [recorded[r][keep] for r in outputs],
                                        rate_hz, nper)
    band = f <= stop_hz
    return write_fft_measurement(path, optic.channel(f"{drive}_EXC"),
                                 [optic.channel(r) for r in outputs], f[band], pxx[band],
                                 tfs[:, band], cohs[:, band], averages, rate_hz)


def run_open_loop(optic: StateSpaceOptic, drive: str, n: int, *,
                  model: StateSpace | None = None, rate_hz: float = 512.0,
                  amplitude: float = 1.0, seed: int = 0
                  ) -> tuple[NDArray[np.float64], dict[str, NDArray[np.float64]]]:
    """`n` samples of white noise of RMS `amplitude` on `drive`'s EXC and every readback of
    `optic` (or of `model` in its place), noiseless, no loop closed."""
    truth = replace(optic, model=model) if model is not None else optic
    engine = truth.engine(rate_hz=rate_hz, closed=())
    x = amplitude * np.random.default_rng(seed + 1).standard_normal(n)
    block = engine.step(n, {f"{drive}_EXC": x})
    return x, {r: block.channels[r] for r in optic.readbacks}


def scipy_transfers(exc: NDArray[np.float64], ys: Sequence[NDArray[np.float64]],
                    rate_hz: float, nper: int) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Welch's (Hann, half-overlapped segments of `nper`) excitation PSD, and each series'
    transfer function over it and coherence, made with scipy.signal alone: the truth's
    measurements share no code with twind's estimators.

    Returns
    -------
    f, exc_psd : ndarray, shape (nf,)
    tf, coherence : ndarray, shape (len(ys), nf)
    """
    f, pxx = signal.welch(exc, fs=rate_hz, window="hann", nperseg=nper)
    tfs, cohs = [], []
    for y in ys:
        _, pxy = signal.csd(exc, y, fs=rate_hz, window="hann", nperseg=nper)
        _, pyy = signal.welch(y, fs=rate_hz, window="hann", nperseg=nper)
        tfs.append(pxy / pxx)
        with np.errstate(divide="ignore", invalid="ignore"):
            cohs.append(np.nan_to_num(np.abs(pxy) ** 2 / (pxx * pyy)))
    return f, pxx, np.array(tfs), np.array(cohs)
