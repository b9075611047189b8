"""Linear rigid-body dynamics ``M q'' + C q' + K q = f`` about an equilibrium.

Both suspension models (analytical T000134 and geometric) produce a :class:`Mechanics`; the
rest of twind only ever sees this.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

# Suspension-point inputs: translation along the beam, sideways, and yaw of the clamp frame.
SUSPENSION_POINT = ("x_sp", "y_sp", "phi_sp")
_SP_DOF = {"x_sp": "POS", "y_sp": "SIDE", "phi_sp": "YAW"}
MODAL_CONDITION = 1e8
"""Largest condition number of the modes' eigenvectors :meth:`Mechanics.admittance` sums
over (beyond it, near-defective modes lose digits: it inverts per frequency instead)."""


@dataclass(frozen=True)
class Mechanics:
    """Mass, damping and stiffness matrices over named generalised coordinates.

    Attributes
    ----------
    dofs : tuple of str
        Coordinate names, a subset of POS, PIT, YAW, SIDE, VERT, ROLL (m or rad).
    M, C, K : ndarray, shape (n, n)
        Mass (kg, kg m^2), viscous damping and stiffness matrices.
    """

    dofs: tuple[str, ...]
    M: NDArray[np.float64]
    C: NDArray[np.float64]
    K: NDArray[np.float64]

    @property
    def n(self) -> int:
        """Number of generalised coordinates."""
        return len(self.dofs)

    def index(self, dof: str) -> int:
        """Position of coordinate `dof`."""
        return self.dofs.index(dof)

    def suspension_point_forces(self) -> NDArray[np.float64]:
        """Generalised force per unit suspension-point motion, shape (n, 3).

        Moving the clamps rigidly by ``x_sp`` leaves the optic in equilibrium at ``q = x_sp``
        in that coordinate, so the force it produces is the stiffness column of that coordinate.
        """
        return np.stack([self.K[:, self.index(_SP_DOF[sp])] for sp in SUSPENSION_POINT], axis=1)

    def admittance(self, s: NDArray[np.complex128], left: NDArray | None = None,
                   right: NDArray | None = None) -> NDArray[np.complex128]:
        """``left (M s^2 + C s + K)^-1 right`` at each complex frequency, shape
        (len(s), a, b) for `left` (a, n) and `right` (n, b) (default the identity).

        Summed over the modes, ``sum_k (left v_k)(w_k right) / (s - lambda_k)`` from one
        eigendecomposition of the state matrix: one matrix product for all frequencies
        instead of an inverse per frequency (a fit evaluates this thousands of times).
        Modes too close to defective for that (eigenvectors with condition number above
        :data:`MODAL_CONDITION`) fall back to the inverses.

        Parameters
        ----------
        s : ndarray of complex
            Complex frequencies ``2 pi j f`` (rad/s), one-dimensional.
        left : ndarray, shape (a, n), optional
            Applied on the left (e.g. the OSEMs' sensing); default the identity.
        right : ndarray, shape (n, b), optional
            Applied on the right (e.g. the coils' actuation); default the identity.

        Returns
        -------
        ndarray of complex, shape (len(s), a, b)
            Coordinate per generalised force (m/N, rad/(N m)) between `left` and `right`.
        """
        s = np.asarray(s, dtype=complex)
        n = self.n
        left = np.eye(n) if left is None else np.asarray(left)
        right = np.eye(n) if right is None else np.asarray(right)
        A, B = self.state_space()
        lam, V = np.linalg.eig(A)
        if np.linalg.cond(V) > MODAL_CONDITION:
            H = np.linalg.inv(self.M * s[:, None, None] ** 2 + self.C * s[:, None, None]
                              + self.K)
            return left @ H @ right
        a, b = left @ V[:n], np.linalg.solve(V, B) @ right  # (a, 2n), (2n, b)
        residues = (a.T[:, :, None] * b[:, None, :]).reshape(2 * n, -1)
        # above the modes the terms cancel to ~ M^-1 / s^2: taken out exactly, the rest is
        # the sum with residues lambda^2 (the first two Markov parameters are 0 and M^-1)
        high = np.abs(s) > np.abs(lam).max()
        H = np.empty((s.size, residues.shape[1]), dtype=complex)
        with np.errstate(divide="ignore", invalid="ignore"):  # s on a pole: inf
            H[~high] = (1.0 / (s[~high, None] - lam)) @ residues
            inertia = (left @ B[n:] @ right).ravel()  # B's lower block is M^-1
            H[high] = (inertia + (1.0 / (s[high, None] - lam)) @ (residues * lam[:, None] ** 2)) \
                / s[high, None] ** 2
        return H.reshape(s.size, left.shape[0], right.shape[1])

    def state_space(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Continuous state matrices for the state ``[q, q']`` driven by generalised forces.

        Returns
        -------
        A : ndarray, shape (2n, 2n)
        B : ndarray, shape (2n, n)
        """
        n = self.n
        Minv = np.linalg.inv(self.M)
        A = np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ self.K, -Minv @ self.C]])
        B = np.vstack([np.zeros((n, n)), Minv])
        return A, B

    def eigenfrequencies_hz(self) -> NDArray[np.float64]:
        """Undamped normal-mode frequencies (Hz), ascending."""
        w2 = np.linalg.eigvals(np.linalg.solve(self.M, self.K)).real
        return np.sort(np.sqrt(np.clip(w2, 0, None)) / (2 * np.pi))
