"""Whether an excitation may run: sane values for the model rate, and within a channel's limits.

An excitation that would exceed a limit is refused, never clipped: a clipped sine is no
longer the sine the commissioner analyses, and a silent change of the drive is worse than
a clear "no".
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from twind.excitation.design import (
    NOISE_PEAK_SIGMAS,
    multisine_plan,
    multisine_tones,
    noise_shape,
    taper,
)
from twind.excitation.request import (
    MAX_FINITE_SAMPLES,
    MAX_SAMPLES,
    MAX_TONES,
    WAVEFORMS,
    ExcitationError,
    ExcitationRequest,
    channel_match,
    typed,
)
from twind.limits import ServiceLimits



@dataclass(frozen=True)
class Limits:
    """What one ``_EXC`` channel tolerates.

    Attributes
    ----------
    peak : float
        Largest ``|sample|`` allowed (``math.inf``: no limit).
    rms : float
        Largest RMS allowed over the excitation (``math.inf``: no limit).
    """
    peak: float
    rms: float


DEFAULT_LIMITS = Limits(peak=ServiceLimits.exc_peak, rms=ServiceLimits.exc_rms)
"""A twin's limits when its configuration says nothing (:class:`~twind.config.ServiceLimits`)."""


def _positive(key: str, x: object) -> float:
    """A finite number > 0 (an ExcitationError naming `key` otherwise)."""
    if not (isinstance(x, numbers.Real) and not isinstance(x, bool)):
        raise ExcitationError(f"must be a number, got {type(x).__name__}", key)
    if not (math.isfinite(x) and x > 0):
        raise ExcitationError(f"must be a finite number > 0, got {x!r}", key)
    return float(x)


def _frequency(key: str, f: float | None, rate_hz: float, what: str) -> float:
    """A frequency strictly between 0 and Nyquist."""
    if f is None:
        raise ExcitationError(f"missing: {what}", key)
    if math.isnan(f) or math.isinf(f):
        raise ExcitationError(f"must be a finite frequency (Hz), got {f!r}", key)
    if f <= 0:
        raise ExcitationError(f"must be a frequency above 0 Hz, got {f!r} Hz", key)
    if f >= rate_hz / 2:
        raise ExcitationError(f"{f:g} Hz is at or above the Nyquist frequency {rate_hz / 2:g} "
                              f"Hz of the {rate_hz:g} Hz model", key)
    return f


def _level(req: ExcitationRequest, rate_hz: float) -> tuple[float, float, str]:
    """Peak and RMS of what the request will send, and how the peak was found (for messages).

    For deterministic waveforms the untapered (steady-state) levels are used: a taper
    only lowers them.  For a stream, whose samples may be largest where the taper acts,
    the tapered samples themselves are measured.
    """
    wf = req.waveform
    if wf in ("sine", "sweep"):
        return req.amp, req.amp / math.sqrt(2.0), ""
    if wf == "noise":
        # Gaussian: |x| > 6 sigma has probability 2e-9 a sample (once in ~8 h at 16384 Hz)
        return (NOISE_PEAK_SIGMAS * req.amp, req.amp,
                f" (Gaussian noise is taken to peak at {NOISE_PEAK_SIGMAS:g} x its RMS, "
                "6 sigma)")
    if wf == "multisine":
        tones = multisine_tones(req.freq, req.f_stop, req.n_tones, req.freqs)
        plan = multisine_plan(tuple(float(f) for f in tones), rate_hz)
        # The peak of one exact period is the peak for ever (the signal is periodic).
        return (req.amp * float(np.max(np.abs(plan.period))), req.amp * plan.rms,
                " (true peak of one period)")
    s = np.asarray(req.samples)
    n = s.size
    with np.errstate(over="ignore"):  # samples near 1e308: an infinite RMS, refused below
        return _stream_level(s, n, min(int(round(req.ramp * rate_hz)), n // 2))


def _stream_level(s: np.ndarray, n: int, r: int) -> tuple[float, float, str]:
    """Peak and RMS of a stream of `n` samples after tapers of `r` samples."""
    if r:
        head = np.arange(r, dtype=np.int64)
        tail = np.arange(n - r, n, dtype=np.int64)
        edges = np.concatenate([s[:r] * taper(head, r, n), s[n - r:] * taper(tail, r, n)])
        mid = s[r:n - r]
        peak = max(float(np.max(np.abs(edges))), float(np.max(np.abs(mid), initial=0.0)))
        ms = (float(np.sum(edges**2)) + float(np.sum(mid**2))) / n
    else:
        peak, ms = float(np.max(np.abs(s))), float(np.mean(s**2))
    return peak, math.sqrt(ms), ""


def check(req: ExcitationRequest, limits: Limits, rate_hz: float,
          max_samples: int = MAX_SAMPLES) -> None:
    """Refuse, with a reason, any excitation that cannot or must not run.

    Parameters
    ----------
    req : ExcitationRequest
        The request, from :meth:`ExcitationRequest.from_json` or built directly (its field
        types are checked too).
    limits : Limits
        The channel's peak and RMS limits.
    rate_hz : float
        Model rate, e.g. 16384.
    max_samples : int
        Longest stream accepted (its length is checked before its values are looked at).

    Raises
    ------
    ExcitationError
        The first problem found, naming the field: a malformed channel; an unknown
        waveform; a NaN, infinite or negative amplitude; a negative or NaN duration or ramp,
        a ramp longer than half the duration, an infinite sweep; a frequency that is
        missing, not finite, <= 0 or at/above Nyquist; a multisine with neither `n_tones`
        nor `freqs`, both, more than 1000 tones, repeated tones or tones too close to tell
        apart; a noise shape foton cannot read (its message), that is unstable or has no
        gain; a stream without samples, with non-finite samples or with more than
        `max_samples`; a peak above ``limits.peak`` or an RMS above ``limits.rms``.  For
        noise the peak is taken as 6 x the RMS (Gaussian, 6 sigma); for a multisine it is
        the true peak of its exactly periodic period.

    Notes
    -----
    The RMS compared with ``limits.rms`` is that of the whole excitation without its taper
    (sine and sweep: ``amp / sqrt(2)``; multisine: of its period; noise: ``amp``), except for
    a stream, whose tapered samples are measured.
    """
    rate_hz = _check_arguments(limits, rate_hz, max_samples)
    req = typed(req, max_samples)
    channel_match(req.channel)
    if req.waveform not in WAVEFORMS:
        raise ExcitationError(f"{req.waveform!r:.40} is not one of {', '.join(WAVEFORMS)}",
                              "waveform")
    _check_timing(req, rate_hz)
    _check_waveform(req, rate_hz)
    _check_level(req, limits, rate_hz)


def _check_arguments(limits: Limits, rate_hz: float, max_samples: int) -> float:
    """The caller's side of :func:`check`: the limits, the rate (returned as a float) and
    the longest stream."""
    if not isinstance(max_samples, int) or max_samples < 1:
        raise ExcitationError(f"must be a positive integer, got {max_samples!r}", "max_samples")
    rate_hz = _positive("rate_hz", rate_hz)
    if not isinstance(limits, Limits):
        raise ExcitationError(f"expected Limits, got {type(limits).__name__}", "limits")
    for key in ("peak", "rms"):
        v = getattr(limits, key)
        if not (isinstance(v, numbers.Real) and not isinstance(v, bool) and v >= 0):
            # NaN fails v >= 0 too: a NaN limit would otherwise let everything through
            raise ExcitationError(f"must be a number >= 0 (inf: no limit), got {v!r}",
                                  f"limits.{key}")
    return rate_hz


def _check_timing(req: ExcitationRequest, rate_hz: float) -> None:
    """Amplitude, ramp, start, seed and duration: each a number in its range, the ramp at
    most half the duration."""
    wf = req.waveform
    if wf != "stream" and not (math.isfinite(req.amp) and req.amp >= 0):
        raise ExcitationError(f"must be a finite number >= 0, got {req.amp!r}", "amp")
    if not (math.isfinite(req.ramp) and req.ramp >= 0):
        raise ExcitationError(f"must be a finite number of seconds >= 0, got {req.ramp!r}",
                              "ramp")
    if req.ramp * rate_hz > MAX_FINITE_SAMPLES:  # its stop would ramp down as long
        raise ExcitationError(f"{req.ramp:g} s is longer than any excitation may run",
                              "ramp")
    if req.start_gps is not None and not (math.isfinite(req.start_gps) and req.start_gps >= 0):
        raise ExcitationError(f"must be a GPS time >= 0 or null, got {req.start_gps!r}",
                              "start_gps")
    if req.seed < 0:
        raise ExcitationError(f"must be >= 0, got {req.seed}", "seed")
    duration = _duration(req, rate_hz)
    if req.ramp > duration / 2:
        raise ExcitationError(f"{req.ramp:g} s is longer than half the duration "
                              f"({duration:g} s)", "ramp")


def _duration(req: ExcitationRequest, rate_hz: float) -> float:
    """The excitation's duration (s; a stream's from its samples), checked."""
    if req.waveform == "stream":
        if req.samples is None or req.samples.size == 0:
            raise ExcitationError("a stream needs at least one sample", "samples")
        return req.samples.size / rate_hz
    duration = req.duration
    if math.isnan(duration) or duration <= 0:
        raise ExcitationError(f"must be a number of seconds > 0, got {duration!r}",
                              "duration")
    if math.isinf(duration) and req.waveform == "sweep":
        raise ExcitationError("a sweep needs a finite duration", "duration")
    if math.isfinite(duration):
        n = duration * rate_hz  # may overflow to inf: compare before rounding
        if n > MAX_FINITE_SAMPLES:
            raise ExcitationError(f"{duration:g} s is too long for a finite excitation; "
                                  "use inf to run until stopped", "duration")
        if round(n) < 1:
            raise ExcitationError(f"{duration!r} s is shorter than one sample at "
                                  f"{rate_hz:g} Hz", "duration")
    return duration


def _check_waveform(req: ExcitationRequest, rate_hz: float) -> None:
    """The waveform's own parameters: frequencies, tones, noise shape, samples."""
    wf = req.waveform
    if wf == "sine":
        _frequency("freq", req.freq, rate_hz, "a sine needs its frequency")
    elif wf == "sweep":
        _frequency("freq", req.freq, rate_hz, "a sweep needs its start frequency")
        _frequency("f_stop", req.f_stop, rate_hz, "a sweep needs its end frequency")
    elif wf == "multisine":
        _check_multisine(req, rate_hz)
    elif wf == "noise":
        if req.shape is not None:
            noise_shape(req.shape, rate_hz)
    elif not np.all(np.isfinite(req.samples)):
        j = int(np.flatnonzero(~np.isfinite(req.samples))[0])
        raise ExcitationError(f"sample {j} is {req.samples[j]!r}; every sample must be finite",
                              "samples")


def _check_level(req: ExcitationRequest, limits: Limits, rate_hz: float) -> None:
    """The excitation's peak and RMS within the channel's limits: refused, never clipped."""
    peak, rms, how = _level(req, rate_hz)
    field = "amp" if req.waveform != "stream" else "samples"
    if peak > limits.peak:
        raise ExcitationError(
            f"the peak {peak:.6g}{how} exceeds the limit {limits.peak:.6g} of "
            f"{req.channel}; lower the amplitude (excitations are refused, never clipped)",
            field)
    if rms > limits.rms:
        raise ExcitationError(
            f"the RMS {rms:.6g} exceeds the limit {limits.rms:.6g} of {req.channel}; lower "
            "the amplitude (excitations are refused, never clipped)", field)


def _check_multisine(req: ExcitationRequest, rate_hz: float) -> None:
    """Tones given one way or the other, not too many, distinct, between 0 and Nyquist."""
    if req.freqs is not None:
        if req.n_tones is not None or req.freq is not None or req.f_stop is not None:
            raise ExcitationError("give either freqs or n_tones with freq and f_stop, not "
                                  "both", "freqs")
        if not req.freqs:
            raise ExcitationError("a multisine needs at least one tone", "freqs")
        if len(req.freqs) > MAX_TONES:
            raise ExcitationError(f"{len(req.freqs)} tones, more than the {MAX_TONES} a "
                                  "multisine may have", "freqs")
        for f in req.freqs:
            _frequency("freqs", f, rate_hz, "")
        if len(set(req.freqs)) != len(req.freqs):
            raise ExcitationError("a tone is repeated", "freqs")
        return
    if req.n_tones is None:
        raise ExcitationError("a multisine needs n_tones (with freq and f_stop) or freqs",
                              "n_tones")
    if not 1 <= req.n_tones <= MAX_TONES:
        raise ExcitationError(f"must be 1 to {MAX_TONES}, got {req.n_tones}", "n_tones")
    _frequency("freq", req.freq, rate_hz, "a multisine needs its lowest tone")
    if req.n_tones > 1 or req.f_stop is not None:
        _frequency("f_stop", req.f_stop, rate_hz, "a multisine needs its highest tone")
        if req.n_tones > 1 and not req.f_stop > req.freq:
            raise ExcitationError(f"the highest tone ({req.f_stop:g} Hz) must be above the "
                                  f"lowest ({req.freq:g} Hz)", "f_stop")

