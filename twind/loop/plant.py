"""The suspension as the damping loop sees it: coil drive counts in, OSEM metres out.

``P(s) = IN1/OUT = InMat . Sens . (M s^2 + C s + K)^-1 . Act . OutMat . exp(-s tau)`` (MODEL.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind.loop.matrices import input_matrix, output_matrix
from twind.model.mechanics import Mechanics
from twind.model.osem import actuation_matrix, sensing_matrix
from twind.model.params import SOSParams


@dataclass(frozen=True)
class Plant:
    """Mechanics with its OSEM sensing/actuation and the CDS matrices around it.

    Attributes
    ----------
    mechanics : Mechanics
    sensing : ndarray, shape (5, n)
        OSEM reading (m) per coordinate.
    actuation : ndarray, shape (n, 5)
        Generalised force per coil drive count.
    input_matrix : ndarray, shape (4, 5)
        OSEM m -> DOF um/urad.
    output_matrix : ndarray, shape (5, 4)
        DOF ct -> coil ct.
    delay_s : float
        Pure delay in the drive path.
    drive_pole_hz : float
        A real pole in every coil-driver chain (``inf``: none; MODEL.md's ``actuator_pole``).
    """

    mechanics: Mechanics
    sensing: NDArray[np.float64]
    actuation: NDArray[np.float64]
    input_matrix: NDArray[np.float64]
    output_matrix: NDArray[np.float64]
    delay_s: float
    drive_pole_hz: float = math.inf

    @classmethod
    def from_params(cls, p: SOSParams, mech: Mechanics) -> Plant:
        """The nominal OSEM geometry and CDS matrices of MODEL.md around `mech`."""
        return cls(mech, sensing_matrix(p, mech), actuation_matrix(p, mech),
                   input_matrix(p.osem_lever_m), output_matrix(), p.loop_delay_s)

    def response(self, f_hz: NDArray[np.float64]) -> NDArray[np.complex128]:
        """``IN1/OUT`` at frequencies `f_hz`, shape (len(f), 4, 4)."""
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        H = self.mechanics.admittance(s)
        P = self.input_matrix @ self.sensing @ H @ self.actuation @ self.output_matrix
        drive = np.exp(-s * self.delay_s) / (1 + s / (2 * np.pi * self.drive_pole_hz))
        return P * drive[:, None, None]

    def osem_state_space(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Continuous ``(A, B_coil, B_sp, C)``: coil counts (5) and suspension point (3) in,
        OSEM readings (m, 5) out, state ``[q, q']`` (then the coil drivers', with a drive
        pole). The loop delay is not included."""
        A, B = self.mechanics.state_space()
        n = self.mechanics.n
        C = np.hstack([self.sensing, np.zeros((5, n))])
        B_coil, B_sp = B @ self.actuation, B @ self.mechanics.suspension_point_forces()
        if math.isinf(self.drive_pole_hz):
            return A, B_coil, B_sp, C
        # five coil-driver states, each a first-order low-pass ahead of its coil
        w = 2 * np.pi * self.drive_pole_hz
        A = np.block([[A, B_coil], [np.zeros((5, 2 * n)), -w * np.eye(5)]])
        return (A, np.vstack([np.zeros((2 * n, 5)), w * np.eye(5)]),
                np.vstack([B_sp, np.zeros((5, B_sp.shape[1]))]), np.hstack([C, np.zeros((5, 5))]))
