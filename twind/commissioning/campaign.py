"""``twind campaign``: design -> inject -> record -> TF -> fit -> redesign, until the fitted
parameters reach a target uncertainty, pushing each round's fit into a running twin.

Each round designs D-optimal multisines (:mod:`twind.analysis.design.information`) at the current
best parameters, measures every excited DOF for ``averages`` periods (after a settling
period), estimates the TFs with a rectangular window (a periodic excitation has no leakage),
and fits all rounds' data jointly.  Twin time counts the DOFs one after the other, as on a
real optic.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np
from matplotlib.figure import Figure

from twind import DOFS, progress
from twind.analysis.estimation.tf import from_session
from twind.analysis.estimation.tfset import TFSet
from twind.analysis.identification.fit import fit
from twind.analysis.identification.params import FIT_PARAMS, with_params
from twind.analysis.identification.result import FitResult
from twind.bus.keys import data_key
from twind.bus.session import zenoh_config
from twind.channels import TEST_POINTS, dof_channel
from twind.client import TwinClient
from twind.config import OpticConfig
from twind.errors import TwindError
from twind.analysis.design.information import InformationDesign, design_information
from twind.commissioning.measurement import SETTLE_S, measure_tfs
from twind.recording.recorder import Recorder

MIN_AVERAGES = 4
"""Fewer periods leave the coherence estimate (and the errors made from it) meaningless."""
STREAM_CHUNK = 262144
"""Samples per stream request (16 s at 16384 Hz, ~5 MB of JSON)."""
STREAM_LEAD_S = 1.0
"""Wall seconds allowed per stream request (and one more) before the first one starts."""


class Twin(Protocol):
    """Where a campaign measures, and where it pushes what it learnt."""

    def measure(self, design: InformationDesign, averages: int) -> TFSet:
        """TFs of the design's excitations, ``averages`` periods of each DOF.

        Parameters
        ----------
        design : InformationDesign
            The multisine of each excited DOF.
        averages : int
            Periods measured per DOF, after :data:`~twind.commissioning.measurement.SETTLE_S`.

        Returns
        -------
        TFSet
        """

    def push(self, values: dict[str, float]) -> None:
        """Give a twin the fitted parameters (nothing, when there is none to update)."""


class LocalTwin:
    """An in-process twin of the "real" optic, no bus (fast; for benchmarks and tests)."""

    def __init__(self, real: OpticConfig, seed: int = 0) -> None:
        self.real, self.seed, self.rounds = real, seed, 0

    def measure(self, design: InformationDesign, averages: int) -> TFSet:
        """TFs of the design's multisines measured on the "real" optic (rectangular window,
        high-passed below the lowest tone), each round with fresh noise.

        Parameters
        ----------
        design : InformationDesign
            The multisine of each excited DOF.
        averages : int
            Periods measured per DOF, after :data:`~twind.commissioning.measurement.SETTLE_S`.

        Returns
        -------
        TFSet
        """
        rate = self.real.sus.sample_rate_hz
        n = int(round((SETTLE_S + averages * design.period_s) * rate))
        exc = {d: design.waveform(d, n, rate) for d in design.tones}
        self.rounds += 1
        return measure_tfs(self.real, list(design.tones), bw=1 / design.period_s,
                           averages=averages, overlap=0.0, excitation=exc, window="boxcar",
                           seed=self.seed + self.rounds, highpass_hz=_highpass(design))

    def push(self, values: dict[str, float]) -> None:
        pass


class BusTwin:
    """A running twin (``twind serve``): each DOF's multisine is injected as a stream, the
    optic's test points are recorded to MCAP, and the TFs estimated from the recording."""

    def __init__(self, connect: Sequence[str], optic: str, ifo: str = "C1",
                 update: Sequence[str] | None = None, workdir: str | Path | None = None
                 ) -> None:

        self.connect, self.optic, self.ifo = list(connect), optic, ifo
        self.client = TwinClient(self.connect, ifo=ifo)
        self.updated = TwinClient(list(update), ifo=ifo) if update else None
        self.workdir = Path(workdir or tempfile.mkdtemp(prefix="twind-campaign-"))
        self.rounds = 0

    def measure(self, design: InformationDesign, averages: int) -> TFSet:
        """Inject the design's multisines into the optic's EXCs one DOF after another,
        record every DOF's EXC, IN1, IN2 and OUT to an MCAP file in :attr:`workdir`, and
        estimate the TFs from it (rectangular window, the settling skipped, high-passed
        below the lowest tone).

        Parameters
        ----------
        design : InformationDesign
            The multisine of each excited DOF.
        averages : int
            Periods injected per DOF, after :data:`~twind.commissioning.measurement.SETTLE_S`.

        Returns
        -------
        TFSet
        """
        rate = float(self.client.params(self.optic).params["sample_rate_hz"])
        self.rounds += 1
        path = self.workdir / f"{self.optic}-round{self.rounds}.mcap"
        keys = [data_key(dof_channel(self.ifo, self.optic, d, p))
                for d in DOFS for p in TEST_POINTS]
        n = int(round((SETTLE_S + averages * design.period_s) * rate))
        with Recorder(zenoh_config(connect=self.connect, mode="client"), path, keys,
                      ifo=self.ifo, log=lambda line: None):
            for dof in design.tones:
                self._stream(dof_channel(self.ifo, self.optic, dof, "EXC"),
                             design.waveform(dof, n, rate), rate)
            time.sleep(0.5)  # the last blocks on their way to the recorder
        return from_session([path], bw=1 / design.period_s, overlap=0.0, optic=self.optic,
                            window="boxcar", settle_s=SETTLE_S, highpass_hz=_highpass(design))

    def _stream(self, channel: str, samples: np.ndarray, rate: float) -> None:
        """Inject `samples` as back-to-back streams (a request holds at most ~8 MB), then
        wait for the last to end; ``twind tf`` joins them into one excitation."""
        status = self.client.status()
        chunks = -(-samples.size // STREAM_CHUNK)
        start = status.gps + status.speed * STREAM_LEAD_S * (1 + chunks)
        ids = []
        for a in range(0, samples.size, STREAM_CHUNK):
            ids.append(self.client.inject(channel, "stream", samples=samples[a:a + STREAM_CHUNK],
                                          start_gps=start + a / rate))
        while any(e.id in ids for e in self.client.status().excitations):
            time.sleep(0.2)

    def push(self, values: dict[str, float]) -> None:
        if self.updated is None:
            return
        self.updated.params(self.optic, **values)


def _highpass(design: InformationDesign) -> float:
    """Half the lowest tone: below the design, above most of the seismic motion."""
    return 0.5 * min(float(t.min()) for t in design.tones.values())


@dataclass
class Round:
    """One round: its design, the joint fit after it, the twin time spent so far."""

    index: int
    twin_s: float
    design: InformationDesign
    fit: FitResult
    relative_sigma: dict[str, float] = field(init=False)

    def __post_init__(self) -> None:
        self.relative_sigma = {n: float(s / v) for n, v, s in
                               zip(self.fit.names, self.fit.values, self.fit.sigma, strict=True)
                               if not math.isnan(s)}

    @property
    def worst(self) -> tuple[str, float]:
        """The identifiable parameter known worst, and its relative sigma."""
        name = max(self.relative_sigma, key=self.relative_sigma.get)
        return name, self.relative_sigma[name]


def run_campaign(nominal: OpticConfig, twin: Twin, dofs: Sequence[str] = ("POS", "PIT", "YAW"),
                 band: tuple[float, float] = (0.1, 10.0), rms: float = 10.0,
                 period_s: float = 20.0, averages: int = 5, params: Sequence[str] = FIT_PARAMS,
                 target: float = 0.01, max_rounds: int = 8) -> list[Round]:
    """Measure and fit until every identifiable parameter is known to `target` (relative).

    Parameters
    ----------
    nominal : OpticConfig
        The model the campaign starts from.
    twin : Twin
        Where to measure (:class:`LocalTwin`, :class:`BusTwin`) and push fits.
    dofs, band, rms, period_s, averages
        Excited DOFs, design band (Hz), RMS per DOF, multisine period (s) and periods
        averaged per round.
    params : sequence of str
        Parameters to identify.
    target : float
        Relative one-sigma uncertainty to reach.
    max_rounds : int

    Returns
    -------
    list of Round
    """
    if averages < MIN_AVERAGES:
        msg = (f"{averages} averages per round: at least {MIN_AVERAGES} are needed for "
               "coherence-based errors worth fitting with")
        raise TwindError(msg)
    current, measured, rounds, twin_s = nominal, [], [], 0.0
    for k in range(1, max_rounds + 1):
        design = design_information(current, dofs, band, rms, averages * period_s, period_s,
                                    params)
        _progress(k, "measuring", twin_s, rounds)
        measured.append(tones_only(twin.measure(design, averages), design))
        twin_s += len(dofs) * (SETTLE_S + averages * period_s)
        _progress(k, "fitting", twin_s, rounds)
        result = fit(measured, current, params)
        values = result.identified()
        current = replace(current, sus=with_params(current.sus, values))
        twin.push(values)
        rounds.append(Round(k, twin_s, design, result))
        _progress(k, "done", twin_s, rounds)
        if rounds[-1].worst[1] <= target:
            break
    return rounds


def tones_only(tfs: TFSet, design: InformationDesign) -> TFSet:
    """`tfs` with every bin but its column's tones marked incoherent: between the tones of a
    periodic excitation there is no excitation, and the ratio there is noise over zero.

    Parameters
    ----------
    tfs : TFSet
        A measurement of `design`, its bins from 0 Hz at the tones' spacing.
    design : InformationDesign
        The multisines, with the tones of each excited DOF.

    Returns
    -------
    TFSet
        A copy, its coherences zero off the tones (every test point).
    """
    coherence = {p: c.copy() for p, c in tfs.coherence.items()}
    for j, dof in enumerate(tfs.excited):
        k = np.rint(design.tones[dof] / (tfs.frequency_hz[1] - tfs.frequency_hz[0])).astype(int)
        off = np.ones(tfs.frequency_hz.size, dtype=bool)
        off[k[k < off.size]] = False
        for c in coherence.values():
            c[off, :, j] = 0.0
    return replace(tfs, coherence=coherence)


def _progress(k: int, what: str, twin_s: float, rounds: list[Round]) -> None:
    """The round, what it is doing, the twin time spent and the worst parameter so far, on
    the progress bar."""
    worst = f", worst {rounds[-1].worst[0]} {100 * rounds[-1].worst[1]:.3g} %" if rounds else ""
    progress.note(f"round {k} {what}, twin {twin_s / 60:.1f} min{worst}")


def plot_rounds(rounds: list[Round], target: float, path: str | Path) -> Path:
    """Relative uncertainty of each parameter after each round, against twin time.

    Parameters
    ----------
    rounds : list of Round
        The campaign's rounds, in order.
    target : float
        The relative sigma aimed at, drawn as a line.
    path : str or Path
        The image to write (its suffix picks the format).

    Returns
    -------
    Path
    """
    fig = Figure(figsize=(7, 4.5))
    ax = fig.subplots()
    names = sorted({n for r in rounds for n in r.relative_sigma})
    t = [r.twin_s / 60 for r in rounds]
    for n in names:
        ax.semilogy(t, [100 * r.relative_sigma.get(n, np.nan) for r in rounds], "o-", label=n)
    ax.axhline(100 * target, color="k", ls="--", lw=0.8, label="target")
    ax.set_xlabel("twin time [min]")
    ax.set_ylabel("relative sigma [%]")
    ax.set_title(f"{rounds[0].fit.optic}: identification campaign, {len(rounds)} rounds")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    return path
