"""The LIGO-T000134 analytical SOS model in the form docs/model.md states it (POS, PIT, YAW, SIDE)."""

from __future__ import annotations

import numpy as np

from twind import DOFS
from twind.model.mechanics import Mechanics
from twind.model.params import SOSParams


def analytical_mechanics(p: SOSParams) -> Mechanics:
    """M, C, K of T000134 eqs. 69-71 plus SIDE, with viscous damping ``M_ii w_i / Q_i``.

    Parameters
    ----------
    p : SOSParams
        Suspension parameters.

    Returns
    -------
    Mechanics
        Coordinates POS (m), PIT (rad), YAW (rad), SIDE (m).
    """
    m, g, l, b = p.mass_kg, p.g_mps2, p.wire_length_m, p.b_m
    w = {d: 2 * np.pi * f for d, f in p.uncoupled_frequencies_hz().items()}
    M = np.diag([m, p.I_pitch_kgm2, p.I_yaw_kgm2, m])
    K = np.array([
        [m * w["POS"] ** 2, -m * g * b / l, 0.0, 0.0],
        [-m * g * b / l, p.I_pitch_kgm2 * w["PIT"] ** 2, 0.0, 0.0],
        [0.0, 0.0, p.I_yaw_kgm2 * w["YAW"] ** 2, 0.0],
        [0.0, 0.0, 0.0, m * w["SIDE"] ** 2],
    ])
    C = np.diag([M[i, i] * w[d] / p.Q[d] for i, d in enumerate(DOFS)])
    return Mechanics(DOFS, M, C, K)
