"""The corpus's cases: optics drifted at random (:data:`SPREAD`), each but the nulls with one
effect concealed (:func:`conceal`) at :data:`CONCEAL_SIGMA`, and the measurement they are
concealed in."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.analysis.diagnose import (
    MIN_COHERENCE,
)
from twind.analysis.identification.data import FitData
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.params import param_value, with_params
from twind.commissioning.measurement import measure_tfs
from twind.config import OpticConfig
from twind.lab.corpus.physics import _FIRST_SIZE, hidden
from twind.model.plant import Plant

CONCEAL_SIGMA = 3.0
"""Largest change of one bin of IN1/EXC an effect makes, in that bin's standard errors."""
SPREAD = {"wire_length_m": 0.015, "b_m": 0.02, "R1_m": 0.02, "coil_N_per_ct": 0.03,
          "osem_lever_m": 0.015, "Q_POS": 0.15, "Q_PIT": 0.15, "Q_YAW": 0.15, "Q_SIDE": 0.15}
"""Relative standard deviation of each nominal parameter's drift from case to case."""
EFFECTS = ("coil_imbalance", "osem_imbalance", "loop_delay", "actuator_pole", "wire_asymmetry",
           "bounce_roll")
"""The catalogue effects the corpus hides by default. ``side_coupling`` on request, with SIDE
among the excited DOFs: a POS/PIT/YAW measurement barely moves SIDE, so no physical
coupling reaches 3 sigma in it."""
BEYOND = ("resonance", "channel_filter", "coil_imbalance+loop_delay",
          "osem_imbalance+actuator_pole", "wire_asymmetry+coil_imbalance")
"""What the catalogue alone cannot say, hidden by default beside it: a body on the face
(:func:`attached_body`), one channel's own stage (:func:`one_stage`) and pairs of
catalogue effects, each concealed alone and then put in together."""
AVERAGES, RMS = 10, 3.0
EXCITED = ("POS", "PIT", "YAW")
"""The corpus measurement: white EXC of RMS 3 below 30 Hz on each of POS, PIT, YAW in turn,
Hann, 10 averages overlapping by half."""
ROUTE_BW = {"xml": 0.01, "mcap": 0.05}
"""Its resolution (Hz) per route: diaggui sets in example_null's format, the blind sets';
sessions of 5.5 min (at 0.01 Hz one is 27 min long, 2.2 GB of MCAP and 3 min to record).
At 0.05 Hz an effect concealed to the same largest bin has a fifth of the bins, and it is
1.7 to 4.9 times less present (the default effects, in chi^2 units)."""
STOP_HZ = 30.0  # example_null's StopFrequency: the bins a diaggui set holds
@dataclass
class Case:
    """One optic of the corpus.

    Attributes
    ----------
    name : str
    effect : str or None
        The catalogue effect hidden in `plant`; None for a null.
    real : OpticConfig
        The drifted optic.
    plant : Plant
        The plant the twin runs.
    truth : dict
        The effect's parameters in the names of docs/model.md.
    largest_sigma : float
        Largest change of one bin of IN1/EXC the effect makes, in standard errors.
    present : float
        The effect's change summed over the bins, in chi^2 units.
    """

    name: str
    effect: str | None
    real: OpticConfig
    plant: Plant
    truth: dict = field(default_factory=dict)
    largest_sigma: float = 0.0
    present: float = 0.0


def drifted(cfg: OpticConfig, rng: np.random.Generator) -> OpticConfig:
    """`cfg` with each nominal parameter drifted by :data:`SPREAD` (Gaussian).

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    rng : numpy.random.Generator
        Draws the drifts.

    Returns
    -------
    OpticConfig
    """
    values = {k: param_value(cfg.sus, k) * (1 + s * rng.standard_normal())
              for k, s in SPREAD.items()}
    return replace(cfg, sus=with_params(cfg.sus, values))


def conceal(real: OpticConfig, effect: str, reference: FitData, direction: NDArray,
            target: float = CONCEAL_SIGMA, shape: dict | None = None
            ) -> tuple[Plant, dict, float, float]:
    """The effect scaled so that its largest change of a bin ``diagnose`` fits is `target`
    standard errors of `reference` (a measurement of the same kind, its bins as
    ``diagnose`` chooses them).

    Parameters
    ----------
    real : OpticConfig
        The drifted optic.
    effect : str
        One of :data:`MADE`.
    reference : FitData
        The bins and errors the effect is concealed against (:func:`reference_data`).
    direction : ndarray
        Four face gains of an imbalance (see :func:`hidden`).
    target : float
        The largest change of one bin, in its standard errors.
    shape : dict, optional
        As :func:`hidden`.

    Returns
    -------
    plant : Plant
    truth : dict
        The effect's parameters, and ``_size``: the size to hide it again.
    largest : float
        Its largest change of one bin (standard errors).
    present : float
        Its change summed over the bins (chi^2 units).
    """
    base = real.plant()
    model = ClosedLoopModel.of(real, reference)
    rows, cols = _indices(reference)

    def in1(plant: Plant) -> NDArray[np.complex128]:
        return model.response(plant)[:, rows][:, :, cols]

    T0 = in1(base)

    def change(size: float) -> NDArray[np.float64]:
        z = np.abs(in1(hidden(base, effect, size, direction, real.sus, shape)[0]) - T0
                   ) / reference.sigma
        return z[reference.mask]

    size = _FIRST_SIZE[effect]
    if effect == "wire_asymmetry":  # either loop's clamp raised
        size = math.copysign(size, direction[0])
    # nearly linear in size (a tilt's modes: in its square): a few secant steps
    power = 0.5 if effect == "bounce_roll" else 1.0
    for _ in range(3):
        size *= (target / max(change(size).max(), 1e-12)) ** power
    if effect == "loop_delay":  # the engine delays by whole samples
        rate = real.sus.sample_rate_hz
        size = max(round(size * rate), 1) / rate
    z = change(size)
    plant, truth = hidden(base, effect, size, direction, real.sus, shape)
    truth["_size"] = size  # how to hide it again beside another effect (pairs)
    return plant, truth, float(z.max()), float(np.sum(z**2))


def _indices(data: FitData) -> tuple[list[int], list[int]]:

    return [DOFS.index(d) for d in data.responses], [DOFS.index(d) for d in data.excited]


def reference_data(cfg: OpticConfig, seed: int, excited: Sequence[str] = EXCITED,
                   route: str = "xml", bw: float | None = None, averages: int = AVERAGES,
                   rms: float = RMS) -> FitData:
    """A corpus measurement of the nominal optic on `route`, its bins as ``diagnose``
    chooses them: the errors the effects are concealed against.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    seed : int
        Seed of the twin's noise and the excitation.
    excited : sequence of str
        DOFs excited in turn.
    route : str
        ``"xml"`` (bins up to :data:`STOP_HZ`) or ``"mcap"``.
    bw : float, optional
        Resolution (Hz); default the route's (:data:`ROUTE_BW`).
    averages : int
    rms : float
        RMS of the white EXC.

    Returns
    -------
    FitData
    """

    tfs = measure_tfs(cfg, excited, bw=bw or ROUTE_BW[route], averages=averages, rms=rms,
                      seed=seed)
    band = (0.0, STOP_HZ) if route == "xml" else None
    return FitData.from_tfset(tfs, MIN_COHERENCE, band).span()


def make_cases(cfg: OpticConfig, reference: FitData | None, per_effect: int = 3, nulls: int = 3,
               seed: int = 11, effects: Sequence[str] = EFFECTS) -> list[Case]:
    """The corpus: `nulls` drifted optics and `per_effect` of each kind of `effects`
    (a catalogue effect, ``resonance``, ``channel_filter`` or a pair ``"a+b"``), each
    effect concealed.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    reference : FitData or None
        The bins and errors effects are concealed against (:func:`reference_data`); None
        when there are no effects.
    per_effect : int
        Cases of each kind of `effects`.
    nulls : int
        Cases with no effect.
    seed : int
        Seed of the drifts, directions and shapes.
    effects : sequence of str
        Kinds of effect hidden.

    Returns
    -------
    list of Case
        The nulls first.
    """
    rng = np.random.default_rng(seed)
    cases = []
    for k in range(nulls):
        real = drifted(cfg, rng)
        cases.append(Case(f"null #{k + 1}", None, real,
                          real.plant()))
    for effect in effects:
        for k in range(per_effect):
            real = drifted(cfg, rng)
            parts = effect.split("+")
            draws = [_draw(e, rng) for e in parts]
            hid = [conceal(real, e, reference, direction, shape=shape)
                   for e, (direction, shape) in zip(parts, draws, strict=True)]
            sizes = [h[1].pop("_size") for h in hid]
            if len(parts) == 1:
                plant, truth, largest, present = hid[0]
            else:  # each concealed alone, then both put into one plant
                plant = real.plant()
                for e, size, (direction, shape) in zip(parts, sizes, draws, strict=True):
                    plant = hidden(plant, e, size, direction, real.sus, shape)[0]
                truth = {e: h[1] for e, h in zip(parts, hid, strict=True)}
                largest = max(h[2] for h in hid)
                present = sum(h[3] for h in hid)
            cases.append(Case(f"{effect} #{k + 1}", effect, real, plant, truth, largest,
                              present))
    return cases


def _draw(effect: str, rng: np.random.Generator) -> tuple[NDArray, dict | None]:
    """A random direction (face gains) and the shape of a case."""
    direction = rng.standard_normal(4)
    direction /= np.abs(direction).max()
    shape = None
    if effect == "resonance":  # a body anywhere on the face, 0.3-20 Hz, Q 5-100
        shape = {"f_hz": float(np.exp(rng.uniform(math.log(0.3), math.log(20.0)))),
                 "q": float(np.exp(rng.uniform(math.log(5.0), math.log(100.0)))),
                 "point_m": (float(rng.uniform(-0.025, 0.025)),
                             float(rng.uniform(-0.025, 0.025)))}
    elif effect == "channel_filter":  # one face channel (SIDE is barely excited)
        shape = {"kind": str(rng.choice(["coil", "osem"])), "channel": int(rng.integers(4)),
                 "pole_hz": float(np.exp(rng.uniform(math.log(3.0), math.log(50.0))))}
    return direction, shape
