"""Welch transfer-function estimates equal to ``scipy.signal``'s, from one FFT per segment of
each signal: over arrays in memory (:func:`welch_tfs`), or summed while a recording is read
(:class:`WelchStream`), so that ``twind tf`` takes an hour of 16 kHz test points in the
memory of a few segments.

Both transform with FFTW (pyfftw) when it is installed: at the 1.6 M points of a 0.01 Hz
estimate it takes half the time of numpy's pocketfft, and the FFTs are most of the work.
"""

from __future__ import annotations

import bisect
import os
import threading
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from queue import SimpleQueue
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import fft, signal

try:  # FFTW when it is installed; numpy's pocketfft otherwise
    import pyfftw
except ImportError:
    pyfftw = None

from twind import progress
from twind.errors import TwindError

LAG_S = 10.0
"""A streamed segment is summed once every channel holds this much data after it: an event
recorded up to this late (a ``stop`` cutting the excitation short) is known before then.
What arrives later still gives the right answer: :func:`WelchStream.result` checks the
segments summed against the final events and returns None if they differ."""
HISTORY_S = 30.0
"""Seconds of every channel kept before the excitations known so far, for a ``start`` event
recorded after its first samples."""


class WelchError(TwindError):
    """Signals that cannot be averaged as asked."""


# ------------------------------------------------------------------------------ transforms
def _aligned(n: int, dtype: type = np.float64) -> NDArray:
    """An empty array aligned as FFTW's SIMD code wants (plain numpy without pyfftw)."""
    if pyfftw is None:
        return np.empty(n, dtype=dtype)
    return pyfftw.empty_aligned(n, dtype=dtype)


class _RealFFT:
    """One-sided FFT of `n` points from an :func:`_aligned` buffer (destroyed) into another;
    one per thread (FFTW plans are not shared between threads)."""

    def __init__(self, n: int) -> None:
        if pyfftw is None:
            self._plan = None
            return
        self._plan = pyfftw.FFTW(_aligned(n), _aligned(n // 2 + 1, np.complex128),
                                 flags=("FFTW_ESTIMATE", "FFTW_DESTROY_INPUT"), threads=1)

    def __call__(self, src: NDArray[np.float64], out: NDArray[np.complex128]
                 ) -> NDArray[np.complex128]:
        if self._plan is None:
            return np.fft.rfft(src, out=out)
        self._plan.update_arrays(src, out)
        self._plan.execute()
        return out


def _load(parts: Sequence[NDArray], win: NDArray, buf: NDArray) -> NDArray:
    """scipy.signal's segment before its FFT, from its consecutive `parts`: constant
    detrend, window."""
    if len(parts) == 1:
        np.copyto(buf, parts[0])
    else:
        np.concatenate(parts, out=buf)
    buf -= buf.mean()
    buf *= win
    return buf


@nb.njit(cache=True, nogil=True)
def _accumulate_auto(X: NDArray, sxx: NDArray) -> None:  # pragma: no cover - numba
    for i in range(X.size):
        sxx[i] += X[i].real * X[i].real + X[i].imag * X[i].imag


@nb.njit(cache=True, nogil=True)
def _accumulate_cross(X: NDArray, Y: NDArray, sxy: NDArray, syy: NDArray
                      ) -> None:  # pragma: no cover - numba
    # one pass for conj(X) Y and |Y|^2, instead of numpy's three temporaries
    for i in range(X.size):
        xr, xi, yr, yi = X[i].real, X[i].imag, Y[i].real, Y[i].imag
        sxy[i] += complex(xr * yr + xi * yi, xr * yi - xi * yr)
        syy[i] += yr * yr + yi * yi


@dataclass
class _Sums:
    """Sums over segments of ``|X|^2``, ``conj(X) Y`` and ``|Y|^2`` for several responses."""

    nperseg: int
    responses: int
    count: int = 0
    sxx: NDArray = field(init=False)
    sxy: NDArray = field(init=False)
    syy: NDArray = field(init=False)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        nf = self.nperseg // 2 + 1
        self.sxx = np.zeros(nf)
        self.sxy = np.zeros((self.responses, nf), dtype=np.complex128)
        self.syy = np.zeros((self.responses, nf))

    def spectra(self, rate: float, win: NDArray, psd: NDArray | None = None
                ) -> tuple[NDArray[np.float64], NDArray[np.complex128], NDArray[np.float64]]:
        """Frequencies, ``CSD/PSD`` and coherence, scaled as scipy scales them; computed in
        place of the sums (an hour at 0.01 Hz: new memory is slow to fault in), which are
        spent. `psd`, when given, is filled with the excitation's PSD."""
        if self.count == 0:
            msg = "no segments summed, or their spectra already taken"
            raise WelchError(msg)
        # scipy's density scaling and one-sided doubling; they cancel in H and the coherence
        # except through rounding, so they are applied as scipy applies them
        scale = np.full(self.sxx.size, 1.0 / (rate * (win * win).sum()) / self.count)
        scale[1:-1 if self.nperseg % 2 == 0 else None] *= 2
        if psd is not None:
            np.multiply(self.sxx, scale, out=psd)
        _ratios(self.sxx, self.sxy, self.syy, scale)
        self.count = 0
        return fft.rfftfreq(self.nperseg, 1.0 / rate), self.sxy, self.syy


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _ratios(sxx: NDArray, sxy: NDArray, syy: NDArray, scale: NDArray
            ) -> None:  # pragma: no cover - numba
    # numpy's expression in one pass, H into sxy and the coherence into syy: an hour at
    # 0.01 Hz is 0.5 GB of temporaries otherwise; 0/0 is NaN (bins a periodic EXC leaves empty)
    for k in range(sxx.size):
        pxx = sxx[k] * scale[k]
        for i in range(sxy.shape[0]):
            pxy = sxy[i, k] * scale[k]
            pyy = syy[i, k] * scale[k]
            sxy[i, k] = complex(pxy.real / pxx, pxy.imag / pxx)  # numpy's pxy / pxx, 0 too
            syy[i, k] = abs(pxy) ** 2 / pxx / pyy


class _Transforms(threading.local):
    """A thread's FFT plan and output buffers."""

    def __init__(self, n: int) -> None:
        self.fft = _RealFFT(n)
        self.X = _aligned(n // 2 + 1, np.complex128)
        self.Y = _aligned(n // 2 + 1, np.complex128)

    def add(self, bufs: Sequence[NDArray], sums: _Sums) -> None:
        """One segment of the excitation (``bufs[0]``, loaded) and its responses into
        `sums`."""
        X = self.fft(bufs[0], self.X)
        with sums.lock:
            _accumulate_auto(X, sums.sxx)
            sums.count += 1
        progress.tick()
        for i, buf in enumerate(bufs[1:]):
            Y = self.fft(buf, self.Y)
            with sums.lock:
                _accumulate_cross(X, Y, sums.sxy[i], sums.syy[i])


# ------------------------------------------------------------------------------ in memory
def welch_tf(x: NDArray, y: NDArray, rate: float, nperseg: int, overlap: float = 0.5,
             window: str = "hann") -> tuple[NDArray, NDArray, NDArray, int]:
    """``H = CSD(x, y) / PSD(x)``, coherence, and the number of averages, as
    ``scipy.signal.csd``, ``welch`` and ``coherence`` give them (see :func:`welch_tfs`).

    Parameters
    ----------
    x : ndarray
        The excitation.
    y : ndarray
        The response, as long as `x`.
    rate : float
        Sample rate (Hz).
    nperseg : int
        Samples per segment (resolution ``rate / nperseg``).
    overlap : float
        Fraction of a segment shared with the next.
    window : str
        scipy's window name.

    Returns
    -------
    f : ndarray
    h : ndarray of complex
    coherence : ndarray
    averages : int
    """
    f, h, g2, n = welch_tfs(x, [y], rate, nperseg, overlap, window=window)
    return f, h[0], g2[0], n


def welch_tfs(x: NDArray, ys: Sequence[NDArray], rate: float, nperseg: int,
              overlap: float = 0.5, workers: int | None = None, window: str = "hann",
              psd: NDArray[np.float64] | None = None
              ) -> tuple[NDArray[np.float64], NDArray[np.complex128], NDArray[np.float64], int]:
    """Transfer functions ``CSD(x, y) / PSD(x)`` and coherences of several responses to one
    excitation, as ``scipy.signal`` estimates them.

    scipy computes every segment's FFT again for each of ``csd``, ``welch`` and
    ``coherence`` (seven FFTs per pair); here each signal's segments are transformed once,
    with scipy's steps (mean removed, periodic window, one-sided FFT), and the cross and
    auto spectra summed from them. The results equal scipy's to rounding.

    Parameters
    ----------
    x : ndarray
        Excitation.
    ys : sequence of ndarray
        Responses, each as long as `x`.
    rate : float
        Sample rate (Hz).
    nperseg : int
        Samples per segment.
    overlap : float
        Fraction of a segment shared with the next (``noverlap = int(nperseg * overlap)``).
    workers : int, optional
        Threads, each transforming its share of the segments; default the CPU count, at
        most 2 (the FFTs of a few-megasample segment are memory bound).
    window : str
        scipy window name: ``"hann"`` (diaggui's default) or ``"boxcar"`` for a periodic
        excitation whose period is the segment (no leakage, no smoothing of H).
    psd : ndarray, shape (nperseg // 2 + 1,), optional
        Filled with the excitation's power spectral density, as ``scipy.signal.welch``
        gives it, from the same transforms.

    Returns
    -------
    frequency_hz : ndarray, shape (nperseg // 2 + 1,)
    tf : ndarray of complex, shape (len(ys), nfreq)
    coherence : ndarray, shape (len(ys), nfreq)
    averages : int
        Segments averaged.

    Raises
    ------
    WelchError
        If a response is not as long as `x`, or `x` is shorter than a segment.
    """
    x = np.asarray(x, dtype=np.float64)
    ys = [np.asarray(y, dtype=np.float64) for y in ys]
    if any(y.shape != x.shape for y in ys) or x.ndim != 1:
        msg = f"responses of {[y.shape for y in ys]} samples for an excitation of {x.shape}"
        raise WelchError(msg)
    step = _step(nperseg, overlap)
    if x.size < nperseg:
        msg = (f"{x.size} samples, segments of {nperseg} overlapping by {nperseg - step}: "
               "no average")
        raise WelchError(msg)
    n = 1 + (x.size - nperseg) // step
    win = signal.get_window(window, nperseg)
    workers = max(1, min(workers or min(os.cpu_count() or 1, 2), n))
    sums = _Sums(nperseg, len(ys))
    transforms = _Transforms(nperseg)

    def part(segs: range) -> None:
        bufs = [_aligned(nperseg) for _ in range(1 + len(ys))]
        for k in segs:
            cut = slice(k * step, k * step + nperseg)
            transforms.add([_load([s[cut]], win, b)
                            for s, b in zip([x, *ys], bufs, strict=True)],
                           sums)

    bounds = np.linspace(0, n, workers + 1).astype(int)
    ranges = [range(bounds[i], bounds[i + 1]) for i in range(workers)]
    if workers == 1:
        part(ranges[0])
    else:
        with ThreadPoolExecutor(workers, thread_name_prefix="twind-welch") as pool:
            list(pool.map(part, ranges))
    freq, h, g2 = sums.spectra(rate, win, psd)
    return freq, h, g2, n


def _step(nperseg: int, overlap: float) -> int:
    step = nperseg - int(nperseg * overlap)
    if step < 1:
        msg = f"an overlap of {overlap:g} leaves no step between segments of {nperseg}"
        raise WelchError(msg)
    return step


# ------------------------------------------------------------------------------ streamed
@dataclass(frozen=True)
class Segment:
    """The samples one Welch estimate averages: its channels (the excitation first), the
    index in each of the first sample averaged, and how many samples follow it."""

    names: tuple[str, ...]
    starts: tuple[int, ...]
    n: int


@dataclass(frozen=True)
class Extent:
    """A channel's first sample time (GPS), rate (Hz) and samples so far."""

    t0: float
    rate: float
    n: int

    @property
    def t_end(self) -> float:
        """GPS time just after the last sample."""
        return self.t0 + self.n / self.rate


Planner = Callable[[list[dict[str, Any]], Mapping[str, Extent]], dict[Any, Segment]]
"""Segments to average, by key, from the injection events and the channels' extents."""


class _Tail:
    """The latest samples of one channel, kept as the arrays they arrived in (never written
    again): ``samples(a, b)`` is its samples ``a`` to ``b``, in parts."""

    def __init__(self, t0: float, rate: float) -> None:
        self.t0, self.rate = t0, rate
        self.parts: list[NDArray] = []
        self.starts: list[int] = []  # sample index of each part's first sample
        self.head = 0  # parts[head:] are held
        self.total = 0  # samples received
        self.peak = 0  # most samples held at once
        self.next_sequence: int | None = None
        self.regular = True
        """Consecutive blocks at one rate without gaps so far: sample ``i`` at
        ``t0 + i / rate``."""

    @property
    def base(self) -> int:
        """Index of the first sample held."""
        return self.starts[self.head] if self.head < len(self.parts) else self.total

    def extend(self, sequence: NDArray, gps: NDArray, rate: NDArray, n: NDArray,
               x: NDArray) -> None:
        self._check(sequence, gps, rate, n)
        if x.size:
            self.parts.append(x)
            self.starts.append(self.total)
            self.total += x.size
            self.peak = max(self.peak, self.total - self.base)

    def _check(self, sequence: NDArray, gps: NDArray, rate: NDArray, n: NDArray) -> None:
        if not self.regular:
            return
        first = self.next_sequence is None or sequence[0] == self.next_sequence
        expected = self.t0 + (self.total + np.cumsum(n) - n) / self.rate
        self.regular = bool(first and np.all(rate == self.rate) and np.all(np.diff(sequence) == 1)
                            and np.all(np.abs(gps - expected) * self.rate <= 0.05))
        self.next_sequence = int(sequence[-1]) + 1

    def samples(self, a: int, b: int) -> list[NDArray[np.float64]] | None:
        """Samples ``a`` to ``b`` as consecutive views, or None if some were dropped or have
        not arrived."""
        if a < self.base or b > self.total:
            return None
        i = bisect.bisect_right(self.starts, a, self.head) - 1
        out = []
        while self.starts[i] < b:
            lo = self.starts[i]
            out.append(self.parts[i][max(a - lo, 0):b - lo])
            i += 1
            if i == len(self.parts):
                break
        return out

    def drop_before(self, a: int) -> None:
        """Forget the parts wholly before sample `a`."""
        end = len(self.parts)
        while self.head < end and self.starts[self.head] + self.parts[self.head].size <= a:
            self.parts[self.head] = None  # type: ignore[call-overload] - freed now
            self.head += 1
        if self.head > 1024 and 2 * self.head > end:
            del self.parts[:self.head], self.starts[:self.head]
            self.head = 0


@dataclass
class _Streamed:
    segment: Segment
    sums: _Sums
    done: int = 0  # segments summed (or submitted)
    lost: bool = False  # a segment's samples were dropped before it could be summed


class WelchStream:
    """Welch transfer functions of a recording, summed while
    :func:`~twind.recording.fastread.stream_channels` reads it (a ``SampleSink``).

    Each segment is loaded (detrended, windowed) as soon as every channel holds it and
    :data:`LAG_S` more, and transformed on a worker thread; the samples before the
    segments still to come are dropped.

    Parameters
    ----------
    planner : Planner
        The segments to average, asked again whenever events or channels are added.
    bw : float
        Resolution (Hz): segments of ``round(rate / bw)`` samples at the rate of the first
        excitation's channels (a segment at another rate is left to the caller).
    overlap : float
        Fraction of a segment shared with the next.
    window : str
        scipy window name.
    workers : int, optional
        Transform threads; default the CPU count, at most 2.
    """

    def __init__(self, planner: Planner, bw: float, overlap: float = 0.5,
                 window: str = "hann", workers: int | None = None) -> None:
        self.planner = planner
        self.bw, self.overlap, self.window = bw, overlap, window
        self.rate: float | None = None  # of the segments, set by the first one planned
        self.nperseg = self.step = 0
        self.win = np.empty(0)
        self.events: list[dict[str, Any]] = []
        self.tails: dict[str, _Tail] = {}
        self.streamed: dict[Any, _Streamed] = {}
        self._stale = True  # events or channels added since the last plan
        self._unplanned = 0  # samples received since the last look at the segments
        workers = workers or min(os.cpu_count() or 1, 2)
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="twind-welch")
        self._transforms: _Transforms | None = None
        self._free: SimpleQueue[list[NDArray]] = SimpleQueue()  # loaded-segment buffers
        self._buffers = 0
        self._limit = workers + 1  # segments loaded at once (~130 MB each at 0.01 Hz)
        self._futures: list[Future] = []

    # SampleSink
    def event(self, event: dict[str, Any]) -> None:
        """An injection event (see :class:`~twind.recording.fastread.SampleSink`)."""
        self.events.append(event)
        self._stale = True

    def samples(self, name: str, sequence: NDArray[np.int64], n_samples: NDArray[np.int64],
                gps: NDArray[np.float64], rate: NDArray[np.float64],
                x: NDArray[np.float64]) -> None:
        """Blocks of one channel (see :class:`~twind.recording.fastread.SampleSink`).

        Parameters
        ----------
        name : str
            The channel, e.g. ``C1:SUS-ETMX_SUSPOS_IN1``.
        sequence : ndarray of int
            Each block's sequence number.
        n_samples : ndarray of int
            Each block's sample count.
        gps : ndarray
            Each block's GPS start time (s).
        rate : ndarray
            Each block's sample rate (Hz).
        x : ndarray
            The blocks' samples joined; kept, never written.
        """
        tail = self.tails.get(name)
        if tail is None:
            tail = self.tails[name] = _Tail(float(gps[0]), float(rate[0]))
            self._stale = True
        tail.extend(sequence, gps, rate, n_samples, x)
        self._unplanned += x.size
        if self._unplanned >= 8 * tail.rate:  # look every few seconds of recording
            self._advance(lag=True)

    # the sums
    def extents(self, open_ended: bool = False) -> dict[str, Extent]:
        """Every channel's start, rate and samples so far (or, `open_ended`, to come)."""
        return {n: Extent(t.t0, t.rate, 1 << 60 if open_ended else t.total)
                for n, t in self.tails.items()}

    def _replan(self) -> None:
        # while reading, a segment runs to its excitation's end; the data is awaited
        for key, seg in self.planner(self.events, self.extents(open_ended=True)).items():
            known = self.streamed.get(key)
            rate = self.tails[seg.names[0]].rate
            if self.rate is None:
                self.rate = rate
                self.nperseg = int(round(rate / self.bw))
                self.step = _step(self.nperseg, self.overlap)
                self.win = signal.get_window(self.window, self.nperseg)
                self._transforms = _Transforms(self.nperseg)
            if known is None or (known.done == 0 and known.segment != seg):
                self.streamed[key] = _Streamed(seg, _Sums(self.nperseg, len(seg.names) - 1),
                                               lost=rate != self.rate)
            elif (known.segment.names, known.segment.starts) != (seg.names, seg.starts):
                known.lost = True  # summed for other samples: the end decides
            else:
                known.segment = seg
        self._stale = False

    def _advance(self, lag: bool) -> None:
        self._unplanned = 0
        if self._stale:
            self._replan()
        for s in self.streamed.values():
            tails = [self.tails.get(n) for n in s.segment.names]
            while not s.lost and all(tails):
                a = s.done * self.step
                b = a + self.nperseg
                if b > s.segment.n:
                    break
                margin = int(LAG_S * tails[0].rate) if lag else 0
                if any(t.total < start + b + margin
                       for t, start in zip(tails, s.segment.starts, strict=True)):
                    break
                seg = [t.samples(start + a, start + b)
                       for t, start in zip(tails, s.segment.starts, strict=True)]
                if any(x is None for x in seg):
                    s.lost = True
                    break
                self._submit(seg, s.sums)
                s.done += 1
        self._drop()

    def _submit(self, seg: list[NDArray], sums: _Sums) -> None:
        if self._free.empty() and self._buffers < self._limit:
            self._buffers += 1
            self._free.put([_aligned(self.nperseg) for _ in seg])
        bufs = self._free.get()  # waits for a transform to finish when all are loaded
        if len(bufs) < len(seg):
            bufs += [_aligned(self.nperseg) for _ in range(len(seg) - len(bufs))]

        def transform() -> None:
            # loaded here, not while reading: the reading thread is the one that cannot wait
            try:
                loaded = [_load(x, self.win, b) for x, b in zip(seg, bufs, strict=False)]
                self._transforms.add(loaded, sums)
            finally:
                self._free.put(bufs)

        self._futures.append(self._pool.submit(transform))
        self._futures = [f for f in self._futures if not f.done() or f.exception()]

    def _drop(self) -> None:
        """Forget the samples no segment still needs (keeping :data:`HISTORY_S`)."""
        keep = {n: t.total - int(HISTORY_S * t.rate) for n, t in self.tails.items()}
        for s in self.streamed.values():
            if s.lost:
                continue
            for n, start in zip(s.segment.names, s.segment.starts, strict=True):
                # past its end, a segment keeps only the history (a late event may extend it)
                if n in keep and start + s.segment.n >= keep[n]:
                    keep[n] = min(keep[n], start + s.done * self.step)
        for n, a in keep.items():
            self.tails[n].drop_before(a)

    def close(self) -> None:
        """Stop the transforms (after an error: nothing more is summed)."""
        self._pool.shutdown(cancel_futures=True)

    def result(self) -> dict[Any, tuple[Segment, NDArray, NDArray, NDArray, int]] | None:
        """After the last samples: every segment's frequencies, transfer functions,
        coherences and number of averages, by key; None if what was summed is not what
        the complete events and channels ask for (the caller then reads the recording
        whole), or a segment is shorter than ``nperseg``.
        """
        try:
            self._stale = True
            self._advance(lag=False)
            for f in self._futures:
                f.result()
        finally:
            self.close()
        final = self.planner(self.events, self.extents())
        for key, seg in final.items():
            s = self.streamed.get(key)
            wanted = 1 + (seg.n - self.nperseg) // self.step if seg.n >= self.nperseg else 0
            if (s is None or s.lost or wanted == 0 or s.done != wanted
                    or (s.segment.names, s.segment.starts) != (seg.names, seg.starts)
                    or not all(self.tails[n].regular for n in seg.names)):
                return None
        summed = [self.streamed[key] for key in final]
        with ThreadPoolExecutor(2, thread_name_prefix="twind-welch") as pool:
            spectra = pool.map(lambda s: s.sums.spectra(self.rate, self.win), summed)
            return {key: (s.segment, *sp, s.done)
                    for key, s, sp in zip(final, summed, spectra, strict=True)}
