"""The excitations of a recording found in its data, for recordings with no injection events
(the data system's: an awg or diaggui excitation leaves only its EXC test point).

An EXC channel reads exactly zero while nothing is injected; :func:`stretches` returns its
nonzero stretches, and :func:`recognise` what each one's waveform is (a sine, a multisine,
a swept sine or noise) from its spectrum and envelope, so that the estimator can be one
that fits it. :func:`at_one_rate` brings test points recorded at different rates (the
``_DQ`` channels of one model may be stored at 256 to 16384 Hz) to the slowest of them with
scipy's polyphase resampler, the channels resampled named in a warning.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, signal

from twind.channels import DOF_CHANNEL, dof_channel
from twind.errors import MeasurementWarning
from twind.recording.session import Channel, some_names

WAVEFORMS = ("sine", "multisine", "swept sine", "noise")
JOIN_S = 0.5
"""Zero runs shorter than this (s) inside a stretch are part of it: a waveform's own zeros."""
SHORTEST_S = 1.0
"""Nonzero runs shorter than this (s) are not excitations."""
LINE = 100.0
"""How far (power) a spectral line stands above the median of the 65 bins around it."""
TONAL = 0.9
"""Fraction of the power within two bins of lines that makes a waveform tonal."""
STEADY = 0.25
"""Relative scatter of the envelope below which a broadband waveform is a sweep (noise's
Rayleigh envelope scatters by 0.52)."""


@dataclass(frozen=True)
class Stretch:
    """One excitation found in an EXC channel.

    Attributes
    ----------
    channel : str
    start, end : float
        GPS of its first sample and just after its last.
    waveform : str
        One of :data:`WAVEFORMS`.
    tones_hz : tuple of float
        The frequencies of a sine's or multisine's lines (empty otherwise).
    """

    channel: str
    start: float
    end: float
    waveform: str
    tones_hz: tuple[float, ...] = ()

    def __str__(self) -> str:
        tones = (f" at {', '.join(f'{f:.4g}' for f in self.tones_hz[:5])}"
                 f"{' ...' if len(self.tones_hz) > 5 else ''} Hz" if self.tones_hz else "")
        return (f"{self.channel}: GPS {self.start:.3f} to {self.end:.3f} "
                f"({self.end - self.start:.1f} s), {self.waveform}{tones}")


def stretches(ch: Channel, join_s: float = JOIN_S, shortest_s: float = SHORTEST_S
              ) -> list[Stretch]:
    """The nonzero stretches of an EXC channel, each with its waveform recognised.

    Parameters
    ----------
    ch : Channel
    join_s : float
        Zero runs shorter than this (s) do not end a stretch.
    shortest_s : float
        Shorter stretches (s) are left out.

    Returns
    -------
    list of Stretch
        In time order.
    """
    on = np.flatnonzero(np.nan_to_num(ch.samples) != 0)
    if on.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(on) > join_s * ch.rate)
    firsts = np.r_[on[0], on[breaks + 1]]
    lasts = np.r_[on[breaks], on[-1]] + 1
    out = []
    for a, b in zip(firsts, lasts, strict=True):
        if b - a >= shortest_s * ch.rate:
            kind, tones = recognise(ch.samples[a:b], ch.rate)
            out.append(Stretch(ch.name, ch.t0 + a / ch.rate, ch.t0 + b / ch.rate, kind, tones))
    return out


def recognise(x: NDArray[np.float64], rate: float) -> tuple[str, tuple[float, ...]]:
    """What waveform `x` is: tonal (a sine, a multisine) when spectral lines hold
    :data:`TONAL` of its power, else a swept sine when its envelope is steady
    (:data:`STEADY`), else noise.

    Parameters
    ----------
    x : ndarray
        The excitation's samples.
    rate : float
        Hz.

    Returns
    -------
    (str, tuple of float)
        The waveform (:data:`WAVEFORMS`) and, if tonal, its lines' frequencies (Hz).

    Examples
    --------
    >>> t = np.arange(16384 * 20) / 16384
    >>> recognise(np.sin(2 * np.pi * 3.3 * t), 16384.0)[0]
    'sine'
    """
    nperseg = min(len(x), int(rate * 32))  # a line at 0.2 Hz stands 6 bins above DC
    f, p = signal.welch(x, rate, nperseg=nperseg)
    # a line stands far above the spectrum around it (a band-limited noise's edge does not)
    # and within 60 dB of the strongest (a rounding floor has peaks too)
    floor = np.maximum(LINE * ndimage.median_filter(p, 65, mode="nearest"), 1e-6 * p.max())
    lines = signal.find_peaks(p, height=floor)[0]
    near = np.zeros(len(p), bool)
    for k in lines:
        near[max(k - 2, 0):k + 3] = True
    if lines.size and p[near].sum() >= TONAL * p.sum():
        tones = tuple(float(_refined(f, p, k)) for k in lines)
        return ("sine" if len(tones) == 1 else "multisine"), tones
    envelope = np.abs(signal.hilbert(x[: 1 << 22]))
    middle = envelope[len(envelope) // 10: -len(envelope) // 10 or None]
    steady = np.std(middle) < STEADY * np.mean(middle)
    return ("swept sine" if steady else "noise"), ()


def _refined(f: NDArray, p: NDArray, k: int) -> float:
    """A line's frequency between bins: the peak of a parabola through log power."""
    if not 0 < k < len(p) - 1:
        return float(f[k])
    a, b, c = np.log(np.maximum(p[k - 1:k + 2], np.finfo(float).tiny))
    shift = 0.5 * (a - c) / (a - 2 * b + c) if a - 2 * b + c < 0 else 0.0
    return float(f[k] + shift * (f[1] - f[0]))


def every(channels: Mapping[str, Channel]) -> dict[tuple[str, str, str], list[Stretch]]:
    """Every stretch of each EXC channel: awg's injections one after another, a sine
    stepped by hand.

    Parameters
    ----------
    channels : mapping of str to Channel

    Returns
    -------
    dict
        ``(ifo, optic, DOF)`` to its stretches in time order; DOFs with none left out.
    """
    out = {}
    for name, ch in channels.items():
        m = DOF_CHANNEL.match(name)
        if m and m["point"] == "EXC" and (runs := stretches(ch)):
            out[(m["ifo"], m["optic"], m["dof"])] = runs
    return out


def longest(runs: Mapping[tuple[str, str, str], list[Stretch]]
            ) -> dict[tuple[str, str, str], Stretch]:
    """Of each DOF's stretches (:func:`every`), the longest: its excitation when it is not
    a series of single sines."""
    return {k: max(v, key=lambda s: s.end - s.start) for k, v in runs.items()}


def found(channels: Mapping[str, Channel]) -> dict[tuple[str, str, str], Stretch]:
    """The excitation of each EXC channel found in its data, ``(ifo, optic, DOF)`` to its
    :class:`Stretch`: of several, the longest (:func:`longest` of :func:`every`)."""
    return longest(every(channels))


def with_exc(channels: Mapping[str, Channel]) -> dict[str, Channel]:
    """`channels` with each DOF's EXC, where it was not recorded, taken as ``IN2 - IN1``: a
    filter module's IN2 is its IN1 plus its EXC. What the two channels' rounding leaves
    where nothing was injected (4 float32 epsilons of their size) is zero, as a recorded
    EXC's is; the DOFs so found are named in a :class:`~twind.errors.MeasurementWarning`.

    Parameters
    ----------
    channels : mapping of str to Channel
        At one rate (:func:`at_one_rate`).

    Returns
    -------
    dict of str to Channel
    """
    out, derived = dict(channels), []
    for name in channels:
        m = DOF_CHANNEL.match(name)
        if not m or m["point"] != "IN1":
            continue
        exc, in2 = (dof_channel(m["ifo"], m["optic"], m["dof"], p) for p in ("EXC", "IN2"))
        in1, in2 = channels[name], channels.get(in2)
        if exc in channels:
            continue
        if in2 is None or (in2.t0, len(in2.samples)) != (in1.t0, len(in1.samples)):
            continue
        x = np.asarray(in2.samples, float) - np.asarray(in1.samples, float)
        rounding = 4 * np.finfo(np.float32).eps * (np.abs(in1.samples) + np.abs(in2.samples))
        x[np.abs(x) <= rounding] = 0.0
        out[exc] = Channel(exc, in1.unit, in1.rate, in1.t0, x, in1.sequences, in1.gps_starts)
        derived.append(exc)
    if derived:
        warnings.warn(f"not recorded, taken as IN2 - IN1: {some_names(derived)}",
                      MeasurementWarning, stacklevel=2)
    return out


def at_one_rate(channels: Mapping[str, Channel]) -> dict[str, Channel]:
    """`channels` at the slowest of their rates: the faster ones through
    :func:`scipy.signal.resample_poly` (its anti-alias filter, no delay), named in a
    :class:`~twind.errors.MeasurementWarning`.

    Parameters
    ----------
    channels : mapping of str to Channel

    Returns
    -------
    dict of str to Channel
    """
    if not channels:
        return dict(channels)
    rate = min(ch.rate for ch in channels.values())
    out, faster = {}, []
    for name, ch in channels.items():
        if ch.rate == rate:
            out[name] = ch
            continue
        ratio = Fraction(rate / ch.rate).limit_denominator(1 << 16)
        samples = signal.resample_poly(ch.samples, ratio.numerator, ratio.denominator)
        out[name] = Channel(name, ch.unit, rate, ch.t0, samples, ch.sequences, ch.gps_starts)
        faster.append(f"{name} ({ch.rate:g} Hz)")
    if faster:
        warnings.warn(f"resampled to {rate:g} Hz, the slowest test point's rate, with "
                      f"scipy.signal.resample_poly: {some_names(faster)}", MeasurementWarning,
                      stacklevel=2)
    return out
