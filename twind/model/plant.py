"""The suspension as the damping loop sees it: coil drive counts in, OSEM metres out.

``P(s) = IN1/OUT = InMat . Sens . (M s^2 + C s + K)^-1 . Act . OutMat . exp(-s tau)`` (docs/model.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind.model.matrices import input_matrix, output_matrix
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
        A real pole in every coil-driver chain (``inf``: none; docs/model.md's ``actuator_pole``).
    channel_filters : tuple of (str, int, float, float)
        Stages on single channels: ``("coil" or "osem", channel index, pole Hz, zero Hz)``
        multiply that coil's drive (that OSEM's reading) by ``(1 + s/2 pi zero) /
        (1 + s/2 pi pole)`` (``inf``: no zero): a de-whitening or whitening stage that
        differs on one channel.
    """

    mechanics: Mechanics
    sensing: NDArray[np.float64]
    actuation: NDArray[np.float64]
    input_matrix: NDArray[np.float64]
    output_matrix: NDArray[np.float64]
    delay_s: float
    drive_pole_hz: float = math.inf
    channel_filters: tuple[tuple[str, int, float, float], ...] = ()

    @classmethod
    def from_params(cls, p: SOSParams, mech: Mechanics) -> Plant:
        """The nominal OSEM geometry and CDS matrices of docs/model.md around `mech`.

        Parameters
        ----------
        p : SOSParams
            The suspension (OSEM lever, coil strengths, loop delay).
        mech : Mechanics
            Its rigid-body dynamics (of either model).

        Returns
        -------
        Plant
            With no driver pole and no channel stage.
        """
        return cls(mech, sensing_matrix(p, mech), actuation_matrix(p, mech),
                   input_matrix(p.osem_lever_m), output_matrix(), p.loop_delay_s)

    def response(self, f_hz: NDArray[np.float64]) -> NDArray[np.complex128]:
        """``IN1/OUT`` at frequencies `f_hz`, shape (len(f), 4, 4)."""
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        if not self.channel_filters:
            P = self.mechanics.admittance(s, self.input_matrix @ self.sensing,
                                          self.actuation @ self.output_matrix)
        else:  # OSEM readings per coil count, then each channel's own stage on its row/column
            G = self.mechanics.admittance(s, self.sensing, self.actuation)
            for kind, k, pole, zero in self.channel_filters:
                F = (1 + s / (2 * np.pi * zero)) / (1 + s / (2 * np.pi * pole))
                if kind == "coil":
                    G[:, :, k] *= F[:, None]
                else:
                    G[:, k, :] *= F[:, None]
            P = self.input_matrix @ G @ self.output_matrix
        drive = np.exp(-s * self.delay_s) / (1 + s / (2 * np.pi * self.drive_pole_hz))
        return P * drive[:, None, None]

    def osem_state_space(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Continuous ``(A, B_coil, B_sp, C)``: coil counts (5) and suspension point (3) in,
        OSEM readings (m, 5) out, state ``[q, q']`` (then one per channel filter, then the
        coil drivers', with a drive pole). The loop delay is not included."""
        A, B_coil, B_sp, C = self._with_channel_filters()
        if math.isinf(self.drive_pole_hz):
            return A, B_coil, B_sp, C
        # five coil-driver states, each a first-order low-pass ahead of its coil
        w = 2 * np.pi * self.drive_pole_hz
        m = A.shape[0]
        A = np.block([[A, B_coil], [np.zeros((5, m)), -w * np.eye(5)]])
        return (A, np.vstack([np.zeros((m, 5)), w * np.eye(5)]),
                np.vstack([B_sp, np.zeros((5, B_sp.shape[1]))]), np.hstack([C, np.zeros((5, 5))]))

    def _with_channel_filters(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """The mechanics' state space with one state per channel filter: ``F = (p/z) (1 +
        (z - p) / (s + p))`` (p, z in rad/s), its state ``w' = -p w + u`` driven by the
        coil's count (the OSEM's reading)."""
        A, B = self.mechanics.state_space()
        n = self.mechanics.n
        C = np.hstack([self.sensing, np.zeros((5, n))])
        B_coil, B_sp = B @ self.actuation, B @ self.mechanics.suspension_point_forces()
        for kind, k, pole, zero in self.channel_filters:
            p, z = 2 * np.pi * pole, 2 * np.pi * zero
            direct, through = p / z, p * (1 - p / z)  # p/z (z - p), finite as z -> inf
            m = A.shape[0]
            A = np.pad(A, ((0, 1), (0, 1)))
            A[m, m] = -p
            B_coil, B_sp, C = np.pad(B_coil, ((0, 1), (0, 0))), np.pad(B_sp, ((0, 1), (0, 0))), \
                np.pad(C, ((0, 0), (0, 1)))
            if kind == "coil":
                A[:m, m] = through * B_coil[:m, k]
                B_coil[m, k] = 1.0
                B_coil[:m, k] *= direct
            else:
                A[m, :m] = C[k, :m]
                C[k, m] = through
                C[k, :m] *= direct
        return A, B_coil, B_sp, C
