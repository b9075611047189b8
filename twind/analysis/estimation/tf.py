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

import warnings
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import dttxml
import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind import DOFS
from twind.channels import DOF_CHANNEL
from twind.analysis.estimation.demodulation import AVERAGES, DemodulationError, demodulate
from twind.analysis.estimation.excitations import (SHORTEST_S, Stretch, at_one_rate, every,
                                                   longest, with_exc)
from twind.analysis.estimation.lpm import LPMEstimate, lpm_tfs
from twind.analysis.estimation.tfset import (
    ESTIMATORS,
    POINTS,
    Kernel,
    ReadOptions,
    TFError,
    TFSet,
    register_reader,
)
from twind.analysis.estimation.welch import Extent, Segment, WelchStream, welch_tfs
from twind.errors import MeasurementWarning, TwindError
from twind.recording.fastread import event_count, read_channels, stream_channels
from twind.recording.frames import is_frames, read_frames, same_channels
from twind.recording.session import Channel
from twind.recording.validate import event_problem, excitation_problem

__all__ = ["assemble", "from_diaggui", "from_session", "highpassed", "merged", "with_lpm",
           "xml_transfer"]



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
    return assemble(optic, freq, columns, averages, ifo, spans=spans)


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


def assemble(optic: str, freq: NDArray, columns: dict, averages: int, ifo: str = "C1",
             **fields: object) -> TFSet:
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
    **fields
        The set's other fields (``window``, ``spans``, ``exc_psd``...): it is built whole.

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
                 ifo=ifo, **fields)


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
    tfs = assemble(key[1], freq, columns, averages, key[0], window=window, found=notes,
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
        The assembled LPM estimates.
    estimates : mapping of str to LPMEstimate
        The estimate of each excited DOF.

    Returns
    -------
    TFSet
        A new set.
    """
    first = estimates[tfs.excited[0]]
    kernel = Kernel(first.offsets_hz,
                    np.stack([estimates[d].weights for d in tfs.excited], axis=-1))
    rho = [estimates[d].correlation for d in tfs.excited]
    correlated = all(r is not None and r.shape[1] == len(tfs.responses) for r in rho)
    return replace(tfs, window="lpm", kernel=kernel,
                   in1_correlation=np.stack(rho, axis=-1) if correlated else None)


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
    spans = {k[2]: (min(s.start for s in v), max(s.end for s in v)) for k, v in sines.items()}
    return assemble(next(iter(sines))[1], freq, columns, AVERAGES, next(iter(sines))[0],
                    window="sine", found=notes, spans=spans)


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
    return assemble(key[1], freq, columns, averages, key[0], window=window,
                    spans={k[2]: span for k, span in excitations.items()})


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


def _diaggui(paths: list[Path], options: ReadOptions) -> TFSet:
    if options.estimator != "welch":  # not a TFError: the files may well be TFs
        msg = (f"--estimator {options.estimator} needs the time series: diaggui XML holds "
               "diaggui's Welch estimates only")
        raise TwindError(msg)
    return from_diaggui(paths)


def _time_series(paths: list[Path], options: ReadOptions) -> TFSet:
    return from_session(paths, bw=options.bw, overlap=options.overlap, optic=options.optic,
                        estimator=options.estimator, max_hz=options.max_hz,
                        mapping=options.mapping, exc_times=options.exc_times)


register_reader("diaggui", "diaggui .xml", lambda ps: all(p.suffix.lower() == ".xml" for p in ps),
                _diaggui)
register_reader("mcap", ".mcap", lambda ps: all(p.suffix.lower() == ".mcap" for p in ps),
                _time_series)
register_reader("frames", "HDF5 (.h5, .hdf5) or GWF (.gwf)", lambda ps: all(map(is_frames, ps)),
                _time_series)

