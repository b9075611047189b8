"""One optic's damping loop: the plant the loop sees and a filter module per DOF.

Closed-loop test-point responses follow MODEL.md: ``IN2/EXC = (I - P K)^-1``,
``IN1/EXC = IN2/EXC - I``, ``OUT/EXC = K IN2/EXC``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.loop.filtermodule import FilterModule
from twind.loop.plant import Plant


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
            ``closed_loop_OUT_per_EXC`` (f, 4, 4); rows and columns POS, PIT, YAW, SIDE.
        """
        P = self.plant.response(f_hz)
        k = self.controller(f_hz)
        K = k[:, :, None] * np.eye(4)
        in2 = np.linalg.inv(np.eye(4) - P @ K)
        return {
            "plant_IN1_per_OUT": P,
            "controller_diag": k,
            "closed_loop_IN1_per_EXC": in2 - np.eye(4),
            "closed_loop_IN2_per_EXC": in2,
            "closed_loop_OUT_per_EXC": K @ in2,
        }
