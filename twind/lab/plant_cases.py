"""A bench of realistic measurements of KAGRA's suspensions, made from their published models,
and the diagnosis scored against their truth.

A real suspension moves several modes at once, in shapes of its own, and is measured behind
electronics no model has. A case here is one such suspension and its measurement:

* **the truth**: the model's own matrices perturbed (masses, stiffnesses, couplings,
  damping; :mod:`twind.lab.plant_truth`), scaled so that 5-8 of the modes visible in the
  measured elements move by 2-60 % at once, and which model mode became which true mode
  tracked along the way (:func:`~twind.lab.plant_truth.correspondence`);
* **the measurement**: the time-domain engine excited with white noise, each readback passed
  through a measurement chain drawn at random (:class:`~twind.lab.plant_measurement.Chain`:
  calibrations of 1e-3 to 10 and either sign, a delay of 0-20 ms and a first-order low-pass
  at 10-100 Hz common to all, a readback reading another, a drive's crosstalk, coherence
  holes, sensor noise) and Welch's estimate written as diaggui writes it, one file per drive,
  at KAGRA's 1/128 Hz resolution;
* **two kinds** (:data:`KINDS`): ``tm``, one test-mass drive (``TM_TEST_P`` or
  ``TM_TEST_L``) read on every readback, 0-10 or 0-20 Hz, 5 averages, as KAGRA's SRM and BS
  files; ``im``, the six intermediate-mass drives each read on every readback, 0-20 Hz,
  10 averages, open loop.

:func:`make_case` writes a case's files and its truth (``case.json``) into a directory;
:func:`score` reads ``twind diagnose --json``'s object and a case's truth (plain JSON both)
and counts the moved modes read, read as new modes, and the claims that are wrong;
:func:`run` makes, diagnoses (``twind diagnose`` in a process of its own) and scores cases,
one line each, then the totals: ``twind bench --suite cases [--optic SRM,PRM,BS]
[--per-effect N] [--workdir DIR]``.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from twind.config import CONFIG_DIR, load_config
from twind.config.statespace import StateSpaceOptic
from twind.lab.plant_measurement import (
    BW_HZ,
    Chain,
    Coupling,
    Crosstalk,
    Hole,
    measure_chain,
)
from twind.lab.plant_truth import ModeTruth, Perturbation, View, draw_truth, suspension
from twind.model.statespace import StateSpace

KINDS = ("tm", "im")
"""``tm``: one test-mass drive; ``im``: the six intermediate-mass drives."""
RATE_HZ = 512.0
"""The engine's rate: its hold is half a cycle's delay (1 ms), part of the chain's."""
AMPLITUDE = 1.0
"""The excitation's RMS (model units) for a drive that reaches a readback at that readback's
typical level; a drive that reaches none so well is driven harder (white noise: its ASD is
``RMS / sqrt(rate / 2)``)."""
READ_WITHIN = 0.02
"""A moved mode is read when a claim puts it this close to the truth..."""
READ_WITHIN_NARROW = 0.05
"""...or this close for a mode at most a bin wide (``f / Q`` below the resolution)."""
NEW_WITHIN, NEW_BINS = 0.05, 3
"""A resonance claim reads a moved mode as new within 5 % or 3 bins of it."""
MATCH_MODEL = 1e-3
"""A claim names the model mode whose frequency is this close (relative) to its own."""
BAND_BINS = 2
"""A claim beyond every element's coherent runs widened by this many bins is wrong."""
CONFIG = CONFIG_DIR / "kagra"


# ----------------------------------------------------------------------------- a case
@dataclass
class Case:
    """One realistic measurement of an optic and its truth.

    Attributes
    ----------
    optic, kind : str
    seed : int
    directory : Path
    files : list of Path
        One diaggui file per drive.
    drives : tuple of str
    modes : list of ModeTruth
        Every model mode in the band and the true mode it became.
    chain : Chain
        The measurement's nuisance truth.
    perturbation : Perturbation
    band_hz : (float, float)
    resolution_hz : float
    averages : int
    amplitude : tuple of float
        Each drive's excitation (RMS, model units).
    seconds : float
        The time it took to make.
    """

    optic: str
    kind: str
    seed: int
    directory: Path
    files: list[Path]
    drives: tuple[str, ...]
    modes: list[ModeTruth]
    chain: Chain
    perturbation: Perturbation
    band_hz: tuple[float, float]
    resolution_hz: float
    averages: int
    amplitude: tuple[float, ...]
    seconds: float = 0.0
    rate_hz: float = RATE_HZ

    @property
    def moved(self) -> list[ModeTruth]:
        """The visible modes that moved 2 % or more."""
        return [m for m in self.modes if m.moved]

    def to_json(self) -> dict:
        """``case.json``: the files (names in the directory), the truth and the chain."""
        return {"optic": self.optic, "kind": self.kind, "seed": self.seed,
                "files": [p.name for p in self.files], "drives": list(self.drives),
                "band_hz": list(self.band_hz), "resolution_hz": self.resolution_hz,
                "averages": self.averages, "excitation_rms": list(self.amplitude),
                "rate_hz": self.rate_hz, "seconds": self.seconds,
                "modes": [m.to_json() for m in self.modes], "chain": self.chain.to_json(),
                "perturbation": self.perturbation.to_json()}


def optic_of(name: str) -> StateSpaceOptic:
    """The shipped KAGRA optic `name` (``twind/configs/kagra/<name>.toml``)."""
    return load_config(CONFIG / f"{name}.toml").optics[name]


def make_case(optic: StateSpaceOptic, kind: str, seed: int, directory: str | Path, *,
              resolution_hz: float = BW_HZ, averages: int | None = None,
              stop_hz: float | None = None, rate_hz: float = RATE_HZ) -> Case:
    """Draw a case of `kind` (:data:`KINDS`) for `optic` and write it into `directory`: one
    diaggui file per drive and ``case.json`` (:meth:`Case.to_json`).

    Parameters
    ----------
    optic : StateSpaceOptic
    kind : str
    seed : int
        Everything drawn follows from it.
    directory : path
        Made if missing; its files are never overwritten.
    resolution_hz : float
    averages : int, optional
        Default 5 (``tm``) or 10 (``im``).
    stop_hz : float, optional
        Default 10 or 20 Hz at random (``tm``), 20 Hz (``im``).
    rate_hz : float
        The engine's.

    Returns
    -------
    Case
    """
    with threadpool_limits(limits=1, user_api="blas"):  # small matrices: threads only wait
        return _make_case(optic, kind, seed, Path(directory), resolution_hz, averages,
                          stop_hz, rate_hz)


def _make_case(optic: StateSpaceOptic, kind: str, seed: int, directory: Path,
               resolution_hz: float, averages: int | None, stop_hz: float | None,
               rate_hz: float) -> Case:
    """:func:`make_case`."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    drives, band, averages = _plan(kind, rng, resolution_hz, averages, stop_hz)
    readbacks = list(optic.readbacks)
    level, amplitude = _levels(optic, drives, band)
    noise = level * 10 ** rng.uniform(-3.5, -2.5, len(readbacks)) / math.sqrt(rate_hz / 2)
    holes = _hole_bands(readbacks, band, rng)
    view = View(tuple(optic.input_of(d) for d in drives),
                tuple(optic.readbacks[r] for r in readbacks),
                noise[:, None] * math.sqrt(rate_hz / 2) / amplitude[None, :], band,
                resolution_hz, tuple((readbacks.index(r), lo, hi) for r, lo, hi in holes))
    sus = suspension(optic.model)
    drawn = draw_truth(sus, view, rng)
    truth = sus.perturbed(drawn.perturbation)
    chain = _chain(optic, drives, truth, level, noise, holes, amplitude, rate_hz, rng)
    directory.mkdir(parents=True, exist_ok=True)
    files = [measure_chain(optic, d, directory / f"{optic.name}_{d}_exc.xml", chain,
                           model=truth, averages=averages, bw_hz=resolution_hz,
                           rate_hz=rate_hz, amplitude=float(a), stop_hz=band[1],
                           seed=seed * 100 + i)
             for i, (d, a) in enumerate(zip(drives, amplitude, strict=True))]
    case = Case(optic.name, kind, seed, directory, files, drives, drawn.modes, chain,
                drawn.perturbation, band, resolution_hz, averages, tuple(amplitude.tolist()),
                time.perf_counter() - t0, rate_hz)
    (directory / "case.json").write_text(json.dumps(case.to_json(), indent=1))
    return case


def _plan(kind: str, rng: np.random.Generator, resolution_hz: float, averages: int | None,
          stop_hz: float | None) -> tuple[tuple[str, ...], tuple[float, float], int]:
    """A kind's drives, band and averages (those not given drawn or defaulted)."""
    if kind == "tm":
        drive = str(rng.choice(["TM_TEST_P", "TM_TEST_L"]))
        stop = stop_hz or float(rng.choice([10.0, 20.0]))
        return (drive,), (resolution_hz, stop), averages or 5
    if kind == "im":
        return (tuple(f"IM_TEST_{d}" for d in "LTVRPY"), (resolution_hz, stop_hz or 20.0),
                averages or 10)
    raise ValueError(f"no kind {kind!r}; the kinds are {', '.join(KINDS)}")


def _levels(optic: StateSpaceOptic, drives: Sequence[str], band: tuple[float, float]
            ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each readback's typical response (the largest over the optic's drives of its median
    magnitude over the band, model units per unit of drive), and each of `drives`'
    excitation: what brings the readback it reaches best to that typical level (as a
    person measuring chooses an amplitude the sensors see)."""
    f = np.geomspace(max(band[0], 0.05), band[1], 200)
    h = optic.model.response(f, [optic.drives[d] for d in optic.drives],
                             [optic.readbacks[r] for r in optic.readbacks])
    typical = np.median(np.abs(h), axis=0)
    level = typical.max(axis=1)
    own = typical[:, [list(optic.drives).index(d) for d in drives]] / level[:, None]
    return level, AMPLITUDE / own.max(axis=0)


def _hole_bands(readbacks: Sequence[str], band: tuple[float, float],
                rng: np.random.Generator) -> list[tuple[str, float, float]]:
    """One or two readbacks' bands of 5-25 % of their centre, 0.2 Hz to 80 % of the band."""
    out = []
    for _ in range(int(rng.integers(1, 3))):
        centre = math.exp(rng.uniform(math.log(0.2), math.log(0.8 * band[1])))
        half = centre * rng.uniform(0.025, 0.125)
        out.append((str(rng.choice(readbacks)), centre - half, centre + half))
    return out


def _chain(optic: StateSpaceOptic, drives: Sequence[str], truth: StateSpace,
           level: NDArray[np.float64], noise: NDArray[np.float64],
           holes: Sequence[tuple[str, float, float]], amplitude: NDArray[np.float64],
           rate_hz: float, rng: np.random.Generator) -> Chain:
    """A measurement chain drawn at random (see the module's docstring): each hole's noise
    ten times the truth's largest answer in its band, each crosstalk 0.1-3 % of its
    readback's typical calibrated signal (the drive's excitation of RMS `amplitude`)."""
    readbacks = list(optic.readbacks)
    exc_asd = amplitude / math.sqrt(rate_hz / 2)
    sign = rng.choice([-1.0, 1.0], len(readbacks))
    gain = sign * 10 ** rng.uniform(-3, 1, len(readbacks))
    groups: dict[str, list[str]] = {}
    for r in readbacks:
        groups.setdefault(r.split("_")[0], []).append(r)
    pairs = [(a, b) for g in groups.values() for a in g for b in g if a != b]
    chosen = rng.choice(len(pairs), int(rng.integers(1, 4)), replace=False)
    couplings = tuple(Coupling(*pairs[k], float(rng.choice([-1, 1])
                                                * 10 ** rng.uniform(-2.5, -1.3)))
                      for k in chosen)
    crosstalk = []
    for _ in range(int(rng.integers(1, 3))):
        d, r = int(rng.integers(len(drives))), int(rng.integers(len(readbacks)))
        size = 10 ** rng.uniform(-3, -1.5) * abs(gain[r]) * level[r] / amplitude[d]
        crosstalk.append(Crosstalk(drives[d], readbacks[r], float(rng.choice([-1, 1]) * size)))
    inputs = [optic.input_of(d) for d in drives]
    hole_list = []
    for r, lo, hi in holes:
        h = truth.response(np.linspace(lo, hi, 20), inputs, [optic.readbacks[r]])
        hole_list.append(Hole(r, lo, hi, float(10 * (np.abs(h[:, 0]) * exc_asd).max())))
    return Chain({r: float(g) for r, g in zip(readbacks, gain, strict=True)},
                 float(rng.uniform(0, 0.02)), float(10 ** rng.uniform(1, 2)),
                 {r: float(n) for r, n in zip(readbacks, noise, strict=True)}, couplings,
                 tuple(crosstalk), tuple(hole_list))


def read_case(directory: str | Path) -> dict:
    """A case's ``case.json`` (its files' names made paths in `directory`)."""
    directory = Path(directory)
    case = json.loads((directory / "case.json").read_text())
    case["paths"] = [directory / name for name in case["files"]]
    return case


# ----------------------------------------------------------------------------- scoring
@dataclass
class Score:
    """A diagnosis against a case's truth.

    Attributes
    ----------
    moved : int
        Visible modes that moved 2 % or more.
    read : int
        Of those, put within 2 % of the truth (5 % for a mode a bin wide) by a chosen
        ``mode_frequency`` claim of their model mode.
    read_as_new : int
        Of the others, within 5 % or 3 bins of a chosen ``resonance`` claim.
    claims : int
        Chosen claims (every family).
    wrong : int
        Chosen ``mode_frequency`` claims that put their mode where the truth is not,
        ``resonance`` claims near no moved mode, and claims beyond the coherent band.
    beyond : int
        Chosen claims beyond every element's coherent runs (widened by 2 bins).
    reshaped, reshaped_read : int
        Moved modes whose shape changed too (:data:`RESHAPED_MAC`), and of those the read
        or read as new.
    calibrated : int
        Readbacks whose calibration the diagnosis fitted and the truth has.
    miscalibrated : int
        Of those, of the wrong sign or more than :data:`CALIBRATED_WITHIN` from the truth
        (:func:`miscalibrated`).
    seconds : float
        The diagnosis's.
    error : str
        What went wrong when there is no diagnosis to score.
    """

    moved: int = 0
    read: int = 0
    read_as_new: int = 0
    claims: int = 0
    wrong: int = 0
    beyond: int = 0
    reshaped: int = 0
    reshaped_read: int = 0
    calibrated: int = 0
    miscalibrated: int = 0
    seconds: float = math.nan
    error: str = ""
    notes: list[str] = field(default_factory=list)


def score(diagnosis: Mapping, modes: Sequence[Mapping], resolution_hz: float,
          calibration: Mapping[str, float] | None = None) -> Score:
    """Score `diagnosis` (``twind diagnose --json``'s object) against a case's truth (the
    ``modes`` of its ``case.json``, and its readbacks' ``calibration``).

    Parameters
    ----------
    diagnosis : mapping
        Its ``effects`` (claims: ``family``, ``rival_of``, for ``mode_frequency`` the model
        ``mode``'s ``f_hz`` and the claim's ``f_hz``, for ``resonance`` ``params.f_hz``) and
        ``coherent`` (element to ``[lo, hi]`` runs) are read.
    modes : sequence of mapping
        :meth:`~twind.lab.plant_truth.ModeTruth.to_json` of each model mode.
    resolution_hz : float
    calibration : mapping of str to float, optional
        Each readback's true calibration (the chain's); its ``nuisance`` is scored
        against it (:func:`miscalibrated`).

    Returns
    -------
    Score
    """
    chosen = [c for c in diagnosis.get("effects", []) if c.get("rival_of") is None]
    runs = [(lo - BAND_BINS * resolution_hz, hi + BAND_BINS * resolution_hz)
            for element in diagnosis.get("coherent", {}).values() for lo, hi in element]
    moved = [m for m in modes if m["moved"]]
    out = Score(moved=len(moved), claims=len(chosen))
    if calibration:
        fitted = {name: v["value"] for k, v in diagnosis.get("nuisance", {}).items()
                  if (name := k.removeprefix("calibration ")) in calibration}
        off = miscalibrated(fitted, calibration)
        out.calibrated, out.miscalibrated = len(fitted), len(off)
        out.notes += [f"calibration off: {name}" for name in off]
    read = set()
    for c in chosen:
        f = _claimed_hz(c)
        if f is None:
            continue
        inside = any(lo <= f <= hi for lo, hi in runs)
        right = _reads(c, f, modes, moved, resolution_hz)
        out.beyond += not inside
        out.wrong += not (inside and right)
        if c["family"] == "mode_frequency":
            read |= {i for i, m in enumerate(moved) if _mode_read(c, f, m, resolution_hz)}
        if not (inside and right):
            out.notes.append(f"wrong: {c['family']} at {f:.4g} Hz"
                             + ("" if inside else " (beyond the coherent band)"))
    out.read = len(read)
    new = {i for i, m in enumerate(moved) if i not in read for c in chosen
           if c["family"] == "resonance" and _near(_claimed_hz(c), m, resolution_hz)}
    out.read_as_new = len(new)
    reshaped = {i for i, m in enumerate(moved) if m.get("mac", 1.0) < RESHAPED_MAC}
    out.reshaped, out.reshaped_read = len(reshaped), len(reshaped & (read | new))
    out.notes += [f"missed: {m['model_f_hz']:.4g} Hz moved to {m['true_f_hz']:.4g} Hz "
                  f"({m['shift_percent']:+.1f} %"
                  + (f", MAC {m['mac']:.2f}" if i in reshaped else "") + ")"
                  for i, m in enumerate(moved) if i not in read | new]
    return out


RESHAPED_MAC = 0.5
"""A moved mode whose true shape has a MAC below this against its model mode's changed
shape too (a near-degenerate pair mixed): a move in the model's shape cannot take it."""
CALIBRATED_WITHIN = 2.0
"""A readback's fitted calibration is right within this factor of the truth's (after the
one scale they all share)."""


def miscalibrated(fitted: Mapping[str, float], truth: Mapping[str, float]) -> list[str]:
    """The readbacks of `fitted` whose calibration is of the wrong sign or more than
    :data:`CALIBRATED_WITHIN` from `truth`'s, after the one scale and sign they all share
    (the fit holds its first drive's calibration at 1, so every readback's carries that
    drive's true strength): the median ratio's."""
    ratios = {name: g / truth[name] for name, g in fitted.items()}
    if not ratios:
        return []
    values = np.array(list(ratios.values()))
    scale = float(np.median(np.abs(values)))
    sign = float(np.sign(np.median(np.sign(values)))) or 1.0
    return [name for name, r in ratios.items()
            if r * sign <= 0 or abs(math.log(abs(r) / scale)) > math.log(CALIBRATED_WITHIN)]


def _claimed_hz(claim: Mapping) -> float | None:
    """Where a claim puts a mode (None for a family that puts none)."""
    if claim["family"] == "mode_frequency":
        return float(claim["f_hz"])
    if claim["family"] == "resonance":
        return float(claim["params"]["f_hz"])
    return None


def _tolerance(mode: Mapping, resolution_hz: float) -> float:
    """How close a reading of `mode` must be (relative)."""
    narrow = mode["true_f_hz"] / max(mode["true_q"], 1e-300) <= resolution_hz
    return READ_WITHIN_NARROW if narrow else READ_WITHIN


def _mode_read(claim: Mapping, f_hz: float, mode: Mapping, resolution_hz: float) -> bool:
    """Whether a ``mode_frequency`` claim names `mode`'s model mode and puts it within the
    tolerance of its truth."""
    named = claim["mode"]["f_hz"]
    return (abs(named / mode["model_f_hz"] - 1) <= MATCH_MODEL
            and abs(f_hz / mode["true_f_hz"] - 1) <= _tolerance(mode, resolution_hz))


def _near(f_hz: float, mode: Mapping, resolution_hz: float) -> bool:
    """Whether a new resonance at `f_hz` reads `mode` (5 % or 3 bins)."""
    d = abs(f_hz - mode["true_f_hz"])
    return d <= NEW_WITHIN * mode["true_f_hz"] or d <= NEW_BINS * resolution_hz


def _reads(claim: Mapping, f_hz: float, modes: Sequence[Mapping], moved: Sequence[Mapping],
           resolution_hz: float) -> bool:
    """Whether a claim is right: a ``mode_frequency`` claim puts its model mode (any mode of
    that frequency) within the tolerance of its truth; a ``resonance`` claim lies near a
    moved mode."""
    if claim["family"] == "mode_frequency":
        return any(_mode_read(claim, f_hz, m, resolution_hz) for m in modes)
    return any(_near(f_hz, m, resolution_hz) for m in moved)


# ----------------------------------------------------------------------------- the bench
@dataclass
class Result:
    """A case made, diagnosed and scored (or what failed)."""

    optic: str
    kind: str
    seed: int
    directory: Path
    score: Score
    make_seconds: float = math.nan
    diagnosed: bool = True

    def line(self) -> str:
        """One printed line."""
        s = self.score
        head = (f"{self.optic:4s} {self.kind:2s} seed {self.seed:<6d} made "
                f"{self.make_seconds:6.1f} s")
        if s.error:
            return f"{head}  FAILED: {s.error}"
        if not self.diagnosed:
            return f"{head}: moved {s.moved} (not diagnosed)"
        return (f"{head}, diagnosed {s.seconds:6.1f} s: moved {s.moved}: read {s.read}, "
                f"as new {s.read_as_new}; claims {s.claims}: wrong {s.wrong} (beyond the "
                f"coherent band {s.beyond}); calibrations off {s.miscalibrated}/{s.calibrated}")


def diagnose_case(case: Mapping, timeout_s: float) -> tuple[dict | None, float, str]:
    """``twind diagnose`` on a case (:func:`diagnose_files`), its output kept beside the
    files (``diagnosis.json``, ``diagnosis.err``)."""
    directory = case["paths"][0].parent
    return diagnose_files(CONFIG / f"{case['optic']}.toml", case["paths"],
                          directory / "diagnosis", timeout_s)


def diagnose_files(config: Path, paths: Sequence[Path], keep: Path, timeout_s: float
                   ) -> tuple[dict | None, float, str]:
    """``twind diagnose --config CONFIG FILES --json`` in a process of its own, its standard
    output and error kept as `keep` with ``.json`` and ``.err``.

    Returns
    -------
    dict or None
        The diagnosis (None if it failed).
    float
        Seconds.
    str
        Why it failed (``""`` if not).
    """
    command = [sys.executable, "-m", "twind", "diagnose", "--config", str(config),
               *map(str, paths), "--json"]
    t0 = time.perf_counter()
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s,
                              check=False)
    except subprocess.TimeoutExpired:
        return None, time.perf_counter() - t0, f"twind diagnose ran over {timeout_s:g} s"
    seconds = time.perf_counter() - t0
    keep.with_suffix(".json").write_text(done.stdout)
    keep.with_suffix(".err").write_text(done.stderr)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        return None, seconds, f"twind diagnose exited {done.returncode}: {last}"
    try:
        return json.loads(done.stdout), seconds, ""
    except json.JSONDecodeError as err:
        return None, seconds, f"twind diagnose printed no JSON ({err})"


def bench_case(optic: str, kind: str, seed: int, workdir: Path, timeout_s: float,
               diagnose: bool = True) -> Result:
    """One case made (or read, if its directory holds it), diagnosed and scored; whatever
    raises is reported in the result, not raised."""
    directory = workdir / f"{optic}_{kind}_{seed}"
    made = math.nan
    try:
        if not (directory / "case.json").exists():
            made = make_case(optic_of(optic), kind, seed, directory).seconds
        case = read_case(directory)
        made = case["seconds"] if math.isnan(made) else made
    except Exception as err:  # noqa: BLE001 - one bad case must not stop the bench
        return Result(optic, kind, seed, directory,
                      Score(error=f"making it raised {type(err).__name__}: {err}"), made)
    moved = sum(m["moved"] for m in case["modes"])
    if not diagnose:
        notes = [f"moved: {m['model_f_hz']:.4g} Hz to {m['true_f_hz']:.4g} Hz "
                 f"({m['shift_percent']:+.1f} %, MAC {m['mac']:.2f})"
                 for m in case["modes"] if m["moved"]]
        return Result(optic, kind, seed, directory, Score(moved=moved, notes=notes), made,
                      diagnosed=False)
    result, seconds, error = diagnose_case(case, timeout_s)
    if result is None:
        return Result(optic, kind, seed, directory,
                      Score(moved=moved, seconds=seconds, error=error), made)
    try:
        s = score(result, case["modes"], case["resolution_hz"], case["chain"]["calibration"])
    except (KeyError, TypeError, ValueError) as err:
        s = Score(moved=moved, error=f"its JSON could not be scored ({type(err).__name__}: "
                                     f"{err})")
    s.seconds = seconds
    return Result(optic, kind, seed, directory, s, made)


def run(optics: Sequence[str], cases: int, workdir: str | Path, seed: int = 0,
        kinds: Sequence[str] = KINDS, timeout_s: float = 3600.0, diagnose: bool = True,
        say: Callable[[str], object] = print) -> list[str]:
    """The bench: `cases` cases per optic and kind, each made, diagnosed and scored, a line
    each as it is done (through `say`).

    Returns
    -------
    list of str
        The totals.
    """
    workdir = Path(workdir)
    done = []
    for optic in optics:
        for n in range(cases):
            for k, kind in enumerate(kinds):
                r = bench_case(optic, kind, seed + 1000 * n + 100 * k, workdir, timeout_s,
                               diagnose)
                say(r.line())
                for note in r.score.notes:
                    say(f"    {note}")
                done.append(r)
    return totals(done)


def totals(done: Sequence[Result]) -> list[str]:
    """The bench's figures."""
    ok = [r.score for r in done if not r.score.error and r.diagnosed]
    failed = [r for r in done if r.score.error]
    moved = sum(s.moved for s in ok)
    seconds = [r.score.seconds for r in done if not math.isnan(r.score.seconds)]
    made = [r.make_seconds for r in done if not math.isnan(r.make_seconds)]
    return [f"cases: {len(done)}, scored {len(ok)}, failed {len(failed)}"
            + (f" ({', '.join(f'{r.optic} {r.kind} {r.seed}' for r in failed)})"
               if failed else ""),
            f"moved modes read within {100 * READ_WITHIN:g} % ({100 * READ_WITHIN_NARROW:g} % "
            f"for a mode a bin wide): {sum(s.read for s in ok)}/{moved}; read as new: "
            f"{sum(s.read_as_new for s in ok)}",
            f"claims: {sum(s.claims for s in ok)}, wrong {sum(s.wrong for s in ok)}, beyond "
            f"the coherent band {sum(s.beyond for s in ok)}",
            f"moved modes whose shape changed too (MAC below {RESHAPED_MAC:g}): "
            f"{sum(s.reshaped for s in ok)}, read or read as new "
            f"{sum(s.reshaped_read for s in ok)}",
            f"readback calibrations of the wrong sign or off by more than "
            f"{CALIBRATED_WITHIN:g}x: {sum(s.miscalibrated for s in ok)}/"
            f"{sum(s.calibrated for s in ok)}",
            "diagnosis time: " + (f"median {np.median(seconds):.1f} s, largest "
                                  f"{max(seconds):.1f} s" if seconds else "none"),
            "making a case: " + (f"median {np.median(made):.1f} s, largest {max(made):.1f} s"
                                 if made else "none")]
