"""Compare the geometric rigid-body model with the analytical T000134 model (physics only).

Both models are reduced to what the damping loop sees: normal-mode frequencies labelled by the
coordinate that dominates each mode, and the force-to-displacement admittance over POS, PIT,
YAW and SIDE. Only magnitudes are compared: the analytical POS<->PIT off-diagonal has the
opposite sign (T000134 pitch convention, see :mod:`twind.model.geometric`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from twind.model.analytical import analytical_mechanics
from twind.model.geometric import WireGeometry, geometric_mechanics
from twind.model.mechanics import Mechanics
from twind.model.params import SOSParams

if TYPE_CHECKING:  # matplotlib is imported only when plotting
    from matplotlib.axes import Axes

DOFS: tuple[str, ...] = ("POS", "PIT", "YAW", "SIDE")
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


def plot_comparison(cmp: ModelComparison, path: str | Path) -> Path:
    """Write a 4x4 Bode-magnitude matrix of both models' admittances to a PNG.

    Parameters
    ----------
    cmp : ModelComparison
    path : str or Path
        Output PNG file.

    Returns
    -------
    Path
        The file written.
    """
    # Agg canvas directly: no pyplot global state, no display needed
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(14, 11))
    FigureCanvasAgg(fig)
    axes = fig.subplots(4, 4, sharex=True)
    zero = cmp.structurally_zero()
    worst = cmp.max_relative_difference()
    for i, row in enumerate(cmp.dofs):
        for j, col in enumerate(cmp.dofs):
            _panel(axes[i, j], cmp, i, j, zero[i, j], worst[i, j])
            axes[i, j].set_title(f"{row} / {col}", fontsize=9)
        axes[3, i].set_xlabel("frequency (Hz)")
    axes[0, 0].legend(fontsize=8, loc="lower left")
    fig.suptitle("Admittance |displacement / generalised force|: analytical (T000134) vs geometric "
                 "rigid body\n(max relative magnitude difference excluding ±10 % around resonances;"
                 " POS/PIT off-diagonal differs in sign only)", fontsize=10)
    # fixed margins: constrained layout costs seconds on a 4x4 grid
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.05, top=0.91, wspace=0.25, hspace=0.3)
    out = Path(path)
    fig.savefig(out, dpi=100)
    return out


def _panel(ax: "Axes", cmp: ModelComparison, i: int, j: int, zero: bool, worst: float) -> None:
    ax.set_xscale("log")
    ax.set_xlim(0.1, 10)
    if zero:
        ax.text(0.5, 0.5, "0 in both models", ha="center", va="center", transform=ax.transAxes,
                color="0.5")
        ax.set_yticks([])
        return
    ax.loglog(cmp.f_hz, np.abs(cmp.admittance_analytical[:, i, j]), "C0-", lw=1.2, label="analytical")
    ax.loglog(cmp.f_hz, np.abs(cmp.admittance_geometric[:, i, j]), "C1--", lw=1.2, label="geometric")
    ax.text(0.97, 0.95, f"max |Δ| = {100 * worst:.2g} %", ha="right", va="top",
            transform=ax.transAxes, fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
