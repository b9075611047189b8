"""One optic's damping loop: the plant the loop sees and a filter module per DOF.

Closed-loop test-point responses follow docs/model.md: ``IN2/EXC = (I - P K)^-1``,
``IN1/EXC = IN2/EXC - I``, ``OUT/EXC = K IN2/EXC``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.loop.filtermodule import FilterModule
from twind.model.plant import Plant


@dataclass
class DampingLoop:
    """Plant plus the four damping filter modules of one optic.

    Attributes
    ----------
    name : str
        Optic name, e.g. ``"ETMX"``.
    plant : Plant
    modules : dict of str to FilterModule
        Keyed by DOF: POS, PIT, YAW, SIDE.
    """

    name: str
    plant: Plant
    modules: dict[str, FilterModule]

    def controller(self, f_hz: NDArray[np.float64]) -> NDArray[np.complex128]:
        """Diagonal of K (IN2 -> OUT), shape (len(f), 4)."""
        return np.stack([self.modules[d].response(f_hz) for d in DOFS], axis=1)

    def responses(self, f_hz: NDArray[np.float64]) -> dict[str, NDArray[np.complex128]]:
        """Plant, controller and closed-loop test-point responses at `f_hz`.

        Returns
        -------
        dict
            ``plant_IN1_per_OUT`` (f, 4, 4), ``controller_diag`` (f, 4),
            ``closed_loop_IN1_per_EXC``, ``closed_loop_IN2_per_EXC``,
            ``closed_loop_OUT_per_EXC`` (f, 4, 4), and ``closed_loop_IN1_per_LSC``: IN1 per
            excitation past the damping filters (added to OUT, :data:`twind.channels.DRIVE_POINTS`),
            ``(I - P K)^-1 P``; rows and columns POS, PIT, YAW, SIDE.
        """
        P = self.plant.response(f_hz)
        k = self.controller(f_hz)
        # LAPACK's inverse, as the golden responses were made (IN1 = IN2 - I carries its
        # rounding where IN1 is small); the fits take :func:`sensitivity`
        in2 = np.linalg.inv(np.eye(4) - P * k[:, None, :])
        return {
            "plant_IN1_per_OUT": P,
            "controller_diag": k,
            "closed_loop_IN1_per_EXC": in2 - np.eye(4),
            "closed_loop_IN2_per_EXC": in2,
            "closed_loop_OUT_per_EXC": k[:, :, None] * in2,
            "closed_loop_IN1_per_LSC": in2 @ P,
        }


def sensitivity(P: NDArray[np.complex128], k: NDArray[np.complex128]) -> NDArray[np.complex128]:
    """``IN2/EXC = (I - P K)^-1`` at each frequency, for a diagonal controller.

    Parameters
    ----------
    P : ndarray, shape (n, m, m)
        The plant (``IN1/OUT``) at n frequencies.
    k : ndarray, shape (n, m)
        The diagonal of K (``OUT/IN2``) at the same frequencies.

    Returns
    -------
    ndarray, shape (n, m, m)

    Raises
    ------
    numpy.linalg.LinAlgError
        Where ``I - P K`` is exactly singular.

    Notes
    -----
    The fits evaluate this at every bin of every trial, so it is one compiled pass
    (Gauss-Jordan with partial pivoting per frequency) rather than a batched LAPACK call,
    whose per-matrix overhead dominates at 4 x 4.
    """
    P = np.ascontiguousarray(P, dtype=np.complex128)
    k = np.ascontiguousarray(k, dtype=np.complex128)
    if P.ndim != 3 or P.shape[1] != P.shape[2] or k.shape != P.shape[:2]:
        msg = f"plant {P.shape} and controller diagonal {k.shape} do not match"
        raise ValueError(msg)
    out = np.empty_like(P)
    try:
        _sensitivity(P, k, out)
    except ZeroDivisionError:
        msg = "I - P K is singular at some frequency: the loop has a pole there"
        raise np.linalg.LinAlgError(msg) from None
    return out


@nb.njit(cache=True, nogil=True)
def _sensitivity(P: NDArray, k: NDArray, out: NDArray) -> None:  # pragma: no cover - numba
    n, m = k.shape
    a = np.empty((m, 2 * m), dtype=np.complex128)  # [I - P K | I], reduced to [I | S]
    for f in range(n):
        for i in range(m):
            for j in range(m):
                a[i, j] = -P[f, i, j] * k[f, j]
                a[i, m + j] = 0.0
            a[i, i] += 1.0
            a[i, m + i] = 1.0
        for c in range(m):
            piv, best = c, a[c, c].real ** 2 + a[c, c].imag ** 2
            for r in range(c + 1, m):
                v = a[r, c].real ** 2 + a[r, c].imag ** 2
                if v > best:
                    piv, best = r, v
            if piv != c:
                for j in range(c, 2 * m):
                    t = a[c, j]
                    a[c, j] = a[piv, j]
                    a[piv, j] = t
            inv = 1.0 / a[c, c]
            for j in range(c, 2 * m):
                a[c, j] *= inv
            for r in range(m):
                if r != c:
                    g = a[r, c]
                    for j in range(c, 2 * m):
                        a[r, j] -= g * a[c, j]
        for i in range(m):
            for j in range(m):
                out[f, i, j] = a[i, m + j]
