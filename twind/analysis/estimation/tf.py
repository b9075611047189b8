"""Transfer functions from the damping loop's test points: IN1/EXC, IN2/EXC, OUT/EXC, each
with its coherence and standard error, assembled into [response DOF x excited DOF] matrices,
and the open-loop plant recovered from them (docs/model.md's sign convention):

    P = (IN1/EXC) (IN2/EXC)^-1 K^-1 = (IN1/EXC) (OUT/EXC)^-1

Sources: diaggui "Fourier tools" XML files (one per excited DOF, read with dttxml) and MCAP
sessions of the twin (excitation segments from the recorded injection events; Welch estimates
with scipy.signal). The standard error of a Welch estimate is Bendat & Piersol's
``|H| sqrt((1 - g^2) / (2 n g^2))`` for ``n`` averages and coherence ``g^2``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import dttxml
import h5py
import numpy as np
import scipy.io
from numpy.typing import NDArray
from scipy import signal, stats

from twind import DOFS
from twind.channels import DOF_CHANNEL, dof_channel
from twind.analysis.estimation.demodulation import AVERAGES, DemodulationError, demodulate
from twind.analysis.estimation.excitations import (SHORTEST_S, Stretch, at_one_rate, every,
                                                   longest, with_exc)
from twind.analysis.estimation.lpm import LPMEstimate, lpm_tfs
from twind.analysis.estimation.welch import Extent, Segment, WelchStream, welch_tf, welch_tfs
from twind.errors import MeasurementWarning, TwindError
from twind.recording.fastread import event_count, read_channels, stream_channels
from twind.recording.frames import is_frames, read_frames, same_channels
from twind.recording.session import Channel
from twind.recording.validate import event_problem, excitation_problem

__all__ = ["ESTIMATORS", "POINTS", "Kernel", "TFError", "TFSet", "assemble", "from_diaggui", "from_session",
           "highpassed", "welch_tf", "welch_tfs", "xml_transfer"]

POINTS = ("IN1", "IN2", "OUT")
ESTIMATORS = ("welch", "lpm")
"""Welch's (diaggui's), or the local polynomial method's (:mod:`twind.analysis.estimation.lpm`)."""


class TFError(TwindError):
    """A measurement cannot be turned into transfer functions."""


@dataclass(frozen=True)
class Kernel:
    """What an estimate at frequency ``f`` sees of the true response of excited DOF ``e``:
    ``sum_r weights[f, r, e] G(f + offsets_hz[r])`` (the LPM's, which depends on the
    excitation's spectrum; :mod:`twind.analysis.estimation.lpm`)."""

    offsets_hz: NDArray[np.float64]  # (K,)
    weights: NDArray[np.complex128]  # (nf, K, n_excited)


def coherence_floor(averages: int, tests: int, at_least: float = 0.5,
                    false_alarm: float = 0.01) -> float:
    """The coherence a bin must reach to count as driven: `at_least`, and more than an
    undriven bin reaches in any of `tests` bins but with probability `false_alarm`.

    With ``n`` averages an undriven bin's estimate exceeds ``x`` with probability
    ``(1 - x)^(n - 1)`` (Carter, Knapp and Nuttall 1973): with 3 averages a quarter of the
    noise passes 0.5, and a recording's 800 000 bins reach it up to Nyquist.

    Parameters
    ----------
    averages : int
        Welch averages of the estimate (one: no bin can be told from noise).
    tests : int
        Bins (elements x frequencies) looked at together.
    at_least : float
        The floor whatever the averages.
    false_alarm : float
        Probability that noise alone passes in any of the `tests` bins.

    Returns
    -------
    float
        The coherence to reach (``inf`` with one average).

    Examples
    --------
    >>> round(coherence_floor(10, 36012), 3)
    0.813
    """
    if averages < 2:
        return math.inf  # one average's coherence is 1, whatever the signals
    return max(at_least, 1.0 - (false_alarm / max(tests, 1)) ** (1.0 / (averages - 1)))


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
    window: str = "hann"  # of the spectral estimates: "hann" smooths H over ~1 bin; "lpm"
    exc_psd: dict[str, NDArray[np.float64]] | None = None  # per excited DOF, when known
    error: dict[str, NDArray[np.float64]] | None = None  # the estimator's own, when it has one
    kernel: Kernel | None = None  # when the estimate is not the TF at its frequency
    # correlation of the IN1/EXC errors of the responses, [f, response, response, excited]
    # (the LPM's; Welch's are taken as independent)
    in1_correlation: NDArray[np.complex128] | None = None
    found: tuple[str, ...] = ()  # the excitations found in the data (no injection events)
    ifo: str = "C1"  # the interferometer prefix of the channels measured
    # GPS start and end of each excited DOF's excitation; the end None where a file gives
    # only the start (diaggui)
    spans: dict[str, tuple[float, float | None]] = field(default_factory=dict)

    def sigma(self, point: str) -> NDArray[np.float64]:
        """Standard error of the real and of the imaginary part of each element of
        ``point``/EXC: the estimator's own (the LPM's, from its residuals), else Bendat &
        Piersol's from the coherence."""
        if self.error is not None:
            return self.error[point]
        g2 = np.clip(self.coherence[point], 1e-12, 1.0)
        return np.abs(self.tf[point]) * np.sqrt((1 - g2) / (2 * self.averages * g2))

    def estimate(self) -> str:
        """How the TFs were estimated, for a title or a report: ``"Welch (hann), 19
        averages, 0.05 Hz bins"`` or ``"LPM, 0.0167 Hz bins"``."""
        f = self.frequency_hz
        df = f"{float(np.median(np.diff(f))):.3g} Hz bins" if f.size > 1 else "one bin"
        how = "LPM" if self.window == "lpm" else f"Welch ({self.window}), {self.averages} averages"
        return f"{how}, {df}"

    def description(self) -> dict[str, str]:
        """What a figure or report of these TFs shows: ``channels``, ``GPS`` span and
        ``estimate``."""
        points = "{IN1,IN2,OUT}/_EXC"
        starts = [a for a, _ in self.spans.values()]
        ends = [b for _, b in self.spans.values()]
        if not starts:
            gps = "not recorded"
        elif None in ends:
            gps = f"from {min(starts):.0f}"
        else:
            gps = f"{min(starts):.0f}-{max(ends):.0f}"
        return {"channels": f"{self.ifo}:SUS-{self.optic}_SUS<DOF>_{points}, "
                            f"<DOF> {', '.join(self.excited)}",
                "GPS": gps, "estimate": self.estimate()}

    def caption(self) -> str:
        """:meth:`description` in one line, for a figure."""
        return "; ".join(f"GPS {v}" if k == "GPS" else v for k, v in self.description().items())

    def plant(self) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """The open-loop plant over the excited DOFs and its standard error.

        ``P = (IN1/EXC)(OUT/EXC)^-1`` restricted to the excited DOFs' rows; the error is
        propagated to first order from the errors of both matrices, taken as independent.
        Both come from the same noise, so the sigma is conservative: the residuals of a
        twin recording against its model have about half the power it predicts
        (tests/test_tf.py).

        Returns
        -------
        P : ndarray, shape (nf, excited, excited)
            ``IN1/OUT`` (um/ct or urad/ct).
        sigma : ndarray, shape (nf, excited, excited)
            Standard error of its real and of its imaginary parts.
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

    def coherent(self, point: str = "IN1", at_least: float = 0.5) -> NDArray[np.bool_]:
        """The elements of ``point``/EXC driven by their excitation, bin by bin.

        Parameters
        ----------
        point : str
            ``IN1``, ``IN2`` or ``OUT``.
        at_least : float
            The coherence a bin must reach whatever the averages.

        Returns
        -------
        ndarray of bool, shape (nf, responses, excited)
            Where the coherence reaches :func:`coherence_floor` over every element.
        """
        g2 = self.coherence[point]
        return g2 >= coherence_floor(self.averages, g2.size, at_least)

    def coherent_band(self, at_least: float = 0.5) -> tuple[float, float] | None:
        """From the lowest to the highest frequency where some excited DOF's IN1 is driven by
        its own EXC (:meth:`coherent`, and for the LPM's estimates above their own errors at
        1 % over every bin): where the excitation reached the optic. None when no frequency
        is."""
        rows = [self.responses.index(d) for d in self.excited]
        own = self.coherent("IN1", at_least)[:, rows, np.arange(len(rows))]
        if self.error is not None:  # the LPM's: its coherence passes many undriven bins
            h = self.tf["IN1"][:, rows, np.arange(len(rows))]
            snr = np.abs(h) ** 2 / (2 * self.error["IN1"][:, rows, np.arange(len(rows))] ** 2)
            # |H / sigma|^2 / 2 of an undriven bin is F(2, 2n - 2): none of them passes
            own &= snr >= stats.f.isf(0.01 / snr.size, 2, 2 * max(self.averages - 1, 1))
        hit = np.flatnonzero(own.any(axis=1))
        f = self.frequency_hz
        return (float(f[hit[0]]), float(f[hit[-1]])) if hit.size else None

    def band(self, lo: float, hi: float) -> TFSet:
        """Only the frequencies in [lo, hi] (Hz).

        Parameters
        ----------
        lo, hi : float
            The band's edges (Hz), both kept.

        Returns
        -------
        TFSet

        Raises
        ------
        TFError
            If no measured frequency is in the band.
        """
        keep = (self.frequency_hz >= lo) & (self.frequency_hz <= hi)
        if not keep.any():
            msg = (f"no measured frequency in {lo:g}-{hi:g} Hz; the measurement covers "
                   f"{self.frequency_hz.min():g}-{self.frequency_hz.max():g} Hz")
            raise TFError(msg)
        return replace(
            self, frequency_hz=self.frequency_hz[keep],
            tf={k: v[keep] for k, v in self.tf.items()},
            coherence={k: v[keep] for k, v in self.coherence.items()},
            exc_psd={k: v[keep] for k, v in self.exc_psd.items()} if self.exc_psd else None,
            error={k: v[keep] for k, v in self.error.items()} if self.error else None,
            kernel=Kernel(self.kernel.offsets_hz, self.kernel.weights[keep])
            if self.kernel else None,
            in1_correlation=None if self.in1_correlation is None else self.in1_correlation[keep])

    def write(self, path: str | Path) -> Path:
        """Write the transfer functions, their coherence, errors and the plant.

        Parameters
        ----------
        path : path
            ``.h5``/``.hdf5`` (one complex dataset per test point), ``.csv`` (one row per
            frequency, columns named like ``IN1_POS_per_PIT_re``) or ``.mat`` (MATLAB:
            :meth:`write_mat`).

        Returns
        -------
        Path

        Raises
        ------
        TFError
            If the file exists (never overwritten) or its suffix is neither.
        """
        path = Path(path)
        if path.exists():
            msg = f"{path} exists; twind does not overwrite results"
            raise TFError(msg)
        P, Ps = self.plant()
        if path.suffix.lower() in (".h5", ".hdf5"):
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
        if path.suffix.lower() == ".mat":
            return self.write_mat(path)
        msg = f"{path}: write .h5, .hdf5, .csv or .mat (or .png for a plot)"
        raise TFError(msg)

    def write_mat(self, path: Path) -> Path:
        """A MATLAB file (``scipy.io.loadmat`` reads it too): 3-D arrays indexed
        ``[frequency, response, excited]``, ``IN1_per_EXC``, ``IN2_per_EXC``,
        ``OUT_per_EXC`` (complex), their ``coherence_*``, ``SNR_*`` (``g2 / (1 - g2)``,
        dttxml's and the seed's) and ``sigma_*``; ``plant`` and ``plant_sigma``
        (``[frequency, excited, excited]``); ``frequency_hz``; the channels as cell arrays
        (``EXC_channels`` by column, ``IN1_channels``... by row); ``optic``, ``excited``,
        ``responses``, ``averages``.
        """
        P, Ps = self.plant()

        def channels(dofs: list[str], point: str) -> NDArray:
            return np.array([dof_channel(self.ifo, self.optic, d, point) for d in dofs],
                            dtype=object)

        data = {"frequency_hz": self.frequency_hz, "optic": self.optic,
                "excited": np.array(self.excited, dtype=object),
                "responses": np.array(self.responses, dtype=object),
                "averages": self.averages, "EXC_channels": channels(self.excited, "EXC"),
                "plant": P, "plant_sigma": Ps}
        for p in POINTS:
            g2 = self.coherence[p]
            with np.errstate(divide="ignore"):
                data[f"SNR_{p}"] = g2 / (1 - g2)
            data.update({f"{p}_per_EXC": self.tf[p], f"coherence_{p}": g2,
                         f"sigma_{p}": self.sigma(p), f"{p}_channels": channels(
                             self.responses, p)})
        with path.open("xb") as f:
            scipy.io.savemat(f, data, do_compression=True)
        return path

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
    """Transfer functions from diaggui XML files, one per excited DOF (dttxml's ``xfer``).

    Parameters
    ----------
    paths : sequence of path
        diaggui "Fourier tools" measurements: in each, one ``_EXC`` channel and the IN1,
        IN2 and OUT test points of the responses.

    Returns
    -------
    TFSet

    Raises
    ------
    TFError
        If a file is not readable diaggui XML, has no single excitation, or the files
        disagree on the optic or the frequencies.
    """
    columns, freq, optic, averages, ifo, spans = {}, None, None, None, "C1", {}
    for path in paths:
        try:
            acc = dttxml.DiagAccess(str(path))
        except Exception as err:  # noqa: BLE001 - dttxml raises many kinds on a bad file
            msg = f"{path}: not a readable diaggui XML file ({type(err).__name__}: {err})"
            raise TFError(msg) from None
        names = sorted(acc.channels()[0])
        exc = [n for n in names if n.endswith("_EXC") and DOF_CHANNEL.match(n)]
        if len(exc) != 1:
            others = [n for n in names if n.endswith("_EXC")] or names
            msg = (f"{path}: a suspension measurement has one excitation named "
                   "<IFO>:SUS-<OPTIC>_SUS<DOF>_EXC (channel A) and its _IN1, _IN2, _OUT as "
                   f"channels B; this file has {', '.join(exc or others[:4])} "
                   "(`twind tf` shows any measurement's transfer functions)")
            raise TFError(msg)
        m = DOF_CHANNEL.match(exc[0])
        optic, ifo = optic or m["optic"], m["ifo"]
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
                if m["dof"] not in spans:  # diaggui keeps the start only
                    spans[m["dof"]] = (float(acc.xfer(name, exc[0]).gps_second or 0.0), None)
                _warn_unusable(path, name, exc[0], h, g2)
                if freq is None:
                    freq, averages = f, n
                elif len(f) != len(freq) or np.max(np.abs(f - freq)) > 1e-9:
                    msg = f"{path}: its frequency bins differ from the other files'"
                    raise TFError(msg)
                column[(dof, point)] = (h, g2)
        columns[m["dof"]] = column
    return replace(assemble(optic, freq, columns, averages, ifo), spans=spans)


def _warn_unusable(path: str | Path, name: str, exc: str, h: NDArray, g2: NDArray) -> None:
    """Say which bins of `name`/`exc` are NaN or inf: every fit leaves them out."""
    bad = ~(np.isfinite(h) & np.isfinite(g2))
    if bad.any():
        warnings.warn(f"{path}: {name}/{exc}: {int(bad.sum())} of {bad.size} bins are NaN "
                      "or inf and are left out", MeasurementWarning, stacklevel=3)


def xml_transfer(acc, numerator: str, denominator: str):  # noqa: ANN001, ANN201
    """``numerator/denominator`` of a diaggui measurement (a ``dttxml.DiagAccess`` or a
    path): frequencies, transfer function, coherence and number of averages.

    Parameters
    ----------
    acc : dttxml.DiagAccess or str or Path
        The open measurement, or its file.
    numerator : str
        Channel B, e.g. ``C1:SUS-ETMX_SUSPOS_IN1``.
    denominator : str
        Channel A, e.g. ``C1:SUS-ETMX_SUSPOS_EXC``.

    Returns
    -------
    frequency_hz : ndarray
    tf : ndarray of complex
    coherence : ndarray
    averages : int
    """

    if not hasattr(acc, "xfer"):
        acc = dttxml.DiagAccess(str(acc))
    x = acc.xfer(numerator, denominator)
    return (np.asarray(x.FHz, dtype=float), np.asarray(x.xfer, dtype=complex),
            np.asarray(x.coh, dtype=float), int(x.averages))


def assemble(optic: str, freq: NDArray, columns: dict, averages: int, ifo: str = "C1"
             ) -> TFSet:
    """A TFSet from ``columns[excited][(response, point)] = (tf, coherence)``, or
    ``(tf, coherence, sigma)`` from an estimator with its own errors.

    Parameters
    ----------
    optic : str
        The optic's name (``ETMX``).
    freq : ndarray
        The frequencies (Hz) every column shares.
    columns : dict
        By excited DOF, a dict of ``(response DOF, point)`` to its arrays; point ``IN1``,
        ``IN2`` or ``OUT``.
    averages : int
        Averages of the estimates.
    ifo : str
        The interferometer prefix of the channels.

    Returns
    -------
    TFSet
        Responses are the DOFs with IN1, IN2 and OUT in every column.

    Raises
    ------
    TFError
        If nothing is excited, or an excited DOF lacks IN1, IN2 or OUT in some column.
    """
    excited = [d for d in DOFS if d in columns]
    responses = [d for d in DOFS if all((d, p) in columns[e] for e in excited for p in POINTS)]
    if not excited or not set(excited) <= set(responses):
        msg = (f"need IN1, IN2 and OUT of every excited DOF in every measurement; excited "
               f"{excited}, complete responses {responses}")
        raise TFError(msg)
    shape = (len(freq), len(responses), len(excited))

    def matrix(p: str, k: int) -> NDArray:
        # every element is written: np.zeros would fault each page in twice
        out = np.empty(shape, dtype=complex if k == 0 else float)
        for j, e in enumerate(excited):
            for i, r in enumerate(responses):
                out[:, i, j] = columns[e][(r, p)][k]
        return out

    # an hour at 0.01 Hz is 0.5 GB of new memory: faulted in on two threads
    with ThreadPoolExecutor(2) as pool:
        tf = dict(zip(POINTS, pool.map(matrix, POINTS, [0] * len(POINTS)), strict=True))
        coh = dict(zip(POINTS, pool.map(matrix, POINTS, [1] * len(POINTS)), strict=True))
    own = len(next(iter(columns[excited[0]].values()))) == 3
    err = {p: matrix(p, 2) for p in POINTS} if own else None
    return TFSet(optic, np.asarray(freq), excited, responses, tf, coh, averages, error=err,
                 ifo=ifo)


# ------------------------------------------------------------------------------ MCAP sessions
def _test_point(optic: str | None) -> Callable[[str], bool]:
    """The channels ``from_session`` may use: EXC, IN1, IN2, OUT of a DOF (of `optic`)."""

    def wanted(name: str) -> bool:
        m = DOF_CHANNEL.match(name)
        return bool(m) and m["point"] in ("EXC", *POINTS) and optic in (None, m["optic"])

    return wanted


def from_session(paths: Sequence[str | Path], bw: float = 0.01, overlap: float = 0.5,
                 optic: str | None = None, window: str = "hann", settle_s: float = 0.0,
                 highpass_hz: float | None = None, estimator: str = "welch",
                 max_hz: float | None = None, mapping: Mapping[str, str] | None = None,
                 exc_times: Mapping[str, tuple[float, float]] | None = None) -> TFSet:
    """Transfer functions of the excitations recorded in MCAP sessions, gwpy HDF5 files or
    GWF frames.

    Each excited DOF's segment runs from its injection's start to its end: `exc_times`,
    the recorded ``start``/``end``/``stop`` events, or where there are none the EXC
    channel's longest nonzero stretch (:mod:`~twind.analysis.estimation.excitations`;
    single sines found so are each :mod:`demodulated <.demodulation>`; an EXC not recorded
    is IN2 - IN1). Only the test points are read, of `optic` if given, brought to the
    slowest one's rate; the response DOFs are those whose IN1, IN2 and OUT were recorded.
    The Welch sums of an MCAP session with events are taken while it is read
    (:class:`~twind.analysis.estimation.welch.WelchStream`); with gaps, late events or a
    high-pass it is read whole instead, with the same result.

    Parameters
    ----------
    paths : sequence of path
        MCAP files of one session (see :func:`twind.recording.session.session_files`), or
        HDF5 files or GWF frames (:func:`twind.recording.frames.read_frames`): pieces of
        one recording, or measurements a file each, each with its own channels (:func:`merged`).
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
    estimator : str
        ``"welch"``, or ``"lpm"``: Pintelon and Schoukens' local polynomial method over each
        excitation's whole record (:mod:`twind.analysis.estimation.lpm`; `bw`, `overlap` and `window`
        unused). Every excitation is cut to the shortest one's length, so that their
        estimates fall on the same frequencies.
    max_hz : float, optional
        LPM: estimates up to here are those of the whole band (default: Nyquist).
    mapping : mapping of str to str, optional
        HDF5 and GWF: recorded channel names to the twin's
        (:func:`twind.recording.frames.renamer`; ``_DQ`` is dropped anyway).
    exc_times : mapping of str to (float, float), optional
        GPS start and end of each excited DOF's excitation, given by hand (before any
        found in the events or the data).

    Returns
    -------
    TFSet

    Raises
    ------
    TFError
        If no excitation is found, several optics were excited and `optic` is not given, an
        excitation is shorter than ``1/bw`` (a sine: than demodulation needs), or sines and
        other waveforms were found on different DOFs.
    """
    check_estimator(estimator)
    frames = any(is_frames(p) for p in paths)
    if frames and len(paths) > 1 and not same_channels(paths):  # a measurement a file
        each = (bw, overlap, optic, window, settle_s, highpass_hz, estimator, max_hz, mapping)
        return merged([from_session([p], *each, exc_times) for p in paths], list(map(str, paths)))
    # a session without events is read whole once, not streamed first to no end
    if (not (highpass_hz or frames or exc_times) and estimator == "welch"
            and event_count(paths) != 0):
        if (tfs := _streamed(paths, bw, overlap, optic, window, settle_s)) is not None:
            return tfs
    session = (read_frames(paths, _test_point(optic), mapping) if frames
               else read_channels(list(paths), _test_point(optic)))
    channels = with_exc(at_one_rate(session.channels))
    extents = {n: Extent(c.t0, c.rate, len(c.samples)) for n, c in channels.items()}
    # stream events count samples at the model's rate: the fastest channel's, as recorded
    segments, notes, sines = _excitations(session.events, channels, optic, paths, exc_times,
                                          _rate({n: Extent(c.t0, c.rate, 0)
                                                 for n, c in session.channels.items()}))
    if sines:
        return _demodulated(channels, extents, sines, settle_s, notes)
    plans = {key: _Plan.of(key, start, end, extents, settle_s)
             for key, (start, end) in segments.items()}
    shortest = min(plan.n - plan.skip for plan in plans.values())
    columns, freq, averages, estimates = {}, None, None, {}
    for key, plan in plans.items():
        x, *ys = _samples(channels, plan, highpass_hz)
        rate = channels[plan.names[0]].rate
        if estimator == "lpm":
            est, columns[key[2]] = lpm_column(x[:shortest], [y[:shortest] for y in ys], rate,
                                              plan.keys, max_hz)
            freq, averages, estimates[key[2]] = est.frequency_hz, est.averages, est
            continue
        nperseg = _nperseg(rate, bw, plan, settle_s)
        freq, h, g2, averages = welch_tfs(x, ys, rate, nperseg, overlap, window=window)
        columns[key[2]] = {k: (h[i], g2[i]) for i, k in enumerate(plan.keys)}
    tfs = replace(assemble(key[1], freq, columns, averages, key[0]), window=window, found=notes,
                  spans={k[2]: span for k, span in segments.items()})
    return with_lpm(tfs, estimates) if estimates else tfs


def _samples(channels: Mapping[str, Channel], plan: _Plan, highpass_hz: float | None = None
             ) -> list[NDArray[np.float64]]:
    """EXC and then the responses of `plan`, after its settling (high-passed from the
    excitation's start if asked, :func:`highpassed`)."""
    whole = [channels[c].samples[o:][:plan.n] for c, o in zip(plan.names, plan.offsets,
                                                               strict=True)]
    if highpass_hz:
        return highpassed(whole, channels[plan.names[0]].rate, highpass_hz, plan.skip)
    return [w[plan.skip:] for w in whole]


def check_estimator(estimator: str) -> None:
    """A TFError unless `estimator` is one of :data:`ESTIMATORS`."""
    if estimator not in ESTIMATORS:
        msg = f"unknown estimator {estimator!r}: one of {', '.join(ESTIMATORS)}"
        raise TFError(msg)


def lpm_column(x: NDArray[np.float64], ys: Sequence[NDArray[np.float64]], rate: float,
               keys: Sequence[tuple[str, str]], max_hz: float | None = None
               ) -> tuple[LPMEstimate, dict]:
    """One excitation's LPM estimate, its IN1 responses' errors correlated, and
    :func:`assemble`'s column of it; `keys` name `ys` ((response DOF, point), in order).

    Parameters
    ----------
    x : ndarray
        The EXC samples.
    ys : sequence of ndarray
        The responses' samples, each as long as `x`.
    rate : float
        Sample rate (Hz).
    keys : sequence of (str, str)
        ``(response DOF, point)`` of each of `ys`.
    max_hz : float, optional
        Estimates up to here are those of the whole band (default: Nyquist).

    Returns
    -------
    estimate : LPMEstimate
    column : dict
        ``(response DOF, point)`` to ``(tf, coherence, sigma)``.
    """
    est = lpm_tfs(x, ys, rate, max_hz=max_hz,
                  correlated=[i for i, (_, p) in enumerate(keys) if p == "IN1"])
    return est, {k: (est.tf[i], est.coherence[i], est.sigma[i]) for i, k in enumerate(keys)}


def with_lpm(tfs: TFSet, estimates: Mapping[str, LPMEstimate]) -> TFSet:
    """`tfs` marked as LPM estimates, with their kernel and IN1 error correlation, from the
    estimate of each excited DOF (its IN1 responses correlated, in `tfs.responses`' order).

    Parameters
    ----------
    tfs : TFSet
        The assembled LPM estimates; changed in place.
    estimates : mapping of str to LPMEstimate
        The estimate of each excited DOF.

    Returns
    -------
    TFSet
        `tfs` itself.
    """
    first = estimates[tfs.excited[0]]
    tfs.window = "lpm"
    tfs.kernel = Kernel(first.offsets_hz,
                        np.stack([estimates[d].weights for d in tfs.excited], axis=-1))
    rho = [estimates[d].correlation for d in tfs.excited]
    if all(r is not None and r.shape[1] == len(tfs.responses) for r in rho):
        tfs.in1_correlation = np.stack(rho, axis=-1)
    return tfs


@dataclass(frozen=True)
class _Plan:
    """The samples of one excitation: its channels (EXC first), the index in each of the
    excitation's first sample, the samples skipped while the loop settles, the samples."""

    keys: tuple[tuple[str, str], ...]  # (response DOF, point) of names[1:]
    names: tuple[str, ...]
    offsets: tuple[int, ...]
    skip: int
    n: int

    @classmethod
    def of(cls, key: tuple[str, str, str], start: float, end: float,
           extents: Mapping[str, Extent], settle_s: float) -> _Plan:
        """The plan for excitation `key` (ifo, optic, DOF) from `start` to `end` (GPS)."""
        ifo, name, _ = key
        keys = tuple((r, p) for r in DOFS for p in POINTS
                     if all(f"{ifo}:SUS-{name}_SUS{r}_{q}" in extents for q in POINTS))
        names = (_exc(key), *(f"{ifo}:SUS-{name}_SUS{r}_{p}" for r, p in keys))
        if names[0] not in extents:
            msg = f"{names[0]} was excited but is not in the recording"
            raise TFError(msg)
        rate = extents[names[0]].rate
        # channels of a recording joined mid-stream may begin a block apart: each is cut
        # by its own start time, over what all of them hold
        first = max([start] + [extents[c].t0 for c in names])
        last = min([end] + [extents[c].t_end for c in names])
        offsets = tuple(int(round((first - extents[c].t0) * extents[c].rate)) for c in names)
        return cls(keys, names, offsets, max(int(round((start + settle_s - first) * rate)), 0),
                   max(int(round((last - first) * rate)), 0))

    @property
    def segment(self) -> Segment:
        """What is averaged, after the settling."""
        return Segment(self.names, tuple(o + self.skip for o in self.offsets),
                       max(self.n - self.skip, 0))


NICE_BW = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)
"""Resolutions suggested when an excitation is too short for the one asked (Hz)."""


def _nperseg(rate: float, bw: float, plan: _Plan, settle_s: float) -> int:
    """Samples per segment; refused if the excitation holds fewer."""
    nperseg = int(round(rate / bw))
    if plan.n - plan.skip < nperseg:
        dof = DOF_CHANNEL.match(plan.names[0])["dof"]
        held = max(plan.n - plan.skip, 0) / rate
        coarser = next((f"; --bw {b:g} needs {1 / b:g} s" for b in NICE_BW
                        if held and b > bw and 1 / b <= held), "")
        msg = (f"the {dof} excitation holds {held:.1f} s of recorded data after {settle_s:g} s "
               f"of settling, less than 1/bw = {1 / bw:g} s (--bw, default 0.01 Hz){coarser}")
        raise TFError(msg)
    return nperseg


def _excitations(events: list[dict], channels: Mapping[str, Channel], optic: str | None,
                 paths: Sequence[str | Path],
                 exc_times: Mapping[str, tuple[float, float]] | None, rate_hz: float
                 ) -> tuple[dict[tuple[str, str, str], tuple[float, float]], tuple[str, ...],
                            dict[tuple[str, str, str], list[Stretch]]]:
    """The excitation of each excited DOF of one optic: given by hand, from the injection
    events (stream lengths counted at `rate_hz`), or else found in the EXC channels' data
    (refused: none, several optics, sines on some DOFs and other waveforms on others); those
    found in the data, described; and the single sines found, to demodulate."""
    if exc_times:
        segments = {key: exc_times[key[2]] for key in _exc_keys(channels)
                    if key[2] in exc_times}
        if not segments:
            msg = (f"--exc-times {', '.join(exc_times)}: no EXC channel of that DOF in "
                   f"{', '.join(map(str, paths))}; IN1/EXC needs it recorded")
            raise TFError(msg)
    else:
        segments = _segments(events, rate_hz)
    notes: tuple[str, ...] = ()
    sines: dict[tuple[str, str, str], list[Stretch]] = {}
    if not exc_times and not any(optic in (None, k[1]) for k in segments):
        runs = {k: v for k, v in every(channels).items() if optic in (None, k[1])}
        stretches = longest(runs)
        sines = {k: [s for s in v if s.waveform == "sine"] for k, v in runs.items()}
        sines = {k: v for k, v in sines.items() if v}
        if sines and set(sines) != set(stretches):
            msg = (f"sines on {', '.join(k[2] for k in sines)} and other waveforms on "
                   f"{', '.join(k[2] for k in set(stretches) - set(sines))}: twind estimates "
                   "one kind per measurement (give the spans with --exc-times DOF:START:END)")
            raise TFError(msg)
        segments = {k: (s.start, s.end) for k, s in stretches.items()}
        notes = tuple(str(x) for k in stretches for x in sines.get(k, [stretches[k]]))
    if optic is not None:
        segments = {k: v for k, v in segments.items() if k[1] == optic}
    if not segments:
        msg = (f"{', '.join(map(str, paths))}: no excitation found: no injection events, no "
               f"nonzero EXC stretch of {SHORTEST_S:g} s or more in the data (give the spans "
               "with --exc-times DOF:START:END)")
        raise TFError(msg)
    optics = {k[1] for k in segments}
    if len(optics) > 1:
        msg = f"excitations on several optics {sorted(optics)}: choose one with --optic"
        raise TFError(msg)
    return segments, notes, sines


def _demodulated(channels: Mapping[str, Channel], extents: Mapping[str, Extent],
                 sines: Mapping[tuple[str, str, str], list[Stretch]], settle_s: float,
                 notes: tuple[str, ...]) -> TFSet:
    """Each excited DOF's sines demodulated (:func:`demodulate`), on the frequencies of all
    of them: NaN where a DOF's sines did not reach."""
    found_at: dict[str, dict[float, tuple[NDArray, NDArray]]] = {}
    keys = {}
    for key, stretches in sines.items():
        for s in stretches:
            plan = _Plan.of(key, s.start, s.end, extents, settle_s)
            keys[key[2]] = plan.keys
            x, *ys = _samples(channels, plan)
            try:
                f, h, g2 = demodulate(x, ys, channels[plan.names[0]].rate, s.tones_hz[0])
            except DemodulationError as e:
                raise TFError(f"{s}: {e}") from None
            found_at.setdefault(key[2], {})[round(f, 6)] = (h, g2)
    freq = np.array(sorted({f for by_f in found_at.values() for f in by_f}))
    columns = {}
    for dof, by_f in found_at.items():
        h = np.full((len(keys[dof]), freq.size), np.nan, dtype=complex)
        g2 = np.zeros((len(keys[dof]), freq.size))
        for f, (hf, gf) in by_f.items():
            h[:, np.searchsorted(freq, f)], g2[:, np.searchsorted(freq, f)] = hf, gf
        columns[dof] = {k: (h[i], g2[i]) for i, k in enumerate(keys[dof])}
    tfs = assemble(next(iter(sines))[1], freq, columns, AVERAGES, next(iter(sines))[0])
    tfs.window, tfs.found = "sine", notes
    tfs.spans = {k[2]: (min(s.start for s in v), max(s.end for s in v))
                 for k, v in sines.items()}
    return tfs


def merged(sets: Sequence[TFSet], names: Sequence[str]) -> TFSet:
    """The columns of measurements made one after another (files of their own) as one set.

    Parameters
    ----------
    sets : sequence of TFSet
        Of one optic, on the same frequencies, each excitation in one of them.
    names : sequence of str
        Where each came from, for the errors.

    Returns
    -------
    TFSet
        Its averages the fewest of any.

    Raises
    ------
    TFError
        If the optics or frequencies differ, or a DOF was excited in two of them.
    """
    first = sets[0]
    for t, name in zip(sets[1:], names[1:], strict=True):
        if t.optic != first.optic:
            msg = f"{name} measures {t.optic}, {names[0]} {first.optic}"
            raise TFError(msg)
        if t.frequency_hz.shape != first.frequency_hz.shape or np.max(
                np.abs(t.frequency_hz - first.frequency_hz)) > 1e-9:
            msg = f"{name}: its frequency bins differ from {names[0]}'s (another rate or --bw?)"
            raise TFError(msg)
    columns, where = {}, {}
    for t, name in zip(sets, names, strict=True):
        for j, e in enumerate(t.excited):
            if e in where:
                msg = f"{e} is excited in both {where[e]} and {name}"
                raise TFError(msg)
            where[e] = name
            columns[e] = {(r, p): (t.tf[p][:, i, j], t.coherence[p][:, i, j],
                                   *((t.error[p][:, i, j],) if t.error else ()))
                          for i, r in enumerate(t.responses) for p in POINTS}
    out = assemble(first.optic, first.frequency_hz, columns, min(t.averages for t in sets),
                   first.ifo)
    rho = None  # the LPM's IN1 error correlation, where every set has the same responses
    if all(t.in1_correlation is not None and t.responses == out.responses for t in sets):
        rho = np.concatenate([t.in1_correlation for t in sets], axis=-1)
    return replace(out, window=first.window, kernel=first.kernel, in1_correlation=rho,
                   found=tuple(x for t in sets for x in t.found),
                   spans={k: v for t in sets for k, v in t.spans.items()})


def _exc_keys(channels: Mapping[str, Channel]) -> list[tuple[str, str, str]]:
    """(ifo, optic, DOF) of every EXC channel recorded."""
    return [(m["ifo"], m["optic"], m["dof"]) for m in map(DOF_CHANNEL.match, channels)
            if m and m["point"] == "EXC"]


def _streamed(paths: Sequence[str | Path], bw: float, overlap: float, optic: str | None,
              window: str, settle_s: float) -> TFSet | None:
    """:func:`from_session` summed while reading; None where the recording must be read whole
    (gaps, events recorded late or none, an excitation shorter than a segment)."""

    def planner(events: list[dict], extents: Mapping[str, Extent]) -> dict:
        return {key: _Plan.of(key, start, end, extents, settle_s).segment
                for key, (start, end) in _segments(events, _rate(extents)).items()
                if optic in (None, key[1]) and _exc(key) in extents}

    stream = WelchStream(planner, bw, overlap, window)
    try:
        session = stream_channels(list(paths), _test_point(optic), stream)
    except BaseException:
        stream.close()
        raise
    results = stream.result()
    extents = stream.extents()
    excitations = {k: v for k, v in _segments(session.events, _rate(extents)).items()
                   if optic in (None, k[1])}
    if not excitations or results is None or set(results) != set(excitations):
        return None
    columns, averages = {}, 0
    for key, (start, end) in excitations.items():
        _, freq, h, g2, averages = results[key]
        keys = _Plan.of(key, start, end, extents, settle_s).keys
        columns[key[2]] = {k: (h[i], g2[i]) for i, k in enumerate(keys)}
    tfs = assemble(key[1], freq, columns, averages, key[0])
    tfs.window = window
    tfs.spans = {k[2]: span for k, span in excitations.items()}
    return tfs


def _rate(extents: Mapping[str, Extent]) -> float:
    """The rate the events' stream lengths are counted in (the fastest channel's)."""
    return max((e.rate for e in extents.values()), default=16384.0)


def _exc(key: tuple[str, str, str]) -> str:
    """The EXC channel of (ifo, optic, DOF)."""
    return f"{key[0]}:SUS-{key[1]}_SUS{key[2]}_EXC"


def highpassed(signals: Sequence[NDArray], rate: float, f_hz: float, skip: int
               ) -> list[NDArray[np.float64]]:
    """Each signal through the same 8th-order Butterworth high-pass, less its first `skip`
    samples (where the filter's transient lives).

    A rectangular window leaks the large sub-0.2 Hz seismic motion into every bin, and its
    error barely changes from one short segment to the next, so the coherence cannot see
    it; filtering excitation and response alike leaves their ratio, and the periodic steady
    state, untouched.

    Parameters
    ----------
    signals : sequence of ndarray
        EXC and responses, from the excitation's start.
    rate : float
        Sample rate (Hz).
    f_hz : float
        The high-pass corner (Hz).
    skip : int
        Samples dropped from the start of each.

    Returns
    -------
    list of ndarray
    """
    sos = signal.butter(8, f_hz, btype="highpass", fs=rate, output="sos")
    return [signal.sosfilt(sos, np.asarray(x, dtype=float))[skip:] for x in signals]


def _segments(events: list[dict], rate_hz: float = 16384.0
              ) -> dict[tuple[str, str, str], tuple[float, float]]:
    """The excitation interval of each excited test point.

    A stream lasts its samples, anything else its requested duration, cut short by a
    ``stop``.  Injections that follow each other on one channel without a gap (a long
    waveform streamed in several requests, as the service asks) are one excitation; of
    several separate ones the longest is used.
    """
    starts, ends = {}, {}
    problems = [event_problem(ev) or excitation_problem(ev) for ev in events]
    bad = [p for p in problems if p]
    if bad:
        warnings.warn(f"{len(bad)} event(s) in the recording left out: {bad[0]}",
                      MeasurementWarning, stacklevel=3)
    for ev, problem in zip(events, problems, strict=True):
        if problem:
            continue
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
        m = DOF_CHANNEL.match(channel)
        if not (m and exc_id in ends):
            continue
        chain = runs.setdefault((m["ifo"], m["optic"], m["dof"]), [])
        if chain and abs(start - chain[-1][1]) < 0.5 / rate_hz:
            chain[-1][1] = ends[exc_id]
        else:
            chain.append([start, ends[exc_id]])
    return {k: tuple(max(v, key=lambda r: r[1] - r[0])) for k, v in runs.items()}
