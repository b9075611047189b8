"""``twind demo``: a "real" optic with an effect concealed in its plant beside the nominal
one, both excited and recorded on the twin's engine, then each diagnosed from its recording
alone, with the reports a commissioner reads."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from twind.analysis.diagnose import diagnose
from twind.analysis.estimation.tf import from_session
from twind.analysis.identification.inmatrix import recorded_input_matrix
from twind.commissioning.concealed import (
    AVERAGES,
    RMS,
    ROUTE_BW,
    conceal,
    drifted,
    reference_data,
)
from twind.commissioning.measurement import SETTLE_S, record_measurement
from twind.config import OpticConfig
from twind.viz.report import write_report


def run_demo(cfg: OpticConfig, out: str | Path, effect: str = "actuator_pole", seed: int = 3,
             say: Callable[[str], None] = print) -> tuple:
    """A "real" optic (drifted, `effect` concealed in its plant) and the nominal one, both
    excited alike on the twin's engine and recorded as twin sessions (MCAP), then each
    diagnosed from its recording alone; reports (Bode matrices before and after, HTML,
    Rerun) under `out`/real and `out`/nominal.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    out : str or Path
        Directory of the recordings and reports (made if missing).
    effect : str
        One of :data:`~twind.commissioning.hidden.MADE` with no shape (not ``resonance``
        or ``channel_filter``).
    seed : int
        Seed of the drift, the effect's direction and the measurements.
    say : callable
        Takes each line of the report.

    Returns
    -------
    (Diagnosis, Diagnosis)
        The real optic's and the nominal one's.
    """

    out = Path(out)
    rng = np.random.default_rng(seed)
    real = drifted(cfg, rng)
    direction = rng.standard_normal(4)
    plant, truth, largest, present = conceal(real, effect, reference_data(cfg, seed,
                                                                         route="mcap"),
                                             direction / 2)
    say(f"real {cfg.name}: drifted, with {effect} {truth} hidden in its plant "
        f"(largest bin {largest:.1f} sigma, {present:.0f} in chi^2 units over all bins)")
    results = []
    for name, optic, run in (("real", real, plant), ("nominal", cfg, None)):
        out.mkdir(parents=True, exist_ok=True)
        path = out / f"{name}.mcap"
        say(f"{name}: exciting POS, PIT, YAW in turn and recording {path} ...")
        record_measurement(optic, path, bw=ROUTE_BW["mcap"], averages=AVERAGES, rms=RMS,
                           seed=seed + 1, plant=run)
        tfs = from_session([path], bw=ROUTE_BW["mcap"], settle_s=SETTLE_S)
        d = diagnose(tfs, cfg, input_matrix=recorded_input_matrix([path], cfg))
        write_report(d, d.curves(tfs, d.read_through(cfg)), tfs, out / name, [path])
        say(f"{name}: " + "\n  ".join(d.lines()))
        say(f"{name}: report in {out / name}/index.html")
        results.append(d)
    return tuple(results)
