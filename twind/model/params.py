"""Physical parameters of one small optic suspension (SOS), pygwinc style.

Sources: LIGO-T000134 (SOS analytical model, Table 1), and docs/model.md for the
C1 ETMX nominal numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from twind.model.violin import Wire

G_MPS2 = 9.81  # m/s^2, the value docs/model.md and the golden TFs use

ALL_DOFS = ("POS", "PIT", "YAW", "SIDE", "VERT", "ROLL")


@dataclass(frozen=True)
class SOSParams:
    """One small optic hung from a single steel wire loop.

    Attributes carry their unit in the name. ``b_m`` is the height of the wire break-off
    points above the centre of mass, ``R1_m`` half the wire separation at the clamps and
    ``R2_m`` half the separation at the optic (T000134 notation).
    """

    name: str = "ETMX"
    mass_kg: float = 0.243  # optic mass
    radius_m: float = 0.0375  # optic radius (3 inch optic)
    thickness_m: float = 0.025  # optic thickness
    I_pitch_kgm2: float = 9.80859375e-05  # m (r^2/4 + t^2/12)
    I_yaw_kgm2: float = 9.80859375e-05  # m (r^2/4 + t^2/12)
    I_roll_kgm2: float = 1.70859375e-04  # m r^2 / 2 + ... about the beam axis
    wire_length_m: float = 0.248  # l, clamp to break-off, vertical
    b_m: float = 0.0007  # break-off height above the centre of mass
    R1_m: float = 0.006877  # half wire separation at the clamps
    R2_m: float = 0.0375  # half wire separation at the optic
    vertical_stiffness_Npm: float = 2456.0  # both wire segments together, axial
    Q: dict[str, float] = field(
        default_factory=lambda: {d: (1000.0 if d in ("VERT", "ROLL") else 500.0) for d in ALL_DOFS}
    )  # free-swinging quality factors
    osem_lever_m: float = 0.019  # h: face OSEMs at (y, z) = (+-h, +-h)
    coil_N_per_ct: float = 2.5e-09  # each face coil
    side_coil_N_per_ct: float = 2.5e-09
    loop_delay_s: float = 1.0 / 16384  # one model cycle in the drive path
    sample_rate_hz: float = 16384.0  # CDS model rate
    g_mps2: float = G_MPS2
    wire: Wire = field(default_factory=Wire)  # its material and violin modes

    def updated(self, **changes: Any) -> SOSParams:
        """Return a copy with some parameters changed: ``Q`` may be a partial dict, and
        ``Q_POS`` etc. (the names ``twind fit`` reports) set one DOF's Q."""
        q = {k[2:]: changes.pop(k) for k in [k for k in changes if k.startswith("Q_")]}
        if q or "Q" in changes:
            changes["Q"] = {**self.Q, **changes.get("Q", {}), **q}
        return replace(self, **changes)

    def uncoupled_frequencies_hz(self) -> dict[str, float]:
        """Uncoupled resonance frequencies of T000134 (and VERT, ROLL from the wire stiffness)."""
        g, l, b, m = self.g_mps2, self.wire_length_m, self.b_m, self.mass_kg
        w2 = {
            "POS": g / l,
            "PIT": m * g * b * (l + b) / (self.I_pitch_kgm2 * l),
            "YAW": m * g * self.R1_m * self.R2_m / (self.I_yaw_kgm2 * l),
            "SIDE": g / (l + b),
            "VERT": self.vertical_stiffness_Npm / m,
            "ROLL": self.vertical_stiffness_Npm * self.R2_m**2 / self.I_roll_kgm2,
        }
        return {d: float(np.sqrt(v) / (2 * np.pi)) for d, v in w2.items()}

    def check(self) -> list[tuple[str, str]]:
        """Return ``(key, problem)`` pairs for physically impossible values (empty when fine)."""
        problems = []
        for key in ("mass_kg", "radius_m", "thickness_m", "I_pitch_kgm2", "I_yaw_kgm2",
                    "I_roll_kgm2", "wire_length_m", "R1_m", "R2_m", "vertical_stiffness_Npm",
                    "osem_lever_m", "sample_rate_hz"):
            if not getattr(self, key) > 0:
                problems.append((key, f"must be positive, got {getattr(self, key)}"))
        if not self.b_m > 0:
            problems.append(("b_m", f"must be positive (break-off above the centre of mass), got {self.b_m}"))
        if self.loop_delay_s < 0:
            problems.append(("loop_delay_s", f"must not be negative, got {self.loop_delay_s}"))
        for dof in ALL_DOFS:
            if not self.Q.get(dof, 0) > 0:
                problems.append((f"Q.{dof}", f"must be positive, got {self.Q.get(dof)}"))
        problems += [(f"wire.{key}", problem) for key, problem in self.wire.check()]
        return problems
