"""Compare the geometric rigid-body model with the analytical T000134 model (physics only).

Both models are reduced to what the damping loop sees: normal-mode frequencies labelled by the
coordinate that dominates each mode, and the force-to-displacement admittance over POS, PIT,
YAW and SIDE. Only magnitudes are compared: the analytical POS<->PIT off-diagonal has the
opposite sign (T000134 pitch convention, see :mod:`twind.model.geometric`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from twind import DOFS
from twind.model.analytical import analytical_mechanics
from twind.model.geometric import WireGeometry, geometric_mechanics
from twind.model.mechanics import Mechanics
from twind.model.params import SOSParams

RESONANCE_EXCLUSION = 0.10  # fractional band around each resonance left out of comparisons
_ZERO = 1e-12  # relative to the largest diagonal admittance: below is structurally zero


@dataclass(frozen=True)
class ModelComparison:
    """Eigenfrequencies and admittances of the analytical and geometric models.

    Attributes
    ----------
    f_hz : ndarray, shape (nf,)
        Frequencies of the admittances.
    eigen_analytical_hz : dict
        Normal-mode frequency per dominant coordinate, POS, PIT, YAW, SIDE.
    eigen_geometric_hz : dict
        The same for the geometric model, also VERT and ROLL.
    admittance_analytical, admittance_geometric : ndarray, shape (nf, 4, 4)
        Displacement per generalised force (m/N, rad/(N m), ...), rows and columns :data:`DOFS`.
    dofs : tuple of str
        Row and column order of the admittances.
    """

    f_hz: NDArray[np.float64]
    eigen_analytical_hz: dict[str, float]
    eigen_geometric_hz: dict[str, float]
    admittance_analytical: NDArray[np.complex128]
    admittance_geometric: NDArray[np.complex128]
    dofs: tuple[str, ...] = DOFS

    def eigen_difference_pct(self) -> dict[str, float]:
        """Geometric minus analytical eigenfrequency, in % of the analytical, per coordinate."""
        return {d: 100 * (self.eigen_geometric_hz[d] / f - 1)
                for d, f in self.eigen_analytical_hz.items()}

    def structurally_zero(self) -> NDArray[np.bool_]:
        """(4, 4) mask of elements that vanish in both models at every frequency."""
        scale = max(np.abs(np.diagonal(Y, axis1=1, axis2=2)).max()
                    for Y in (self.admittance_analytical, self.admittance_geometric))
        small = [np.all(np.abs(Y) <= _ZERO * scale, axis=0)
                 for Y in (self.admittance_analytical, self.admittance_geometric)]
        return small[0] & small[1]

    def off_resonance(self, exclusion: float = RESONANCE_EXCLUSION) -> NDArray[np.bool_]:
        """(nf,) mask of frequencies farther than `exclusion` (fraction) from every resonance."""
        poles = [*self.eigen_analytical_hz.values(), *self.eigen_geometric_hz.values()]
        f = self.f_hz[:, None]
        return np.all(np.abs(f / np.array(poles)[None, :] - 1) > exclusion, axis=1)

    def relative_difference(self) -> NDArray[np.float64]:
        """``|Y_geo| / |Y_ana| - 1`` per frequency and element, NaN where structurally zero."""
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.abs(self.admittance_geometric) / np.abs(self.admittance_analytical) - 1
        rel[:, self.structurally_zero()] = np.nan
        return rel

    def max_relative_difference(self, exclusion: float = RESONANCE_EXCLUSION) -> NDArray[np.float64]:
        """(4, 4) largest ``| |Y_geo|/|Y_ana| - 1 |`` away from resonances (NaN where zero)."""
        rel = np.abs(self.relative_difference()[self.off_resonance(exclusion)])
        out = np.full(rel.shape[1:], np.nan)
        live = ~self.structurally_zero()
        out[live] = np.max(rel[:, live], axis=0)
        return out


def eigenfrequencies_by_dof(mech: Mechanics) -> dict[str, float]:
    """Undamped normal-mode frequencies (Hz), each labelled by its dominant coordinate.

    A mode's participation in coordinate ``j`` is the mass-weighted ``v_j (M v)_j`` of its
    mass-normalised shape (the participations of one mode sum to 1); modes and coordinates are
    paired one-to-one so that the total participation is largest, which reduces to "largest
    participation" whenever that is unambiguous.

    Parameters
    ----------
    mech : Mechanics

    Returns
    -------
    dict
        Coordinate name -> frequency (Hz).
    """
    M = 0.5 * (mech.M + mech.M.T)
    K = 0.5 * (mech.K + mech.K.T)
    w2, V = scipy.linalg.eigh(K, M)
    participation = np.abs(V * (M @ V))  # (coordinate, mode)
    rows, cols = linear_sum_assignment(-participation)
    freq = np.sqrt(np.clip(w2, 0.0, None)) / (2 * np.pi)
    return {mech.dofs[r]: float(freq[c]) for r, c in zip(rows, cols)}


def compare_models(
    p: SOSParams, f_hz: ArrayLike, *, geometry: WireGeometry | None = None
) -> ModelComparison:
    """Eigenfrequencies and POS/PIT/YAW/SIDE admittances of both models for parameters `p`.

    Parameters
    ----------
    p : SOSParams
        Suspension parameters (both models).
    f_hz : array_like
        Frequencies (Hz) of the admittances.
    geometry : WireGeometry, optional
        Geometric model to compare; default :meth:`WireGeometry.from_params` of `p` (ideal).

    Returns
    -------
    ModelComparison
    """
    f = np.asarray(f_hz, dtype=float)
    s = 2j * np.pi * f
    ana = analytical_mechanics(p)
    geo = geometric_mechanics(geometry if geometry is not None else WireGeometry.from_params(p))
    return ModelComparison(
        f_hz=f,
        eigen_analytical_hz=eigenfrequencies_by_dof(ana),
        eigen_geometric_hz=eigenfrequencies_by_dof(geo),
        admittance_analytical=_restricted_admittance(ana, s),
        admittance_geometric=_restricted_admittance(geo, s),
    )


def _restricted_admittance(mech: Mechanics, s: NDArray[np.complex128]) -> NDArray[np.complex128]:
    # invert the full system first: VERT/ROLL of the geometric model still shape SIDE
    idx = [mech.index(d) for d in DOFS]
    return mech.admittance(s)[np.ix_(np.arange(len(s)), idx, idx)]
