"""The corpus's cases: optics drifted at random, each but the nulls with one effect or a
pair concealed (:mod:`twind.commissioning.concealed`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from twind.analysis.identification.data import FitData
from twind.commissioning.concealed import conceal, drifted
from twind.commissioning.hidden import hidden
from twind.config import OpticConfig
from twind.model.plant import Plant

EFFECTS = ("coil_imbalance", "osem_imbalance", "loop_delay", "actuator_pole", "wire_asymmetry",
           "bounce_roll")
"""The catalogue effects the corpus hides by default. ``side_coupling`` on request, with SIDE
among the excited DOFs: a POS/PIT/YAW measurement barely moves SIDE, so no physical
coupling reaches 3 sigma in it."""

BEYOND = ("resonance", "channel_filter", "coil_imbalance+loop_delay",
          "osem_imbalance+actuator_pole", "wire_asymmetry+coil_imbalance")
"""What the catalogue alone cannot say, hidden by default beside it: a body on the face
(:func:`~twind.commissioning.hidden.attached_body`), one channel's own stage
(:func:`~twind.commissioning.hidden.one_stage`) and pairs of catalogue effects, each
concealed alone and then put in together."""


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
        The bins and errors effects are concealed against
        (:func:`~twind.commissioning.concealed.reference_data`); None when there are no
        effects.
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
