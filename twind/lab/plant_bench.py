"""``twind bench --suite statespace``: twind on state-space optics, measured as KAGRA measures
them: open loop through a TEST point, closed loop through a damping loop's EXC.

For each optic: nulls (the model itself, measured open loop through an intermediate-mass TEST
point and closed loop through its damping loop's EXC) and moved modes (one of the model's
modes the intermediate mass carries, moved by Brauer's update of the matrix,
:func:`~twind.lab.plant_measurement.moved`, then measured both ways). Every case is one
diaggui file made by the time-domain engine and Welch
(:func:`~twind.lab.plant_measurement.measure`) and diagnosed from the file alone. A moved
mode counts as found when a ``mode_frequency`` claim puts it within 2 % of an independent
peak fit of the measured element (:func:`~twind.lab.plant_measurement.peak`); twind's
frequency is also set against the truth, and the peak fit too (a closed loop's peak is the
whole closed loop's, which the other loops move; a peak of a few bins is poorly fitted).
chi2/nu must fall at least twofold where the change acts (the whole band's is printed
beside). Each DOF's closed-loop plant is set beside its open-loop one over the bins coherent
in both.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from twind import progress
from twind.analysis.statespace.diagnose import PlantDiagnosis, diagnose_plant
from twind.analysis.statespace.measurement import PlantSet, read_plant
from twind.analysis.statespace.model import other_loops
from twind.config.statespace import StateSpaceOptic
from twind.lab.plant_measurement import measure, moved, peak

DOFS6 = ("L", "T", "V", "R", "P", "Y")
RATE_HZ = 2048.0
"""The engine's rate in the benchmark (the front end's is 16384 Hz; a ZOH at 2048 Hz delays
by a quarter millisecond, which the fitted delay absorbs, and aliases 1e-3 of the response
at 30 Hz)."""
NOISE = 1e-2
"""Each readback's noise over the excitation (white, per rtHz): coherences of 0.9-0.999
where the intermediate mass answers, as KAGRA's SRM measurement has."""
FOUND_WITHIN = 0.02
"""A moved mode is found when twind puts it within this of the independent peak fit."""


@dataclass
class Case:
    """One diagnosed file: what was hidden and what was found."""

    optic: str
    kind: str  # "null" or "moved"
    drive: str
    closed: bool
    diagnosis: PlantDiagnosis
    seconds: float
    mode: int | None = None
    f_model_hz: float = math.nan
    f_true_hz: float = math.nan
    f_peak_hz: float = math.nan

    @property
    def claimed(self) -> list[str]:
        """The changes claimed."""
        return [c.effect.key() for c in self.diagnosis.chosen]

    def found_hz(self) -> float:
        """The frequency twind gives the moved mode (NaN: no ``mode_frequency`` claim for
        it)."""
        for c in self.diagnosis.chosen:
            if c.effect.family == "mode_frequency" and c.effect.target[0] == self.mode:
                return self.diagnosis.modal.modes[self.mode].f_hz * math.exp(
                    self.diagnosis.final.own(c.effect)["log_f"])
        return math.nan

    @property
    def improvement(self) -> float:
        """chi2/nu of the model over that of the refitted one, over every bin."""
        return self.diagnosis.nominal.chi2_nu / self.diagnosis.final.chi2_nu

    @property
    def local_improvement(self) -> float:
        """The same over the bins the moved mode's claim moves (NaN: no such claim)."""
        for c in self.diagnosis.chosen:
            if c.effect.family == "mode_frequency" and c.effect.target[0] == self.mode \
                    and c.local is not None:
                return c.local[0] / c.local[1]
        return math.nan

    def line(self) -> str:
        """One printed line."""
        d = self.diagnosis
        head = (f"{self.optic:4s} {self.kind:5s} {'closed' if self.closed else 'open':6s} "
                f"{self.drive:10s} {self.seconds:5.1f} s  chi2/nu {d.nominal.chi2_nu:7.3g} -> "
                f"{d.final.chi2_nu:<7.3g}")
        if self.kind == "null":
            return f"{head} claims: {', '.join(self.claimed) or 'none'}"
        got = self.found_hz()
        return (f"{head} mode {self.f_model_hz:.4g} Hz moved to {self.f_true_hz:.4g}; peak "
                f"fit {self.f_peak_hz:.4g}; twind {got:.4g} "
                f"({100 * (got / self.f_peak_hz - 1):+.2g} % of the peak fit, "
                f"{100 * (got / self.f_true_hz - 1):+.2g} % of the truth), chi2/nu "
                f"{self.local_improvement:.3g} times lower where it acts; claims: "
                f"{', '.join(self.claimed) or 'none'}")


@dataclass(frozen=True)
class Agreement:
    """A DOF's closed-loop plant against its open-loop one, over the bins coherent in both:
    as measured, and less what the other loops feed back (as the model makes it,
    :func:`~twind.analysis.statespace.model.other_loops`)."""

    optic: str
    dof: str
    bins: int
    median: float
    """Median of ``|closed / open - 1|``."""
    mean: float
    """Magnitude of the inverse-variance mean of ``closed / open - 1``."""
    sigma: float
    """Its standard error."""
    chi2_nu: float
    """Of ``closed / open`` against 1 (1: the two differ by their noise only)."""
    mean_less_loops: float = math.nan
    chi2_nu_less_loops: float = math.nan

    def line(self) -> str:
        """One printed line."""
        return (f"{self.optic} IM {self.dof}: closed-loop plant against open loop over "
                f"{self.bins} bins coherent in both: mean closed/open - 1 "
                f"{100 * self.mean:.2g} +- {100 * self.sigma:.2g} %, chi2/nu "
                f"{self.chi2_nu:.3g} (less the other loops' feedback: "
                f"{100 * self.mean_less_loops:.2g} %, chi2/nu {self.chi2_nu_less_loops:.3g}); "
                f"median |closed/open - 1| {100 * self.median:.2g} %")


def movable(optic: StateSpaceOptic, dof: str) -> list[tuple[int, float]]:
    """The modes of `optic` its intermediate mass's `dof` carries most (label ``IM <dof>``),
    of Q 5 or more, 0.1-20 Hz, as ``(index, f_hz)`` in the modal form of ``IM_TEST_<dof>``
    to ``IM_DAMP_<dof>_IN1``."""
    modal = optic.modal((f"IM_TEST_{dof}",), (f"IM_DAMP_{dof}_IN1",))
    return [(m.index, m.f_hz) for m in modal.modes
            if m.label == f"IM {dof}" and m.q >= 5 and 0.1 <= m.f_hz <= 20]


def cases(optics: Sequence[StateSpaceOptic], nulls: int, moves: int, workdir: Path,
          seed: int = 0) -> Iterator[Case]:
    """Every case of the benchmark, made, diagnosed and yielded in turn.

    Parameters
    ----------
    optics : sequence of StateSpaceOptic
    nulls : int
        Null files per optic (alternately open and closed loop, DOF by DOF).
    moves : int
        Moved modes per optic, each measured open and closed loop.
    workdir : Path
        Where the diaggui files are written.
    seed : int
    """
    rng = np.random.default_rng(seed)
    for optic in optics:
        for n in range(nulls):
            dof = DOFS6[n // 2 % 6]
            yield _case(optic, "null", dof, n % 2 == 1, workdir, seed + 100 * n, optic.model)
        pool = [(dof, k, f) for dof in DOFS6 for k, f in movable(optic, dof)]
        for n in range(moves):
            dof, k, f = pool[int(rng.integers(len(pool)))]
            factor = float(rng.choice([-1, 1]) * rng.uniform(0.04, 0.15) + 1)
            model, f_true = moved(optic.model, f, factor)
            for closed in (False, True):
                yield _case(optic, "moved", dof, closed, workdir, seed + 1000 + 100 * n, model,
                            mode=k, f_model=f, f_true=f_true)


def _case(optic: StateSpaceOptic, kind: str, dof: str, closed: bool, workdir: Path,
          seed: int, model, mode: int | None = None, f_model: float = math.nan,  # noqa: ANN001
          f_true: float = math.nan) -> Case:
    """One file measured and diagnosed."""
    drive = f"IM_DAMP_{dof}" if closed else f"IM_TEST_{dof}"
    path = workdir / f"{optic.name}_{kind}_{drive}_{seed}.xml"
    if not path.exists():
        measure(optic, drive, path, model=model, seed=seed, noise=NOISE, rate_hz=RATE_HZ,
                closed=None if closed else ())
    plant = read_plant([path], optic)
    t0 = time.perf_counter()
    d = diagnose_plant(plant, optic)
    seconds = time.perf_counter() - t0
    f_peak = math.nan
    if kind == "moved":
        i = plant.readbacks.index(f"IM_DAMP_{dof}_IN1")
        f_peak = peak(plant.frequency_hz, plant.H[:, i, 0], f_true)
    return Case(optic.name, kind, drive, closed, d, seconds, mode, f_model, f_true, f_peak)


def closed_against_open(optic: StateSpaceOptic, dof: str, workdir: Path, seed: int = 0
                        ) -> Agreement:
    """The plant of `dof` from a closed-loop file (all six loops closed) against its open-loop
    file, over the bins coherent in both."""
    plants: list[PlantSet] = []
    for closed in (False, True):
        drive = f"IM_DAMP_{dof}" if closed else f"IM_TEST_{dof}"
        path = workdir / f"{optic.name}_null_{drive}_{seed}.xml"
        if not path.exists():
            measure(optic, drive, path, seed=seed, noise=NOISE, rate_hz=RATE_HZ,
                    closed=None if closed else ())
        plants.append(read_plant([path], optic))
    a, b = plants
    i = a.readbacks.index(f"IM_DAMP_{dof}_IN1")
    both = a.coherent()[:, i, 0] & b.coherent()[:, i, 0]
    if not both.any():
        return Agreement(optic.name, dof, 0, math.nan, math.nan, math.nan, math.nan)
    loops = other_loops(optic, b.drives, b.readbacks, b.frequency_hz, b.resolution_hz)
    loops = np.zeros_like(b.H) if loops is None else loops  # None: no other loop closed
    ha, hb = a.H[both, i, 0], b.H[both, i, 0]
    sa, sb = a.sigma[both, i, 0], b.sigma[both, i, 0]
    median = float(np.median(np.abs(hb / ha - 1)))
    mean, sigma, chi2_nu = _compared(hb, sb, ha, sa)
    less, _, chi2_less = _compared(hb - loops[both, i, 0], sb, ha, sa)
    return Agreement(optic.name, dof, int(both.sum()), median, mean, sigma, chi2_nu, less,
                     chi2_less)


def _compared(closed: NDArray[np.complex128], closed_sigma: NDArray[np.float64],
              open_: NDArray[np.complex128], open_sigma: NDArray[np.float64]
              ) -> tuple[float, float, float]:
    """The magnitude of the inverse-variance mean of ``closed / open - 1``, its standard
    error, and chi2/nu of ``closed / open`` against 1, from each side's standard error."""
    ratio = closed / open_
    sigma = np.abs(ratio) * np.hypot(closed_sigma / np.abs(closed), open_sigma / np.abs(open_))
    w = 1 / sigma**2
    mean = np.sum(w * (ratio - 1)) / np.sum(w)
    return (float(abs(mean)), float(1 / np.sqrt(np.sum(w))),
            float(np.mean(np.abs(ratio - 1) ** 2 / sigma**2) / 2))


def run(optics: Sequence[StateSpaceOptic], nulls: int = 6, moves: int = 4,
        workdir: str | Path | None = None, seed: int = 0) -> list[str]:
    """The benchmark: a line per case as it is done, then the figures.

    Returns
    -------
    list of str
        The summary lines (the per-case lines are printed as they come).
    """
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        done: list[Case] = []
        for case in cases(optics, nulls, moves, work, seed):
            progress.tick()
            print(case.line(), flush=True)
            done.append(case)
        agreement = [closed_against_open(o, dof, work, seed) for o in optics for dof in DOFS6]
    return summary(done, agreement)


def summary(done: Sequence[Case], agreement: Sequence[Agreement]) -> list[str]:
    """The benchmark's figures."""
    null = [c for c in done if c.kind == "null"]
    move = [c for c in done if c.kind == "moved"]
    found = [c for c in move if abs(c.found_hz() / c.f_peak_hz - 1) <= FOUND_WITHIN]
    better = [c for c in found if c.local_improvement >= 2]
    slowest = max((c.seconds for c in done), default=math.nan)
    out = [f"nulls with a change claimed: {sum(bool(c.claimed) for c in null)}/{len(null)}",
           f"moved modes found within {100 * FOUND_WITHIN:g} % of the peak fit: "
           f"{len(found)}/{len(move)}; of those, chi2/nu at least halved where the change "
           f"acts: {len(better)}/{len(found)} (over every bin: "
           f"{sum(c.improvement >= 2 for c in found)}/{len(found)})",
           "moved modes, twind against the peak fit (%): " + ", ".join(
               f"{100 * (c.found_hz() / c.f_peak_hz - 1):+.2g}" for c in move),
           "moved modes, twind against the truth (%): " + ", ".join(
               f"{100 * (c.found_hz() / c.f_true_hz - 1):+.2g}" for c in move),
           "moved modes, the peak fit against the truth (%): " + ", ".join(
               f"{100 * (c.f_peak_hz / c.f_true_hz - 1):+.2g}" for c in move),
           f"diagnosis time: median {np.median([c.seconds for c in done]):.1f} s, "
           f"slowest {slowest:.1f} s ({max(c.diagnosis.plant.frequency_hz.size for c in done)}"
           " bins a file)"]
    return out + [a.line() for a in agreement]
