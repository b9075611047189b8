"""CDS input and output matrices between OSEM basis and DOF basis (docs/model.md)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from twind.model.osem import FACE_POSITION

# The input matrix calibrates m -> um (POS, SIDE) and rad -> urad (PIT, YAW).
CALIBRATION = 1e6


def input_matrix(lever_m: float) -> NDArray[np.float64]:
    """OSEM readings (m) -> DOF signals (um, urad), shape (4, 5): rows POS PIT YAW SIDE."""
    y, z = np.array(list(FACE_POSITION.values()), dtype=float).T
    m = np.zeros((4, 5))
    m[0, :4] = 0.25
    m[1, :4] = z / (4 * lever_m)
    m[2, :4] = y / (4 * lever_m)
    m[3, 4] = 1.0
    return CALIBRATION * m


def output_matrix() -> NDArray[np.float64]:
    """DOF outputs (ct) -> coil drives (ct), shape (5, 4): columns POS PIT YAW SIDE."""
    m = np.zeros((5, 4))
    for i, (y, z) in enumerate(FACE_POSITION.values()):
        m[i, :3] = (1.0, z, y)
    m[4, 3] = 1.0
    return m
