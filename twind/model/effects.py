"""Physics the nominal model leaves out: MODEL.md's catalogue, each entry a change to the plant.

Every effect is zero at zero parameters, so "nominal + effect" nests the nominal model (what
a likelihood-ratio test needs).  Parameters carry MODEL.md's names, flattened for fitting:
``gains`` {UL, UR, LL, LR} become ``gain_UL`` ... ``gain_LR``.

| id               | physics (MODEL.md)                                          | parameters              |
| ---------------- | ----------------------------------------------------------- | ----------------------- |
| coil_imbalance   | face coil i pushes F_i (1 + g_i)                             | gain_UL .. gain_LR      |
| osem_imbalance   | face OSEM i reads s_i (1 + g_i)                              | gain_UL .. gain_LR      |
| loop_delay       | delay beyond the one-cycle nominal                           | extra_s (s)             |
| actuator_pole    | every coil driver x 1 / (1 + s / 2 pi f)                     | f_hz (Hz)               |
| side_coupling    | face OSEMs also read ks y; face coils also push ka F_i along y | sensing, actuation    |
| wire_asymmetry   | centre of mass off the wire plane by d: K_xphi = K_phix = -m g d / l | delta_m (m)     |

``bounce_roll`` needs the VERT and ROLL coordinates of the geometric model and is not here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from twind.errors import TwindError
from twind.loop.plant import Plant
from twind.model.mechanics import Mechanics
from twind.model.osem import FACE_POSITION
from twind.model.params import SOSParams

FACES = tuple(FACE_POSITION)  # UL, UR, LL, LR: the first four OSEM columns/rows


class EffectError(TwindError):
    """An unknown effect, or parameters it does not take."""


@dataclass(frozen=True)
class Effect:
    """One entry of the catalogue.

    Attributes
    ----------
    id : str
        MODEL.md's identifier.
    params : tuple of str
        Its parameters (all zero: the nominal model).
    physics : str
        One line for a report.
    apply : callable
        ``(plant, sus, values) -> plant`` with the effect in.
    scale : dict of str to float
        A typical size of each parameter, for finite differences and starting steps.
    """

    id: str
    params: tuple[str, ...]
    physics: str
    apply: Callable[[Plant, SOSParams, Mapping[str, float]], Plant]
    scale: dict[str, float]


def _gains(values: Mapping[str, float]) -> np.ndarray:
    return np.array([1.0 + values.get(f"gain_{f}", 0.0) for f in FACES] + [1.0])


def _coil_imbalance(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    return replace(plant, actuation=plant.actuation * _gains(v)[None, :])


def _osem_imbalance(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    return replace(plant, sensing=plant.sensing * _gains(v)[:, None])


def _loop_delay(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    return replace(plant, delay_s=plant.delay_s + v.get("extra_s", 0.0))


def _actuator_pole(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    # parametrised by 1/f so that zero is "no pole" and the model nests the nominal one
    inv = v.get("inv_f_hz", 0.0)
    return replace(plant, drive_pole_hz=math.inf if inv <= 0 else 1.0 / inv)


def _side_coupling(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    dofs = plant.mechanics.dofs
    sensing, actuation = plant.sensing.copy(), plant.actuation.copy()
    side, pos = dofs.index("SIDE"), dofs.index("POS")
    sensing[:4, side] += v.get("sensing", 0.0)
    actuation[side, :4] += v.get("actuation", 0.0) * actuation[pos, :4]
    return replace(plant, sensing=sensing, actuation=actuation)


def _wire_asymmetry(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    mech = plant.mechanics
    i, j = mech.index("POS"), mech.index("YAW")
    K = mech.K.copy()
    k = -sus.mass_kg * sus.g_mps2 * v.get("delta_m", 0.0) / sus.wire_length_m
    K[i, j] += k
    K[j, i] += k
    return replace(plant, mechanics=Mechanics(mech.dofs, mech.M, mech.C, K))


_GAINS = tuple(f"gain_{f}" for f in FACES)
CATALOGUE: dict[str, Effect] = {e.id: e for e in (
    Effect("coil_imbalance", _GAINS, "face coils of unequal strength: F_i x (1 + g_i)",
           _coil_imbalance, dict.fromkeys(_GAINS, 0.01)),
    Effect("osem_imbalance", _GAINS, "face OSEMs of unequal gain: s_i x (1 + g_i)",
           _osem_imbalance, dict.fromkeys(_GAINS, 0.01)),
    Effect("loop_delay", ("extra_s",), "delay beyond the one-cycle nominal (ADC/DAC, AA/AI)",
           _loop_delay, {"extra_s": 1e-4}),
    Effect("actuator_pole", ("inv_f_hz",), "a pole in every coil-driver chain",
           _actuator_pole, {"inv_f_hz": 1e-2}),
    Effect("side_coupling", ("sensing", "actuation"),
           "SIDE mixes into the face OSEMs (sensing) and the face coils push sideways",
           _side_coupling, {"sensing": 0.01, "actuation": 0.01}),
    Effect("wire_asymmetry", ("delta_m",), "centre of mass off the wire plane: K_x,yaw",
           _wire_asymmetry, {"delta_m": 1e-4}),
)}


def with_effect(plant: Plant, sus: SOSParams, effect: str, values: Mapping[str, float]
                ) -> Plant:
    """`plant` with catalogue `effect` at parameter `values` (missing ones are zero).

    Parameters
    ----------
    plant : Plant
        The nominal plant of `sus`.
    sus : SOSParams
        The suspension's parameters (mass, wire length for ``wire_asymmetry``).
    effect : str
        A key of :data:`CATALOGUE`.
    values : mapping of str to float
        The effect's parameters.

    Returns
    -------
    Plant
    """
    if effect not in CATALOGUE:
        msg = f"unknown effect {effect!r}; the catalogue has {', '.join(CATALOGUE)}"
        raise EffectError(msg)
    entry = CATALOGUE[effect]
    unknown = sorted(set(values) - set(entry.params))
    if unknown:
        msg = f"{effect} takes {', '.join(entry.params)}, not {', '.join(unknown)}"
        raise EffectError(msg)
    return entry.apply(plant, sus, values)


def model_names(effect: str, values: Mapping[str, float], sigma: Mapping[str, float | None]
                ) -> tuple[dict, dict]:
    """An effect's fitted parameters and their sigmas in MODEL.md's names: the face gains
    as ``{"gains": {"UL": ...}}``, a driver pole as ``f_hz`` (fitted as 1/f, which is
    linear near the nominal model; its sigma propagated to first order)."""
    if effect in ("coil_imbalance", "osem_imbalance"):
        return ({"gains": {f: values[f"gain_{f}"] for f in FACES}},
                {"gains": {f: sigma[f"gain_{f}"] for f in FACES}})
    if effect == "actuator_pole":
        inv, s = values["inv_f_hz"], sigma["inv_f_hz"]
        f = 1 / inv if inv > 0 else math.inf
        return {"f_hz": f}, {"f_hz": None if s is None or inv <= 0 else s / inv**2}
    return dict(values), dict(sigma)
