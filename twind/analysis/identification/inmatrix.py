"""The input matrix, measured: each DOF's IN1 against the OSEM readings the front end
combines into it, before anything is read as suspension physics.

A DOF's IN1 is its row of the input matrix times the five OSEM readings (``SEN_OUT``),
sample by sample; where a recording holds both, a least-squares fit of IN1 on the readings
gives the row the front end used, whatever moved the optic (an excitation, the ground, the
sensors' own noise, which reaches every direction). A row that differs from the
configured one (a sign typed wrong, a row left from a diagonalisation, OSEMs swapped)
changes every closed-loop response; read through the configured row, it looks like a
misfit of the suspension. Here it is named and the plant is read through the measured
matrix.

The fit is exact up to the recorded samples' rounding, so an element is called different
when it differs by more than :data:`TOLERANCE` of its row's largest element (what a
matrix written to three or four digits may carry) and by more than :data:`N_SIGMA` of its
standard error. The output matrix needs the coil drives' test points, which the twin
does not record. The method: docs/diagnose.md, "The input matrix".
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from twind import DOFS, OSEMS
from twind.channels import DOF_CHANNEL, OSEM_CHANNEL, dof_channel, osem_channel
from twind.config import OpticConfig
from twind.recording.fastread import stream_channels
from twind.recording.frames import is_frames, read_frames
from twind.recording.session import RecordingError

SPAN_S = 64.0
"""Seconds of the recording fitted: from where every channel has data."""
TOLERANCE = 1e-3
"""A difference smaller than this fraction of its row's largest element is not called."""
N_SIGMA = 5.0
"""A difference within this many standard errors is not called."""
EXACT = 1e-3
"""A fit whose residual RMS is a larger fraction of IN1's says IN1 is not the OSEM
readings through a fixed matrix (a filter between them, a different rate): not checked."""


@dataclass(frozen=True)
class InputMatrixCheck:
    """The input matrix the recorded IN1 and OSEM readings imply, against the configured.

    Attributes
    ----------
    configured : ndarray, shape (4, 5)
        DOF (um, urad) per OSEM um, rows POS, PIT, YAW, SIDE; columns UL, UR, LL, LR, SIDE.
    measured, sigma : ndarray, shape (4, 5), or None
        The fitted matrix and its standard errors; None where not checked.
    residual : ndarray, shape (4,), or None
        Each row's fit residual RMS over IN1's RMS.
    seconds : float
        The span fitted.
    why : str
        Why it was not checked ("" when it was).
    """

    configured: NDArray[np.float64]
    measured: NDArray[np.float64] | None = None
    sigma: NDArray[np.float64] | None = None
    residual: NDArray[np.float64] | None = None
    seconds: float = 0.0
    why: str = ""

    @property
    def checked(self) -> bool:
        """Whether the recording held what the check needs."""
        return self.measured is not None

    @property
    def differs(self) -> NDArray[np.bool_]:
        """Per element, whether it differs from the configured one (all False unchecked)."""
        if self.measured is None:
            return np.zeros(self.configured.shape, dtype=bool)
        d = np.abs(self.measured - self.configured)
        scale = np.abs(self.configured).max(axis=1, keepdims=True)
        return (d > TOLERANCE * scale) & (d > N_SIGMA * self.sigma)

    @property
    def rows(self) -> list[str]:
        """The DOFs whose rows differ."""
        return [d for d, row in zip(DOFS, self.differs, strict=True) if row.any()]

    @property
    def same(self) -> bool:
        """Checked and as configured, or not checked."""
        return not self.rows

    def config(self, cfg: OpticConfig) -> OpticConfig:
        """`cfg` with the measured rows where they differ (`cfg` itself where none do)."""
        if self.same:
            return cfg
        rows = [self.measured[i] if d in self.rows else self.configured[i]
                for i, d in enumerate(DOFS)]
        return replace(cfg, input_matrix=tuple(tuple(float(x) for x in r) for r in rows))

    def lines(self) -> list[str]:
        """What a commissioner reads: as configured, the rows that differ, or why not
        checked."""
        if not self.checked:
            return [f"input matrix: not checked ({self.why})"]
        if self.same:
            return [f"input matrix: as configured (IN1 against the OSEM readings, "
                    f"{self.seconds:.0f} s, within {TOLERANCE:g} of each row's largest)"]
        out = []
        for d in self.rows:
            i = DOFS.index(d)
            which = ", ".join(o for o, x in zip(OSEMS, self.differs[i], strict=True) if x)
            out.append(f"input matrix: {d}'s row differs from the configuration at {which}; "
                       "the plant is read through the measured row")
            out.append(f"  measured   {_row(self.measured[i])}")
            out.append(f"  configured {_row(self.configured[i])}")
        return out

    def to_json(self) -> dict[str, Any]:
        """The check's numbers: ``checked``, ``differs`` (DOFs), the matrices, ``why``."""
        def listed(a: NDArray | None) -> list | None:
            return None if a is None else a.tolist()

        return {"checked": self.checked, "differs": self.rows, "columns": list(OSEMS),
                "rows": list(DOFS), "configured": self.configured.tolist(),
                "measured": listed(self.measured), "sigma": listed(self.sigma),
                "residual": listed(self.residual), "seconds": self.seconds, "why": self.why}


def _row(r: NDArray[np.float64]) -> str:
    return " ".join(f"{o} {x:+9.4g}" for o, x in zip(OSEMS, r, strict=True))


def check_input_matrix(in1: NDArray[np.float64], sen: NDArray[np.float64],
                       cfg: OpticConfig, rate_hz: float) -> InputMatrixCheck:
    """Fit each DOF's IN1 on the OSEM readings and compare with `cfg`'s input matrix.

    Parameters
    ----------
    in1 : ndarray, shape (4, n)
        POS, PIT, YAW, SIDE IN1 (um, urad).
    sen : ndarray, shape (5, n)
        UL, UR, LL, LR, SIDE readings (um), the same samples.
    cfg : OpticConfig
    rate_hz : float
        Their sample rate.

    Returns
    -------
    InputMatrixCheck
    """
    configured = cfg.cds_input_matrix()
    x = sen.T
    measured, _, rank, _ = np.linalg.lstsq(x, in1.T, rcond=None)
    if rank < x.shape[1]:
        return InputMatrixCheck(configured, why="the OSEM readings do not span five directions")
    fitted = in1.T - x @ measured
    dof = max(x.shape[0] - x.shape[1], 1)
    s2 = (fitted**2).sum(axis=0) / dof
    unscaled = np.diag(np.linalg.inv(x.T @ x))
    sigma = np.sqrt(np.outer(s2, unscaled))
    scale = np.sqrt(np.mean(in1**2, axis=1))
    residual = np.sqrt(np.mean(fitted**2, axis=0)) / np.where(scale > 0, scale, 1.0)
    seconds = x.shape[0] / rate_hz
    if np.any(residual > EXACT):
        worst = DOFS[int(np.argmax(residual))]
        why = (f"{worst} IN1 is not a fixed combination of the OSEM readings: the fit "
               f"leaves {residual.max():.1%} of it")
        return InputMatrixCheck(configured, residual=residual, seconds=seconds, why=why)
    return InputMatrixCheck(configured, measured.T, sigma, residual, seconds)


def recorded_input_matrix(paths: Sequence[str | Path], cfg: OpticConfig,
                          mapping: Mapping[str, str] | None = None) -> InputMatrixCheck:
    """:func:`check_input_matrix` on the first :data:`SPAN_S` seconds of a recording that
    holds `cfg`'s optic's IN1 and OSEM readings.

    Parameters
    ----------
    paths : sequence of path
        An MCAP session's files, or HDF5 files or GWF frames.
    cfg : OpticConfig
    mapping : mapping of str to str, optional
        HDF5 and GWF: recorded names to the twin's (``--map``).

    Returns
    -------
    InputMatrixCheck
        Not checked (with why) when a channel is missing, the rates differ, the span has
        too few samples, or the files cannot be read (as the transfer functions' reading
        will then say).
    """
    configured = cfg.cds_input_matrix()
    wanted = _wanted(cfg.name)
    try:
        if any(is_frames(p) for p in paths):  # the first file: its span is enough
            channels = {n: (c.t0, c.rate, c.samples)
                        for n, c in read_frames(paths[:1], wanted, mapping).channels.items()}
        else:
            span = _FirstSpan(len(DOFS) + len(OSEMS))
            try:
                stream_channels(list(paths), wanted, span)
            except _Enough:  # the rest of the recording is not read
                pass
            channels = span.channels()
        in1, sen, rate = _aligned(channels, cfg.name)
    except RecordingError as err:
        return InputMatrixCheck(configured, why=str(err))
    return check_input_matrix(in1, sen, cfg, rate)


def _wanted(optic: str):  # noqa: ANN202 - Callable[[str], bool]
    def wanted(name: str) -> bool:
        m = DOF_CHANNEL.match(name)
        if m:
            return m["optic"] == optic and m["point"] == "IN1"
        m = OSEM_CHANNEL.match(name)
        return bool(m) and m["optic"] == optic

    return wanted


def _aligned(channels: Mapping[str, tuple[float, float, NDArray]], optic: str
             ) -> tuple[NDArray, NDArray, float]:
    """IN1 (4, n) and the OSEM readings (5, n) over the span every channel covers."""
    ifos = {n.split(":", 1)[0] for n in channels}
    if len(ifos) != 1:
        msg = "no OSEM readings recorded" if not ifos else f"channels of {sorted(ifos)}"
        raise RecordingError(msg)
    ifo = ifos.pop()
    names = ([dof_channel(ifo, optic, d, "IN1") for d in DOFS]
             + [osem_channel(ifo, optic, o) for o in OSEMS])
    missing = [n for n in names if n not in channels]
    if missing:
        msg = f"{', '.join(missing)} not recorded"
        raise RecordingError(msg)
    rates = {channels[n][1] for n in names}
    if len(rates) != 1:
        msg = f"IN1 and the OSEM readings recorded at different rates ({sorted(rates)} Hz)"
        raise RecordingError(msg)
    rate = rates.pop()
    start = max(channels[c][0] for c in names)
    stop = min(channels[c][0] + len(channels[c][2]) / rate for c in names)
    n = max(int(round((stop - start) * rate)), 0)
    data = np.array([channels[c][2][skip:skip + n] for c in names
                     for skip in [int(round((start - channels[c][0]) * rate))]])
    data = data[:, np.all(np.isfinite(data), axis=0)]
    if data.shape[1] < 2 * len(names):
        msg = "too few samples where IN1 and every OSEM reading were recorded"
        raise RecordingError(msg)
    return data[:4], data[4:], rate


class _Enough(Exception):  # noqa: N818 - a signal, not an error
    """Raised by :class:`_FirstSpan` to end the reading once it holds what it needs."""


class _FirstSpan:
    """A :class:`~twind.recording.fastread.SampleSink` keeping the first :data:`SPAN_S`
    seconds of each channel, up to its first lost block; once `wanted` channels have theirs
    it ends the reading (:class:`_Enough`)."""

    def __init__(self, wanted: int) -> None:
        self._wanted = wanted
        self._parts: dict[str, list[NDArray]] = {}
        self._start: dict[str, tuple[float, float]] = {}
        self._next: dict[str, int] = {}
        self._done: set[str] = set()

    def samples(self, name: str, sequence: NDArray[np.int64], n_samples: NDArray[np.int64],
                gps: NDArray[np.float64], rate: NDArray[np.float64], x: NDArray[np.float64]
                ) -> None:
        """Blocks of one channel (see :class:`~twind.recording.fastread.SampleSink`)."""
        if name in self._done:
            return
        if name not in self._start:
            self._start[name], self._next[name], self._parts[name] = (
                (float(gps[0]), float(rate[0])), int(sequence[0]), [])
        t0, r = self._start[name]
        lost = np.flatnonzero((sequence != self._next[name] + np.arange(len(sequence)))
                              | (rate != r))
        keep = int(n_samples[: lost[0]].sum()) if lost.size else len(x)
        self._parts[name].append(x[:keep])
        self._next[name] += len(sequence)
        if lost.size or sum(len(p) for p in self._parts[name]) >= SPAN_S * r:
            self._done.add(name)
            if len(self._done) >= self._wanted:
                raise _Enough

    def event(self, event: dict[str, Any]) -> None:
        """Injection events are not needed."""

    def channels(self) -> dict[str, tuple[float, float, NDArray[np.float64]]]:
        """``(t0, rate, samples)`` by channel."""
        return {n: (*self._start[n], np.concatenate(p)) for n, p in self._parts.items()}
