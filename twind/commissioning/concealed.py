"""An optic with physics the model left out, as the demo and the proof corpus make it:
drifted at random from its nominal parameters (:data:`SPREAD`), an effect put into its plant
by hand (:mod:`twind.commissioning.hidden`) and concealed (:func:`conceal`) at
:data:`CONCEAL_SIGMA` against the measurement it will be found in (:func:`reference_data`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.analysis.diagnose import MIN_COHERENCE
from twind.analysis.identification.data import FitData
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.params import param_value, with_params
from twind.commissioning.hidden import FIRST_SIZE, hidden
from twind.commissioning.measurement import measure_tfs
from twind.config import OpticConfig
from twind.model.plant import Plant

CONCEAL_SIGMA = 3.0
"""Largest change of one bin of IN1/EXC an effect makes, in that bin's standard errors."""

SPREAD = {"wire_length_m": 0.015, "b_m": 0.02, "R1_m": 0.02, "coil_N_per_ct": 0.03,
          "osem_lever_m": 0.015, "Q_POS": 0.15, "Q_PIT": 0.15, "Q_YAW": 0.15, "Q_SIDE": 0.15}
"""Relative standard deviation of each nominal parameter's drift from case to case."""

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
        One of :data:`~twind.commissioning.hidden.MADE`.
    reference : FitData
        The bins and errors the effect is concealed against (:func:`reference_data`).
    direction : ndarray
        Four face gains of an imbalance (see :func:`~twind.commissioning.hidden.hidden`).
    target : float
        The largest change of one bin, in its standard errors.
    shape : dict, optional
        As :func:`~twind.commissioning.hidden.hidden`.

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

    size = FIRST_SIZE[effect]
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
