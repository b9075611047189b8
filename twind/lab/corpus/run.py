"""The corpus measured and diagnosed along a route (diaggui XML or MCAP)."""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from twind.analysis.diagnose import (
    diagnose,
    evidence,
    explained,
    f_profile,
)
from twind.analysis.estimation.diaggui import write_measurement_set
from twind.analysis.estimation.tf import from_diaggui, from_session
from twind.analysis.identification.params import FitError
from twind.commissioning.concealed import (
    AVERAGES,
    EXCITED,
    RMS,
    ROUTE_BW,
    STOP_HZ,
    reference_data,
)
from twind.commissioning.measurement import SETTLE_S, measure_tfs, record_measurement
from twind.config import OpticConfig
from twind.lab.corpus.cases import EFFECTS, Case, make_cases
from twind.lab.corpus.scoring import Score, _line, body_start, score, summary


def measure(case: Case, route: str, workdir: Path, seed: int,  # noqa: ANN201 - TFSet
            excited: Sequence[str] = EXCITED, bw: float | None = None,
            averages: int = AVERAGES, rms: float = RMS):
    """The case's measurement as users have it: ``"xml"`` (a diaggui set written from the
    twin's TFs, up to :data:`~twind.commissioning.concealed.STOP_HZ`) or ``"mcap"`` (a
    session recorded from the twin's engine), each DOF of `excited` in turn, at resolution
    `bw` (default the route's), with `averages` and an excitation of `rms`.

    Parameters
    ----------
    case : Case
        The optic measured (its drifted parameters and its plant).
    route : str
        ``"xml"`` or ``"mcap"``.
    workdir : Path
        Where the files go (a new directory in it).
    seed : int
        Seed of the twin's noise and the excitation.
    excited : sequence of str
        DOFs excited in turn.
    bw : float, optional
        Resolution (Hz); default the route's (:data:`~twind.commissioning.concealed.ROUTE_BW`).
    averages : int
    rms : float
        RMS of the white EXC.

    Returns
    -------
    TFSet

    Raises
    ------
    ValueError
        If `route` is neither.
    """

    if route not in ROUTE_BW:
        msg = f"unknown route {route!r}: xml or mcap"
        raise ValueError(msg)
    bw = bw or ROUTE_BW[route]
    here = Path(tempfile.mkdtemp(dir=workdir))
    if route == "xml":
        tfs = measure_tfs(case.real, excited, bw=bw, averages=averages, rms=rms, seed=seed,
                          plant=case.plant)
        return from_diaggui(write_measurement_set(tfs, here, stop_hz=STOP_HZ))
    path = record_measurement(case.real, here / "session.mcap", excited, bw=bw,
                              averages=averages, rms=rms, seed=seed, plant=case.plant)
    try:
        return from_session([path], bw=bw, settle_s=SETTLE_S)
    finally:
        path.unlink()


def run_corpus(cfg: OpticConfig, route: str = "xml", per_effect: int = 3, nulls: int = 3,
               seed: int = 11, effects: Sequence[str] = EFFECTS,
               say: Callable[[str], None] = print, excited: Sequence[str] = EXCITED,
               bw: float | None = None, averages: int = AVERAGES, rms: float = RMS
               ) -> list[Score]:
    """Build the corpus, measure (at resolution `bw`, default
    :data:`~twind.commissioning.concealed.ROUTE_BW`'s, with `averages` and excitation `rms`)
    and diagnose every case (each DOF of `excited` in turn), print a line each and the
    rates, each kind apart.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic (every diagnosis's model).
    route : str
        ``"xml"`` (diaggui sets) or ``"mcap"`` (twin sessions).
    per_effect : int
        Cases of each kind of `effects`.
    nulls : int
        Cases with no effect.
    seed : int
        Seed of the corpus and, offset by case, of each measurement.
    effects : sequence of str
        Kinds of effect hidden (:func:`make_cases`).
    say : callable
        Takes each line of the report.
    excited : sequence of str
        DOFs excited in turn.
    bw : float, optional
        Resolution (Hz); default the route's.
    averages : int
    rms : float
        RMS of the white EXC.

    Returns
    -------
    list of Score
    """

    bw = bw or ROUTE_BW[route]
    say(f"resolution {bw:g} Hz, {averages} averages, excitation RMS {rms:g}")
    cases = make_cases(cfg, reference_data(cfg, seed, excited, route, bw, averages, rms),
                       per_effect, nulls, seed, effects)
    scores = []
    with tempfile.TemporaryDirectory(prefix="twind-corpus-") as tmp:
        for k, case in enumerate(cases):
            t0 = time.perf_counter()
            tfs = measure(case, route, Path(tmp), seed + 100 + k, excited, bw, averages, rms)
            t1 = time.perf_counter()
            try:
                d = diagnose(tfs, cfg)
            except FitError as err:  # a failure of the tool, scored as a miss
                say(f"{case.name:18s} diagnose failed: {err}")
                d = None
            t2 = time.perf_counter()
            s = score(case, d, t2 - t0, t2 - t1)
            if d is not None and case.effect == "resonance":
                start = body_start(case.truth)
                s.truth_p, s.truth_lr = evidence(tfs, cfg, d, "resonance", start)
                found = next(c for c in d.first_step if c.effect == "resonance")
                s.truth_margin = s.truth_lr - found.lr
                s.f_allowed = f_profile(tfs, cfg, d, start)
                s.final_lr = explained(tfs, d)
            scores.append(s)
            say(_line(s))
    for line in summary(scores):
        say(line)
    return scores
