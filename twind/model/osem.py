"""Where the OSEMs sit on the optic and what they see and push (rigid-body kinematics).

Face OSEMs look along the beam axis (POS) at (y, z) = (+-h, +-h) on the optic face; the SIDE
OSEM looks along y at the centre-of-mass height (docs/model.md, "OSEMs and coils").
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from twind.model.mechanics import Mechanics
from twind.model.params import SOSParams

FACE_POSITION = {"UL": (1, 1), "UR": (-1, 1), "LL": (1, -1), "LR": (-1, -1)}  # (y, z) / lever


def _face_row(dofs: tuple[str, ...], y: float, z: float) -> NDArray[np.float64]:
    # displacement along x of the face point (y, z): x + z*PIT + y*YAW (docs/model.md convention)
    lever = {"POS": 1.0, "PIT": z, "YAW": y}
    return np.array([lever.get(d, 0.0) for d in dofs])


def sensing_matrix(p: SOSParams, mech: Mechanics) -> NDArray[np.float64]:
    """OSEM readings (m) per unit generalised coordinate, shape (5, n), rows
    :data:`twind.OSEMS`.

    Parameters
    ----------
    p : SOSParams
        The suspension (its OSEM lever arm).
    mech : Mechanics
        The coordinates read; those not POS, PIT, YAW or SIDE read nothing.

    Returns
    -------
    ndarray, shape (5, n)
    """
    h = p.osem_lever_m
    rows = [_face_row(mech.dofs, y * h, z * h) for y, z in FACE_POSITION.values()]
    rows.append(np.array([1.0 if d == "SIDE" else 0.0 for d in mech.dofs]))
    return np.array(rows)


def actuation_matrix(p: SOSParams, mech: Mechanics) -> NDArray[np.float64]:
    """Generalised force per DAC count on each coil, shape (n, 5), columns :data:`twind.OSEMS`.

    A face coil pushes along x at its OSEM's position with ``F = -alpha * drive``; the
    collocated coil therefore acts through the transpose of the sensing geometry.

    Parameters
    ----------
    p : SOSParams
        The suspension (OSEM lever arm, face and SIDE coil strengths in N/ct).
    mech : Mechanics
        The coordinates pushed.

    Returns
    -------
    ndarray, shape (n, 5)
    """
    gains = np.array([p.coil_N_per_ct] * 4 + [p.side_coil_N_per_ct])
    return -sensing_matrix(p, mech).T * gains
