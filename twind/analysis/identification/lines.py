"""Narrow lines above the pendulum band in an optic's readings, such as its wires' violin
modes: each line's frequency and, from how it rings down, its Q.

A violin mode rings for minutes (Q of 1e5 to 1e7 at 0.5 to 3 kHz), so a spectrum of a recording
minutes long cannot resolve its width; its decay can, as LIGO measures violin Qs. Each line is
found in the readings' averaged spectra (:data:`SEGMENT_S` segments) as a bin standing above
the median of its neighbours as Gaussian noise would in one of 1e9 bins of all the readings
(:data:`FALSE_ALARM`; the median's own scatter aside), in the reading that sees it best, and
kept if at least 5 segments hold it :data:`SNR` times above the noise. That reading is
demodulated at the line (refined on the whole recording's spectrum) in the same segments, and
``A exp((-gamma + 2 pi i delta) t)`` is fitted to the segments' complex amplitudes, all of
them, in the complex plane, where the noise adds alike to each: ``f = f_line + delta`` and
``Q = pi f / gamma``, with standard errors from the residuals. A decay within :data:`DECAY_SIGMA`
of its standard error is not resolved and the line's Q is given as a lower bound: a mode still
driven, a mode too slow for the recording, or a line that is no mode (the mains' harmonics are
steady). Two modes closer than the segments resolve (2 Hz: peaks are 3 bins apart at least, and
a 1 s Hann segment's main lobe is 2 Hz wide) are one line, and their beat biases its Q.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, signal, stats
from scipy.optimize import least_squares

from twind import DOFS, OSEMS
from twind.config import OpticConfig
from twind.errors import TwindError
from twind.model.violin import PairReading, read_pair, segment_modes, violin_modes
from twind.simulation.engine import Engine

MIN_HZ = 100.0
"""Lowest frequency searched: above the pendulum, bounce and roll modes."""

SEGMENT_S = 1.0
"""Seconds per segment of the spectra and of the demodulation: 1 Hz bins."""

NEIGHBOURS_HZ = 25.0
"""Width of the running median a bin is compared with."""

FALSE_ALARM = 1e-9
"""Probability per bin, over all the readings, that Gaussian noise stands as high over its
neighbours' median as a line must: the threshold falls as the segments averaged grow in
number (4.2 for 8 s of five readings, 1.4 for 200 s)."""

HANN_OVERLAP = 0.167
"""Squared correlation of two Hann-windowed segments overlapping by half: Welch's averaged
spectrum of ``K`` segments has the variance of ``K / (1 + 2 * 0.167)`` independent ones."""

NEAR = 0.25
"""A model's violin mode names a line within this fraction of its frequency (ETMX's measured
pair lies 7 % and 18 % above its model's)."""

DECAY_SIGMA = 3.0
"""Decay rates within this many standard errors of zero are not resolved."""

SNR = 5.0
"""A line is kept when at least 5 of its segments' amplitudes are this many times the
noise's (all segments enter its fit)."""

MOST = 20
"""Lines reported at most, the strongest."""

DRIVE_CT = 30000.0
"""The drive (ct) :func:`violin_ringdown` rings a mode with: near a 16-bit DAC's range."""


@dataclass(frozen=True)
class Line:
    """One narrow line and how it rang.

    Attributes
    ----------
    frequency_hz, frequency_sigma_hz : float
        Its frequency and standard error.
    q, q_sigma : float
        Its quality factor and standard error; NaN when its decay is not resolved.
    q_lower : float
        A lower bound of Q (the decay rate plus :data:`DECAY_SIGMA` standard errors):
        what the recording says when it does not resolve the decay; NaN for a line growing
        beyond doubt.
    amplitude : float
        Its amplitude at the start of the fitted segments, in the reading's unit.
    reading : str
        The reading that sees it best.
    state : str
        ``"ringing down"``, ``"growing"`` or ``"steady"`` (decay not resolved).
    decay_per_s, decay_sigma_per_s : float
        The fitted decay rate ``gamma`` (``Q = pi f / gamma``) and its standard error.
    times_s, segments : ndarray
        Each segment's middle (s from the first) and complex amplitude at the line, which
        the decay was fitted to (not in :meth:`to_json`).
    """

    frequency_hz: float
    frequency_sigma_hz: float
    q: float
    q_sigma: float
    q_lower: float
    amplitude: float
    reading: str
    state: str
    decay_per_s: float = math.nan
    decay_sigma_per_s: float = math.nan
    times_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False,
                                         compare=False)
    segments: NDArray[np.complex128] = field(default_factory=lambda: np.zeros(0, complex),
                                             repr=False, compare=False)

    def text(self, unit: str = "") -> str:
        """One line for a person, the amplitude in `unit`."""
        f = f"{self.frequency_hz:.4f} Hz +- {1e3 * self.frequency_sigma_hz:.2g} mHz"
        if self.state == "ringing down":
            q = f"Q {self.q:.3g} +- {self.q_sigma:.2g}"
        else:
            q = self.state if math.isnan(self.q_lower) else f"{self.state}, Q > {self.q_lower:.3g}"
        return f"{f}, {q}, {self.amplitude:.3g} {unit} in {self.reading}".replace("  ", " ")

    def to_json(self) -> dict:
        """Its numbers and names, NaN as null."""
        return {k: (None if isinstance(v, float) and math.isnan(v) else v)
                for k, v in self.__dict__.items() if k not in ("times_s", "segments")}


def find_lines(readings: NDArray[np.float64], rate_hz: float, names: Sequence[str],
               min_hz: float = MIN_HZ) -> list[Line]:
    """The narrow lines in `readings` above `min_hz`, strongest first (at most :data:`MOST`).

    Parameters
    ----------
    readings : ndarray, shape (k, n)
        Signals of one optic, e.g. its five OSEMs (um).
    rate_hz : float
        Their sample rate.
    names : sequence of str
        The readings' names, e.g. ``OSEMS``.
    min_hz : float
        The lowest frequency searched.

    Returns
    -------
    list of Line
        Empty when the readings hold no line, or their rate reaches no higher than `min_hz`.

    Raises
    ------
    TwindError
        If the readings are shorter than 8 segments or not one per name.
    """
    x = np.asarray(readings, dtype=float)
    if x.ndim != 2 or x.shape[0] != len(names):
        msg = f"expected {len(names)} readings ({', '.join(names)}), got shape {x.shape}"
        raise TwindError(msg)
    if not np.all(np.isfinite(x)):
        bad = [names[k] for k in np.flatnonzero(~np.isfinite(x).all(axis=1))]
        msg = f"the readings of {', '.join(bad)} hold NaN or infinite samples (a gap?)"
        raise TwindError(msg)
    nseg = int(round(SEGMENT_S * rate_hz))
    if x.shape[1] < 8 * nseg:
        msg = (f"a recording of {x.shape[1] / rate_hz:.1f} s is too short to find lines "
               f"(at least {8 * SEGMENT_S:g} s)")
        raise TwindError(msg)
    if rate_hz / 2 <= min_hz:
        return []
    f, psd = signal.welch(x, fs=rate_hz, nperseg=nseg, axis=1)
    width = max(3, int(NEIGHBOURS_HZ * SEGMENT_S) | 1)
    floor = np.maximum(ndimage.median_filter(psd, size=(1, width), mode="nearest"),
                       np.finfo(float).tiny)
    ratio = psd / floor
    best = ratio.max(axis=0)
    best[(f < min_hz) | (f > 0.98 * rate_hz / 2)] = 0.0
    height = _threshold(x.shape[1] // nseg, len(names))
    peaks, _ = signal.find_peaks(best, height=height, distance=3)
    peaks = peaks[np.argsort(best[peaks])[::-1]][:MOST]
    spectra: dict[int, NDArray[np.complex128]] = {}
    lines = []
    for k in peaks:
        row = int(np.argmax(ratio[:, k]))
        if row not in spectra:
            spectra[row] = np.fft.rfft(x[row] - x[row].mean())
        f0 = _refined(spectra[row], x.shape[1], rate_hz, f[k])
        line = _ringing(x[row], rate_hz, f0, floor[row, k], names[row])
        if line is not None:
            lines.append(line)
    return lines


def _threshold(m: int, readings: int) -> float:
    """The power over the median that Gaussian noise exceeds with probability
    :data:`FALSE_ALARM` in any of `readings` readings, in Welch's average of the ``2 m - 1``
    half-overlapping segments of a recording `m` segments long: a gamma variable of the
    shape of that many independent segments (:data:`HANN_OVERLAP`)."""
    k = 2 * m - 1
    shape = k / (1 + 2 * HANN_OVERLAP * (k - 1) / k)
    noise = stats.gamma(shape, scale=1 / shape)
    return float(noise.isf(FALSE_ALARM / readings) / noise.median())


def _refined(spectrum: NDArray[np.complex128], n: int, rate_hz: float, near_hz: float) -> float:
    """The frequency of the largest bin of the whole recording's `spectrum` within a segment
    bin of `near_hz`: a phase step between segments well within pi."""
    df = rate_hz / n
    lo, hi = int((near_hz - 1 / SEGMENT_S) / df), int((near_hz + 1 / SEGMENT_S) / df) + 1
    return (lo + int(np.argmax(np.abs(spectrum[lo:hi])))) * df


def _ringing(x: NDArray[np.float64], rate_hz: float, f0: float, floor: float,
             name: str) -> Line | None:
    """The line at `f0` in `x`, on a noise of one-sided density `floor` (unit^2/Hz): its
    segments' amplitudes and the fits of their decay and phase; None when fewer than 5
    segments stand above the noise."""
    nseg = int(round(SEGMENT_S * rate_hz))
    m = x.size // nseg
    window = np.hanning(nseg)
    # segment k's sum of w x exp(-2 pi i f0 t): its own phasor times the first segment's
    kernel = window * np.exp(-2j * np.pi * f0 * np.arange(nseg) / rate_hz)
    a = (x[:m * nseg].reshape(m, nseg) @ kernel) * np.exp(-2j * np.pi * f0 * nseg / rate_hz
                                                         * np.arange(m))
    a *= 2 / window.sum()
    # white noise of density S gives E|a|^2 = 2 S rate sum(w^2) / sum(w)^2
    noise = math.sqrt(2 * floor * rate_hz * (window**2).sum()) / window.sum()
    if np.count_nonzero(np.abs(a) > SNR * noise) < 5:
        return None
    tk = (np.arange(m) + 0.5) * SEGMENT_S
    amplitude, gamma, f, cov = _fit_ringdown(tk, a, f0)
    sigma, f_sigma = (float(x) for x in np.sqrt(np.abs(np.diag(cov)[2:])))
    bound = gamma + DECAY_SIGMA * sigma
    q_lower = np.pi * f / bound if bound > 0 else math.nan
    fitted = {"decay_per_s": gamma, "decay_sigma_per_s": sigma, "times_s": tk, "segments": a}
    if gamma > DECAY_SIGMA * sigma:
        q = np.pi * f / gamma
        return Line(f, f_sigma, q, q * sigma / gamma, q_lower, amplitude, name, "ringing down",
                    **fitted)
    state = "growing" if gamma < -DECAY_SIGMA * sigma else "steady"
    return Line(f, f_sigma, math.nan, math.nan, q_lower, amplitude, name, state, **fitted)


def _fit_ringdown(t: NDArray[np.float64], a: NDArray[np.complex128], f0: float
                  ) -> tuple[float, float, float, NDArray[np.float64]]:
    """``A exp((-gamma + 2 pi i (f - f0)) t)`` fitted to the segments' amplitudes `a` at
    times `t`, in the complex plane, where the noise adds alike to every segment (the
    logarithm of a faint segment's amplitude would be biased, and leaving such segments out
    biases the decay).

    Returns
    -------
    amplitude : float
        ``|A|``.
    gamma, f : float
        The decay rate (1/s) and the frequency (Hz).
    cov : ndarray, shape (4, 4)
        Covariance of (Re A, Im A, gamma, f) from the residuals.
    """
    scale = np.abs(a).max()
    a = a / scale
    strong = np.flatnonzero(np.abs(a) > 0.5)
    if strong.size < 3:  # a fast decay or growth: three segments from the largest
        first = min(int(strong[0]), a.size - 3)
        strong = np.arange(first, first + 3)
    tf, af = t[strong], a[strong]
    slope, _ = np.polyfit(tf, np.log(np.abs(af)), 1, w=np.abs(af))
    dphase, _ = np.polyfit(tf, np.unwrap(np.angle(af)), 1, w=np.abs(af))
    shape = np.exp((slope + 1j * dphase) * (tf - tf[0]))
    start = (np.sum(af * np.conj(shape)) / np.sum(np.abs(shape) ** 2)
             * np.exp(-(slope + 1j * dphase) * tf[0]))

    def residual(p: NDArray[np.float64]) -> NDArray[np.float64]:
        r = a - (p[0] + 1j * p[1]) * np.exp((-p[2] + 2j * np.pi * p[3]) * t)
        return np.concatenate([r.real, r.imag])

    fit = least_squares(residual, [start.real, start.imag, -slope, dphase / (2 * np.pi)],
                        x_scale="jac", method="lm")
    dof = 2 * t.size - 4
    variance = np.sum(fit.fun**2) / dof
    units = np.array([scale, scale, 1.0, 1.0])  # A was fitted in units of the largest |a|
    cov = np.linalg.pinv(fit.jac.T @ fit.jac) * variance * np.outer(units, units)
    p = fit.x
    return float(scale * abs(p[0] + 1j * p[1])), float(p[2]), float(f0 + p[3]), cov


@dataclass(frozen=True)
class LineReport:
    """The lines of an optic's OSEM readings beside its model's violin modes.

    Attributes
    ----------
    optic : str
    found : tuple of Line
        As :func:`find_lines` found them, strongest first.
    model : tuple of (str, int, float, float)
        The model's violin modes up to the readings' Nyquist frequency: segment, order,
        frequency (Hz) and Q (:func:`twind.model.violin.segment_modes`).
    pair : PairReading or None
        The two strongest lines ringing down (so modes, not the mains) near the model's
        first violin modes (:data:`NEAR`), read as the segments' length or tension
        difference.
    """

    optic: str
    found: tuple[Line, ...]
    model: tuple[tuple[str, int, float, float], ...]
    pair: PairReading | None = None

    def nearest(self, line: Line) -> tuple[str, int, float, float] | None:
        """The model's violin mode nearest `line`, None when none lies within :data:`NEAR`
        of it."""
        if not self.model:
            return None
        near = min(self.model, key=lambda m: abs(m[2] - line.frequency_hz))
        return near if abs(line.frequency_hz / near[2] - 1) <= NEAR else None

    def lines(self) -> list[str]:
        """The lines, each with the model's nearest violin mode, for a person."""
        if not self.found:
            return [f"{self.optic}: no line above {MIN_HZ:g} Hz stands above the OSEM noise "
                    "(a violin mode rung up, e.g. through LSC_EXC, rings here for minutes)"]
        rows = [f"{self.optic} lines above {MIN_HZ:g} Hz: frequency, Q from the decay, "
                "amplitude and the OSEM seeing it best; the model's nearest violin mode"]
        for line in self.found:
            near = self.nearest(line)
            model = (f"; no model violin mode within {100 * NEAR:.0f} %" if near is None else
                     f"; model: segment {near[0]}'s n={near[1]} at {near[2]:.2f} Hz "
                     f"({100 * (line.frequency_hz / near[2] - 1):+.1f} %), Q {near[3]:.3g}")
            rows.append(f"  {line.text('um')}{model}")
        if self.pair is not None:
            rows += [f"  {row}" for row in self.pair.lines()]
        return rows

    def to_json(self) -> dict:
        """The ``lines`` of ``twind freeswing --json``."""
        def named(line: Line) -> dict:
            near = self.nearest(line)
            return {**line.to_json(), "model": None if near is None else {
                "segment": near[0], "n": near[1], "frequency_hz": near[2], "q": near[3]}}

        return {"found": [named(line) for line in self.found],
                "model": [{"segment": s, "n": n, "frequency_hz": f, "q": q}
                          for s, n, f, q in self.model],
                "pair": None if self.pair is None else asdict(self.pair)}


def violin_lines(optic: OpticConfig, sen: NDArray[np.float64], rate_hz: float) -> LineReport:
    """The lines of `optic`'s five OSEM readings `sen` (um) beside its violin modes.

    Parameters
    ----------
    optic : OpticConfig
        The model whose wires' violin modes name the lines (its ``violin_modes`` setting
        does not matter: the modes are the stiff-string formula's).
    sen : ndarray, shape (5, n)
        UL, UR, LL, LR, SIDE.
    rate_hz : float

    Returns
    -------
    LineReport
    """
    found = tuple(find_lines(sen, rate_hz, OSEMS))
    model = tuple(segment_modes(optic.wire_segments(), optic.sus.wire, rate_hz / 2))
    report = LineReport(optic.name, found, model)
    firsts = [line for line in found if line.state == "ringing down"
              and (near := report.nearest(line)) is not None and near[1] == 1]
    if len(firsts) < 2:
        return report
    return LineReport(optic.name, found, model,
                      pair_reading(optic, firsts[0].frequency_hz, firsts[1].frequency_hz))


def pair_reading(optic: OpticConfig, f_a_hz: float, f_b_hz: float) -> PairReading:
    """A measured pair of `optic`'s first violin modes read as its segments' length or
    tension difference (:func:`twind.model.violin.read_pair`), with its model's segment
    length and break-off separation."""
    length = float(np.mean([s.length_m for s in optic.wire_segments()]))
    return read_pair(f_a_hz, f_b_hz, length, optic.sus.R2_m)


def violin_ringdown(optic: OpticConfig, f_hz: float | None = None, ring_up_s: float = 1600.0,
                    duration_s: float = 400.0, seed: int = 0, drive_ct: float = DRIVE_CT
                    ) -> tuple[NDArray[np.float64], float, float]:
    """A violin mode of the twin rung up and let ring down, as LIGO measures violin Qs: a
    sine at `f_hz` into POS's LSC_EXC (the coils, past the damping filters) for `ring_up_s`,
    then `duration_s` of ringdown with the damping on and the twin's noise.

    Parameters
    ----------
    optic : OpticConfig
        An optic whose model keeps violin modes (``[suspension.wire] violin_modes``).
    f_hz : float, optional
        The drive's frequency; by default the model's violin mode a POS drive moves POS's
        IN1 most at.
    ring_up_s, duration_s : float
        Seconds of drive and of ringdown.
    seed : int
        Seed of the twin's noise.
    drive_ct : float
        The sine's amplitude (ct): the DAC's range rings a mode to ~1e-3 um in half an hour.

    Returns
    -------
    sen : ndarray, shape (5, n)
        The OSEM readings (um) of the ringdown.
    rate_hz, f_hz : float
        Their rate and the frequency driven.

    Raises
    ------
    TwindError
        If the optic's wires are rigid, or the times are not finite and >= 0.
    """
    if not (math.isfinite(ring_up_s) and ring_up_s >= 0 and math.isfinite(duration_s)
            and duration_s > 0):
        msg = f"ring-up and ringdown must be finite, >= 0 and > 0 s, got {ring_up_s}, {duration_s}"
        raise TwindError(msg)
    modes = violin_modes(optic.mechanics())
    if not modes:
        msg = (f"{optic.name}'s plant has rigid wires: set [suspension.wire] violin_modes "
               "(docs/etmx_violin.toml) to ring a violin mode")
        raise TwindError(msg)
    loop = optic.loop()
    if f_hz is None:
        at = np.array([f for _, f, _ in modes])
        f_hz = float(at[np.argmax(np.abs(loop.responses(at)["closed_loop_IN1_per_LSC"][:, 0, 0]))])
    engine = Engine([loop], {optic.name: optic.noise}, seed=seed, rate_hz=optic.rate_hz)
    rate = engine.rate_hz
    block = int(16 * rate)
    up = int(round(ring_up_s * rate))
    for a in range(0, up, block):
        k = min(block, up - a)
        lsc = np.zeros((1, len(DOFS), k))
        lsc[0, 0] = drive_ct * np.sin(2 * np.pi * f_hz * (a + np.arange(k)) / rate)
        engine.step(k, lsc=lsc)
    n = int(round(duration_s * rate))
    sen = np.empty((len(OSEMS), n))
    for a in range(0, n, block):
        b = min(n, a + block)
        sen[:, a:b] = engine.step(b - a).sen[0]
    return sen, rate, f_hz
