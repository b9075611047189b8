"""Transfer functions from the damping loop's test points: IN1/EXC, IN2/EXC, OUT/EXC, each
with its coherence and standard error, assembled into [response DOF x excited DOF] matrices,
and the open-loop plant recovered from them (seed eq. 14, MODEL.md's sign convention):

    P = (IN1/EXC) (IN2/EXC)^-1 K^-1 = (IN1/EXC) (OUT/EXC)^-1

Sources: diaggui "Fourier tools" XML files (one per excited DOF, read with dttxml) and MCAP
sessions of the twin (excitation segments from the recorded injection events; Welch estimates
with scipy.signal). The standard error of a Welch estimate is Bendat & Piersol's
``|H| sqrt((1 - g^2) / (2 n g^2))`` for ``n`` averages and coherence ``g^2``.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind import DOFS
from twind.errors import TwindError

POINTS = ("IN1", "IN2", "OUT")
_CHANNEL = re.compile(r"^(?P<ifo>\w+):SUS-(?P<optic>\w+?)_SUS(?P<dof>POS|PIT|YAW|SIDE)_(?P<point>\w+)$")


class TFError(TwindError):
    """A measurement cannot be turned into transfer functions."""


@dataclass
class TFSet:
    """Closed-loop transfer functions of one optic, one column per excited DOF.

    Arrays are indexed ``[frequency, response DOF, excited DOF]``.
    """

    optic: str
    frequency_hz: NDArray[np.float64]
    excited: list[str]
    responses: list[str]
    tf: dict[str, NDArray[np.complex128]]  # "IN1", "IN2", "OUT" per EXC
    coherence: dict[str, NDArray[np.float64]]
    averages: int
    window: str = "hann"  # of the spectral estimates: "hann" smooths H over ~1 bin
    exc_psd: dict[str, NDArray[np.float64]] | None = None  # per excited DOF, when known

    def sigma(self, point: str) -> NDArray[np.float64]:
        """Standard error of each element of ``point``/EXC (Bendat & Piersol)."""
        g2 = np.clip(self.coherence[point], 1e-12, 1.0)
        return np.abs(self.tf[point]) * np.sqrt((1 - g2) / (2 * self.averages * g2))

    def plant(self) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """The open-loop plant over the excited DOFs and its standard error.

        ``P = (IN1/EXC)(OUT/EXC)^-1`` restricted to the excited DOFs' rows; the error is
        propagated to first order from the errors of both matrices, taken as independent.
        Both come from the same noise, so the sigma is conservative: the residuals of a
        twin recording against its model have about half the power it predicts
        (tests/test_tf.py); the identification issue calibrates it.
        """
        rows = [self.responses.index(d) for d in self.excited]
        m1 = self.tf["IN1"][:, rows, :]
        mo = self.tf["OUT"][:, rows, :]
        s1 = self.sigma("IN1")[:, rows, :]
        so = self.sigma("OUT")[:, rows, :]
        inv = np.linalg.inv(mo)
        P = m1 @ inv
        # dP = dM1 inv - P dMO inv: variances add element by element
        var = (s1**2) @ (np.abs(inv) ** 2) + (np.abs(P) ** 2) @ (so**2) @ (np.abs(inv) ** 2)
        return P, np.sqrt(var)

    def band(self, lo: float, hi: float) -> TFSet:
        """Only the frequencies in [lo, hi]."""
        keep = (self.frequency_hz >= lo) & (self.frequency_hz <= hi)
        return TFSet(self.optic, self.frequency_hz[keep], self.excited, self.responses,
                     {k: v[keep] for k, v in self.tf.items()},
                     {k: v[keep] for k, v in self.coherence.items()}, self.averages,
                     self.window,
                     {k: v[keep] for k, v in self.exc_psd.items()} if self.exc_psd else None)

    def write(self, path: str | Path) -> Path:
        """HDF5 (``.h5``/``.hdf5``: one complex dataset per test point, coherence, errors,
        plant) or CSV (``.csv``: one row per frequency, columns named like
        ``IN1_POS_per_PIT_re``). An existing file is refused."""
        path = Path(path)
        if path.exists():
            msg = f"{path} exists; twind does not overwrite results"
            raise TFError(msg)
        P, Ps = self.plant()
        if path.suffix.lower() in (".h5", ".hdf5"):
            import h5py

            with h5py.File(path, "x") as f:
                f.attrs.update(optic=self.optic, excited=self.excited, responses=self.responses,
                               averages=self.averages)
                f["frequency_hz"] = self.frequency_hz
                for p in POINTS:
                    f[f"{p}_per_EXC"] = self.tf[p]
                    f[f"coherence_{p}"] = self.coherence[p]
                    f[f"sigma_{p}"] = self.sigma(p)
                f["plant"], f["plant_sigma"] = P, Ps
            return path
        if path.suffix.lower() == ".csv":
            cols, names = [self.frequency_hz], ["frequency_hz"]
            for p in POINTS:
                for i, r in enumerate(self.responses):
                    for j, e in enumerate(self.excited):
                        h = self.tf[p][:, i, j]
                        cols += [h.real, h.imag, self.coherence[p][:, i, j], self.sigma(p)[:, i, j]]
                        names += [f"{p}_{r}_per_{e}_{x}" for x in ("re", "im", "coh", "sigma")]
            for i, r in enumerate(self.excited):
                for j, e in enumerate(self.excited):
                    cols += [P[:, i, j].real, P[:, i, j].imag, Ps[:, i, j]]
                    names += [f"plant_{r}_per_{e}_{x}" for x in ("re", "im", "sigma")]
            np.savetxt(path, np.column_stack(cols), delimiter=",", header=",".join(names),
                       comments="")
            return path
        msg = f"{path}: write .h5, .hdf5 or .csv (or .png for a plot)"
        raise TFError(msg)

    def to_json(self) -> dict:
        """The ``twind tf --json`` object."""
        P, Ps = self.plant()

        def cplx(a: NDArray) -> dict:
            return {"re": a.real.tolist(), "im": a.imag.tolist()}

        return {"optic": self.optic, "frequency_hz": self.frequency_hz.tolist(),
                "excited": self.excited, "responses": self.responses,
                "IN1_per_EXC": cplx(self.tf["IN1"]), "IN2_per_EXC": cplx(self.tf["IN2"]),
                "OUT_per_EXC": cplx(self.tf["OUT"]),
                "coherence_IN1": self.coherence["IN1"].tolist(),
                "sigma_IN1": self.sigma("IN1").tolist(), "plant": cplx(P),
                "plant_sigma": Ps.tolist(), "averages": self.averages}


# ------------------------------------------------------------------------------ diaggui XML
def from_diaggui(paths: Sequence[str | Path]) -> TFSet:
    """Transfer functions from diaggui XML files, one per excited DOF (dttxml's ``xfer``)."""
    import dttxml

    columns, freq, optic, averages = {}, None, None, None
    for path in paths:
        try:
            acc = dttxml.DiagAccess(str(path))
        except Exception as err:  # noqa: BLE001 - dttxml raises many kinds on a bad file
            msg = f"{path}: not a readable diaggui XML file ({type(err).__name__}: {err})"
            raise TFError(msg) from None
        names = sorted(acc.channels()[0])
        exc = [n for n in names if n.endswith("_EXC") and _CHANNEL.match(n)]
        if len(exc) != 1:
            msg = f"{path}: expected one SUS ..._EXC channel (channel A), found {exc or 'none'}"
            raise TFError(msg)
        m = _CHANNEL.match(exc[0])
        optic = optic or m["optic"]
        if m["optic"] != optic:
            msg = f"{path}: excites {m['optic']}, the other files {optic}"
            raise TFError(msg)
        column = {}
        for dof in DOFS:
            for point in POINTS:
                name = f"{m['ifo']}:SUS-{optic}_SUS{dof}_{point}"
                if name not in names:
                    continue
                f, h, g2, n = xml_transfer(acc, name, exc[0])
                if freq is None:
                    freq, averages = f, n
                elif len(f) != len(freq) or np.max(np.abs(f - freq)) > 1e-9:
                    msg = f"{path}: its frequency bins differ from the other files'"
                    raise TFError(msg)
                column[(dof, point)] = (h, g2)
        columns[m["dof"]] = column
    return assemble(optic, freq, columns, averages)


def xml_transfer(acc, numerator: str, denominator: str):  # noqa: ANN001, ANN201
    """``numerator/denominator`` of a diaggui measurement (a ``dttxml.DiagAccess`` or a
    path): frequencies, transfer function, coherence and number of averages."""
    import dttxml

    if not hasattr(acc, "xfer"):
        acc = dttxml.DiagAccess(str(acc))
    x = acc.xfer(numerator, denominator)
    return (np.asarray(x.FHz, dtype=float), np.asarray(x.xfer, dtype=complex),
            np.asarray(x.coh, dtype=float), int(x.averages))


def assemble(optic: str, freq: NDArray, columns: dict, averages: int) -> TFSet:
    """A TFSet from ``columns[excited][(response, point)] = (tf, coherence)``."""
    excited = [d for d in DOFS if d in columns]
    responses = [d for d in DOFS if all((d, p) in columns[e] for e in excited for p in POINTS)]
    if not excited or not set(excited) <= set(responses):
        msg = (f"need IN1, IN2 and OUT of every excited DOF in every measurement; excited "
               f"{excited}, complete responses {responses}")
        raise TFError(msg)
    shape = (len(freq), len(responses), len(excited))
    tf = {p: np.zeros(shape, dtype=complex) for p in POINTS}
    coh = {p: np.zeros(shape) for p in POINTS}
    for j, e in enumerate(excited):
        for i, r in enumerate(responses):
            for p in POINTS:
                tf[p][:, i, j], coh[p][:, i, j] = columns[e][(r, p)]
    return TFSet(optic, np.asarray(freq), excited, responses, tf, coh, averages)


# ------------------------------------------------------------------------------ MCAP sessions
def _test_point(optic: str | None) -> Callable[[str], bool]:
    """The channels ``from_session`` may use: EXC, IN1, IN2, OUT of a DOF (of `optic`)."""

    def wanted(name: str) -> bool:
        m = _CHANNEL.match(name)
        return bool(m) and m["point"] in ("EXC", *POINTS) and optic in (None, m["optic"])

    return wanted


def from_session(paths: Sequence[str | Path], bw: float = 0.01, overlap: float = 0.5,
                 optic: str | None = None, window: str = "hann", settle_s: float = 0.0,
                 highpass_hz: float | None = None) -> TFSet:
    """Welch transfer functions of the excitations recorded in MCAP sessions.

    Each excited DOF's segment runs from its injection's start to its end (the recorded
    ``start``/``end``/``stop`` events); Hann windows of ``1/bw`` seconds. Only the test
    points (EXC, IN1, IN2, OUT) are read, of `optic` if given; the response DOFs are those
    whose IN1, IN2 and OUT were recorded.

    Parameters
    ----------
    paths : sequence of path
        MCAP files of one session (see :func:`twind.recording.reader.session_files`).
    bw : float
        Resolution (Hz): segments of ``round(rate / bw)`` samples.
    overlap : float
        Fraction of a segment shared with the next.
    optic : str, optional
        The optic, when several were excited.
    window : str
        ``"hann"``, or ``"boxcar"`` for periodic excitations of period ``1/bw``.
    settle_s : float
        Seconds skipped at the start of each excitation (the loop's transient).
    highpass_hz : float, optional
        High-pass EXC and responses alike from the excitation's start (see
        :func:`highpassed`).

    Returns
    -------
    TFSet

    Raises
    ------
    TFError
        If no excitation is found, several optics were excited and `optic` is not given, or
        an excitation is shorter than ``1/bw``.
    """
    from twind.recording.fastread import read_channels

    session = read_channels(list(paths), _test_point(optic))
    rates = {ch.rate for ch in session.channels.values()}
    segments = _segments(session.events, max(rates) if rates else 16384.0)
    if optic is not None:
        segments = {k: v for k, v in segments.items() if k[1] == optic}
    if not segments:
        msg = f"{', '.join(map(str, paths))}: no excitation segment found in the injection events"
        raise TFError(msg)
    optics = {k[1] for k in segments}
    if len(optics) > 1:
        msg = f"excitations on several optics {sorted(optics)}: choose one with --optic"
        raise TFError(msg)
    columns, freq, averages = {}, None, None
    for (ifo, name, dof), (start, end) in segments.items():
        keys = [(r, p) for r in DOFS for p in POINTS
                if all(f"{ifo}:SUS-{name}_SUS{r}_{q}" in session for q in POINTS)]
        chans = [session[f"{ifo}:SUS-{name}_SUS{dof}_EXC"]] + [
            session[f"{ifo}:SUS-{name}_SUS{r}_{p}"] for r, p in keys]
        rate = chans[0].rate
        # channels of a recording joined mid-stream may begin a block apart: each is cut
        # by its own start time, over what all of them hold
        first = max([start] + [c.t0 for c in chans])
        last = min([end] + [c.t_end for c in chans])
        skip = max(int(round((start + settle_s - first) * rate)), 0)
        n = int(round((last - first) * rate))
        whole = [c.samples[int(round((first - c.t0) * c.rate)):][:n] for c in chans]
        if highpass_hz:
            x, *ys = highpassed(whole, rate, highpass_hz, skip)
        else:
            x, *ys = (w[skip:] for w in whole)
        nperseg = int(round(rate / bw))
        if x.size < nperseg:
            msg = (f"the {dof} excitation holds {x.size / rate:.1f} s of recorded data after "
                   f"{settle_s:g} s of settling, less than 1/bw = {1 / bw:g} s")
            raise TFError(msg)
        f, h, g2, navg = welch_tfs(x, ys, rate, nperseg, overlap, window=window)
        freq, averages = f, navg
        columns[dof] = {k: (h[i], g2[i]) for i, k in enumerate(keys)}
    tfs = assemble(next(iter(optics)), freq, columns, averages)
    tfs.window = window
    return tfs


def highpassed(signals: Sequence[NDArray], rate: float, f_hz: float, skip: int
               ) -> list[NDArray[np.float64]]:
    """Each signal through the same 8th-order Butterworth high-pass, less its first `skip`
    samples (where the filter's transient lives).

    A rectangular window leaks the large sub-0.2 Hz seismic motion into every bin, and its
    error barely changes from one short segment to the next, so the coherence cannot see
    it; filtering excitation and response alike leaves their ratio, and the periodic steady
    state, untouched.
    """
    sos = signal.butter(8, f_hz, btype="highpass", fs=rate, output="sos")
    return [signal.sosfilt(sos, np.asarray(x, dtype=float))[skip:] for x in signals]


def welch_tf(x: NDArray, y: NDArray, rate: float, nperseg: int, overlap: float = 0.5,
             window: str = "hann") -> tuple[NDArray, NDArray, NDArray, int]:
    """``H = CSD(x, y) / PSD(x)``, coherence, and the number of averages.

    The values of ``scipy.signal.csd``, ``welch`` and ``coherence`` (Hann window, constant
    detrend, one-sided density), from one FFT per segment of each signal: see
    :func:`welch_tfs`.
    """
    f, h, g2, n = welch_tfs(x, [y], rate, nperseg, overlap, window=window)
    return f, h[0], g2[0], n


def welch_tfs(x: NDArray, ys: Sequence[NDArray], rate: float, nperseg: int,
              overlap: float = 0.5, workers: int | None = None, window: str = "hann"
              ) -> tuple[NDArray[np.float64], NDArray[np.complex128], NDArray[np.float64], int]:
    """Transfer functions ``CSD(x, y) / PSD(x)`` and coherences of several responses to one
    excitation, as ``scipy.signal`` estimates them.

    scipy computes every segment's FFT again for each of ``csd``, ``welch`` and
    ``coherence`` (seven FFTs per pair); here each signal's segments are transformed once,
    with scipy's steps (mean removed, periodic Hann window, ``rfft``), and the cross and
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
    window : str
        scipy window name: ``"hann"`` (diaggui's default) or ``"boxcar"`` for a periodic
        excitation whose period is the segment (no leakage, no smoothing of H).
    workers : int, optional
        Threads, each summing its share of the segments; default the CPU count, at most 2
        (the FFTs of a few-megasample segment are memory bound).

    Returns
    -------
    frequency_hz : ndarray, shape (nperseg // 2 + 1,)
    tf : ndarray of complex, shape (len(ys), nfreq)
    coherence : ndarray, shape (len(ys), nfreq)
    averages : int
        Segments averaged.

    Raises
    ------
    TFError
        If a response is not as long as `x`, or `x` is shorter than a segment.
    """
    import os
    from concurrent.futures import ThreadPoolExecutor

    from scipy import fft

    x = np.asarray(x, dtype=np.float64)
    ys = [np.asarray(y, dtype=np.float64) for y in ys]
    if any(y.shape != x.shape for y in ys) or x.ndim != 1:
        msg = f"responses of {[y.shape for y in ys]} samples for an excitation of {x.shape}"
        raise TFError(msg)
    noverlap = int(nperseg * overlap)
    step = nperseg - noverlap
    if x.size < nperseg or step < 1:
        msg = f"{x.size} samples, segments of {nperseg} overlapping by {noverlap}: no average"
        raise TFError(msg)
    n = 1 + (x.size - nperseg) // step
    win = signal.get_window(window, nperseg)
    nf = nperseg // 2 + 1
    workers = max(1, min(workers or min(os.cpu_count() or 1, 2), n))

    def part(segs: range) -> tuple[NDArray, NDArray, NDArray]:
        sxx = np.zeros(nf)
        sxy = np.zeros((len(ys), nf), dtype=np.complex128)
        syy = np.zeros((len(ys), nf))
        buf = np.empty(nperseg)
        for k in segs:
            cut = slice(k * step, k * step + nperseg)
            X = _segment_fft(x[cut], win, buf, fft)
            _accumulate_auto(X, sxx)
            for i, y in enumerate(ys):
                _accumulate_cross(X, _segment_fft(y[cut], win, buf, fft), sxy[i], syy[i])
        return sxx, sxy, syy

    bounds = np.linspace(0, n, workers + 1).astype(int)
    ranges = [range(bounds[i], bounds[i + 1]) for i in range(workers)]
    if workers == 1:
        parts = [part(ranges[0])]
    else:
        with ThreadPoolExecutor(workers, thread_name_prefix="twind-welch") as pool:
            parts = list(pool.map(part, ranges))
    sxx, sxy, syy = (sum(p[j] for p in parts) for j in range(3))
    # scipy's density scaling and one-sided doubling; they cancel in H and the coherence
    # except through rounding, so they are applied as scipy applies them
    scale = np.full(nf, 1.0 / (rate * (win * win).sum()) / n)
    scale[1:-1 if nperseg % 2 == 0 else None] *= 2
    pxx = sxx * scale
    pxy = sxy * scale
    pyy = syy * scale
    freq = fft.rfftfreq(nperseg, 1.0 / rate)
    with np.errstate(invalid="ignore", divide="ignore"):  # bins a periodic EXC leaves empty
        return freq, pxy / pxx, np.abs(pxy) ** 2 / pxx / pyy, n


def _segment_fft(seg: NDArray, win: NDArray, buf: NDArray, fft) -> NDArray:
    """scipy.signal's segment: constant detrend, window, one-sided FFT."""
    np.subtract(seg, seg.mean(), out=buf)
    buf *= win
    return fft.rfft(buf, overwrite_x=True)


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


def _segments(events: list[dict], rate_hz: float = 16384.0
              ) -> dict[tuple[str, str, str], tuple[float, float]]:
    """The excitation interval of each excited test point.

    A stream lasts its samples, anything else its requested duration, cut short by a
    ``stop``.  Injections that follow each other on one channel without a gap (a long
    waveform streamed in several requests, as the service asks) are one excitation; of
    several separate ones the longest is used.
    """
    starts, ends = {}, {}
    for ev in events:
        if ev.get("event") == "start":
            starts[ev["id"]] = (ev["channel"], ev["start_gps"])
            req = ev.get("request") or {}
            samples = req.get("samples")
            duration = (samples["n"] / rate_hz if req.get("waveform") == "stream"
                        and isinstance(samples, dict) else req.get("duration"))
            if isinstance(duration, (int, float)) and np.isfinite(duration):
                ends[ev["id"]] = ev["start_gps"] + duration
        elif ev.get("event") == "stop" and ev.get("id") in starts:
            ends[ev["id"]] = min(ends.get(ev["id"], np.inf), ev["gps"])
    runs: dict[tuple[str, str, str], list[list[float]]] = {}
    for exc_id, (channel, start) in sorted(starts.items(), key=lambda kv: kv[1][1]):
        m = _CHANNEL.match(channel)
        if not (m and exc_id in ends):
            continue
        chain = runs.setdefault((m["ifo"], m["optic"], m["dof"]), [])
        if chain and abs(start - chain[-1][1]) < 0.5 / rate_hz:
            chain[-1][1] = ends[exc_id]
        else:
            chain.append([start, ends[exc_id]])
    return {k: tuple(max(v, key=lambda r: r[1] - r[0])) for k, v in runs.items()}
