"""Sample generators of excitations: sine, log sweep, Schroeder multisine, shaped noise, stream.

A :class:`Waveform` hands out its samples in blocks of any size; the blocks always
concatenate to the same long render, bit for bit, because every deterministic sample is
computed from its own absolute index and noise is drawn and filtered in fixed internal
chunks.  A run therefore repeats exactly whatever block size the engine or a client uses.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind.excitation.design import multisine_plan, multisine_tones, noise_shape, taper
from twind.excitation.request import MAX_FINITE_SAMPLES, ExcitationRequest

NOISE_CHUNK = 8192
"""White noise is drawn and filtered this many samples at a time, whatever the block size."""


class Waveform:
    """Stateful generator of one excitation's samples, sample 0 = its start.

    Parameters
    ----------
    req : ExcitationRequest
        A request that :func:`twind.excitation.check` accepted.
    rate_hz : float
        Model rate.
    total : int or None
        Samples in the excitation; None = until stopped.
    """

    def __init__(self, req: ExcitationRequest, rate_hz: float, total: int | None) -> None:
        self.request, self.rate_hz = req, float(rate_hz)
        self._total = total
        n_ramp = int(round(req.ramp * self.rate_hz))
        # ramp <= duration / 2 is checked in seconds; rounding must not make ramps overlap
        self._n_ramp = n_ramp if total is None else min(n_ramp, total // 2)
        self._pos = 0
        self._stop_end: int | None = None  # end set by stop(), with its own ramp
        self._stop_ramp = 0

    # -- public -------------------------------------------------------------------------------
    @property
    def total_samples(self) -> int | None:
        """Samples in the whole excitation (after :meth:`stop`, up to its end); None = infinite."""
        ends = [e for e in (self._total, self._stop_end) if e is not None]
        return min(ends) if ends else None

    @property
    def held_bytes(self) -> int:
        """Memory the waveform keeps beyond its state (a period, samples), in bytes."""
        return 0

    @property
    def position(self) -> int:
        """Samples handed out so far (including zeros after the end)."""
        return self._pos

    @property
    def done(self) -> bool:
        """True once every sample of the excitation has been handed out."""
        end = self.total_samples
        return end is not None and self._pos >= end

    def stop(self, ramp: float = 0.0) -> None:
        """End the excitation from the next sample on, after a raised-cosine ramp down.

        Parameters
        ----------
        ramp : float
            Seconds of ramp down (0: the next sample is already zero).  The excitation never
            runs longer than it would have without the stop.

        Raises
        ------
        ValueError
            For a negative or non-finite ramp.
        """
        if not (math.isfinite(ramp) and ramp >= 0):
            msg = f"stop ramp must be a finite number of seconds >= 0, got {ramp!r}"
            raise ValueError(msg)
        n = int(round(min(ramp * self.rate_hz, MAX_FINITE_SAMPLES)))
        end = self._pos + n
        if self._stop_end is None or end < self._stop_end:
            self._stop_end, self._stop_ramp = end, n

    def next(self, n: int) -> NDArray[np.float64]:
        """The next `n` samples; zeros after the end.

        Parameters
        ----------
        n : int
            Block length (>= 0).

        Returns
        -------
        ndarray, shape (n,)
            Consecutive calls concatenate exactly to one long call.
        """
        n = int(n)
        if n < 0:
            msg = f"block length must be >= 0, got {n}"
            raise ValueError(msg)
        lo = self._pos
        out = np.zeros(n)
        end = self.total_samples
        m = n if end is None else max(0, min(n, end - lo))
        if m:
            idx = np.arange(lo, lo + m, dtype=np.int64)
            out[:m] = self._render(idx)
            self._apply_window(out[:m], idx)
        self._pos = lo + n
        return out

    # -- internals ----------------------------------------------------------------------------
    def _apply_window(self, block: NDArray[np.float64], idx: NDArray[np.int64]) -> None:
        lo, hi = int(idx[0]), int(idx[-1]) + 1
        r = self._n_ramp
        # Most blocks are in the flat middle: skip the window there (multiplying by 1.0
        # would change nothing, it would only cost time).
        if r and (lo < r or (self._total is not None and hi > self._total - r)):
            block *= taper(idx, r, self._total)
        if self._stop_end is not None and self._stop_ramp and hi > self._stop_end - self._stop_ramp:
            # the closing half of a taper whose end is the stop's end
            tail = idx >= self._stop_end - self._stop_ramp
            k = self._stop_end - 1 - idx[tail]
            block[tail] *= 0.5 * (1.0 - np.cos(math.pi * k / self._stop_ramp))

    def _render(self, idx: NDArray[np.int64]) -> NDArray[np.float64]:
        """Untapered samples at absolute indices `idx` (contiguous, increasing)."""
        raise NotImplementedError

    def __repr__(self) -> str:
        total = "inf" if self.total_samples is None else self.total_samples
        return (f"<{type(self).__name__} {self.request.channel} {self.request.waveform} "
                f"{self._pos}/{total} samples at {self.rate_hz:g} Hz>")


class SineWave(Waveform):
    """``amp * sin(2 pi f t)``, t = n / rate."""

    def _render(self, idx: NDArray[np.int64]) -> NDArray[np.float64]:
        req = self.request
        cycles = idx * (req.freq / self.rate_hz)
        # whole cycles removed so that sin sees a small argument even after days
        cycles -= np.floor(cycles)
        return req.amp * np.sin(2.0 * math.pi * cycles)


class SweepWave(Waveform):
    """Logarithmic sweep from `freq` at t = 0 to `f_stop` at t = `duration`, peak `amp`."""

    def _render(self, idx: NDArray[np.int64]) -> NDArray[np.float64]:
        req = self.request
        t = idx / self.rate_hz
        # chirp is a cosine; phi = -90 degrees makes it a sine that starts at 0
        return req.amp * signal.chirp(t, f0=req.freq, t1=req.duration, f1=req.f_stop,
                                      method="logarithmic", phi=-90.0)


class MultisineWave(Waveform):
    """Equal tones with Schroeder phases, repeating one exactly periodic period of peak `amp`.

    Attributes
    ----------
    freqs : ndarray
        The tones sent (Hz), on the period's frequency grid.
    period_samples : int
        Length of the period.
    """

    def __init__(self, req: ExcitationRequest, rate_hz: float, total: int | None) -> None:
        super().__init__(req, rate_hz, total)
        tones = multisine_tones(req.freq, req.f_stop, req.n_tones, req.freqs)
        plan = multisine_plan(tuple(float(f) for f in tones), float(rate_hz))
        self._period, self.freqs = plan.period, plan.freqs
        self.period_samples = plan.period.size

    @property
    def held_bytes(self) -> int:
        return self._period.nbytes

    def _render(self, idx: NDArray[np.int64]) -> NDArray[np.float64]:
        return self.request.amp * self._period[idx % self.period_samples]


class StreamWave(Waveform):
    """The request's samples, as given (a private copy, so later edits cannot leak in)."""

    def __init__(self, req: ExcitationRequest, rate_hz: float) -> None:
        self._samples = np.array(req.samples, dtype=np.float64)
        super().__init__(req, rate_hz, self._samples.size)

    @property
    def held_bytes(self) -> int:
        return self._samples.nbytes

    def _render(self, idx: NDArray[np.int64]) -> NDArray[np.float64]:
        return self._samples[idx[0]:idx[-1] + 1].copy()


class NoiseWave(Waveform):
    """Gaussian noise from ``default_rng(seed)``, shaped by foton sections, RMS `amp`.

    The shaping filter starts at rest (a gentle start, like a ramp); its state is carried
    from chunk to chunk.  The scale comes from the filter's noise bandwidth
    (:func:`twind.excitation.design.noise_gain`), not from measuring the samples.
    """

    def __init__(self, req: ExcitationRequest, rate_hz: float, total: int | None) -> None:
        super().__init__(req, rate_hz, total)
        self._rng = np.random.default_rng(req.seed)
        if req.shape is None:
            self._sos, self._zi, self._scale = None, None, req.amp
        else:
            shape = noise_shape(req.shape, float(rate_hz))
            self._sos = shape.sos  # a private, writeable copy
            self._zi = np.zeros((self._sos.shape[0], 2))
            self._scale = req.amp / shape.gain_rms
        self._chunk = np.zeros(0)
        self._used = 0  # samples of _chunk already handed out

    def _next_chunk(self) -> None:
        white = self._rng.standard_normal(NOISE_CHUNK)
        if self._sos is not None:
            white, self._zi = signal.sosfilt(self._sos, white, zi=self._zi)
        self._chunk, self._used = white * self._scale, 0

    def _render(self, idx: NDArray[np.int64]) -> NDArray[np.float64]:
        # idx is always the contiguous block after the previous one: only its length matters
        out = np.empty(idx.size)
        filled = 0
        while filled < idx.size:
            if self._used == self._chunk.size:
                self._next_chunk()
            k = min(idx.size - filled, self._chunk.size - self._used)
            out[filled:filled + k] = self._chunk[self._used:self._used + k]
            filled += k
            self._used += k
        return out


def n_samples(duration: float, rate_hz: float) -> int | None:
    """Samples in `duration` seconds at `rate_hz` (rounded); None for an infinite duration.

    Parameters
    ----------
    duration : float
        Seconds; ``inf`` for an excitation that runs until stopped.
    rate_hz : float
        Sample rate (Hz).

    Returns
    -------
    int or None

    Examples
    --------
    >>> n_samples(2.5, 16384)
    40960
    >>> n_samples(float("inf"), 16384) is None
    True
    """
    return None if math.isinf(duration) else int(round(duration * rate_hz))


def make_waveform(req: ExcitationRequest, rate_hz: float) -> Waveform:
    """The generator of a request's samples at the model rate.

    Parameters
    ----------
    req : ExcitationRequest
        A request :func:`twind.excitation.check` accepted at this rate; an unchecked one
        may fail in any way (this function does not repeat the checks).
    rate_hz : float
        Model rate, e.g. 16384.

    Returns
    -------
    Waveform
        Positioned at the excitation's first sample.
    """
    if req.waveform == "stream":
        return StreamWave(req, rate_hz)
    total = n_samples(req.duration, rate_hz)
    cls = {"sine": SineWave, "sweep": SweepWave, "multisine": MultisineWave,
           "noise": NoiseWave}[req.waveform]
    return cls(req, rate_hz, total)
