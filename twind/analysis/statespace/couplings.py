"""Couplings no state-space model has, screened on a fit's residuals: a readback that also
reads another, a drive's flat electronic crosstalk into a readback, a drive that also drives
another input of its stage. Each is linear in its parameters, so its best drop in chi^2 is a
projection of the whitened residuals on its columns, made without a fit."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from twind.analysis.statespace.fit import PlantFit
from twind.analysis.statespace.model import Effect, PlantModel
from twind.analysis.statespace.search import Residuals

MIN_ELEMENT_BINS = 10
"""Coherent bins an element needs for a coupling or a crosstalk to be claimed in it."""
REACHES = 1e-3
"""An input reaches a readback, for a drive that also drives it, where the model's response
there is at least this share of the input's largest at any readback (KAGRA's models
normalise each sensor to its own DOF, so the responses compare): a readback it reaches
more weakly (a symmetry of the model broken by 1e-9 or less) would need a share of it of
1e8 or more, a number, not a coupling."""


COUPLINGS = ("cross_coupling", "drive_coupling", "drive_crosstalk")
"""The families of couplings no model has, each a linear change of the measurement."""


def screen(res: Residuals, model: PlantModel, base: PlantFit, unit: float
           ) -> dict[str, list[tuple[Effect, float, dict[str, float]]]]:
    """The couplings no model has (:data:`COUPLINGS`), screened on the residuals of `base`:
    each member with its drop in chi^2 (in `unit`) and where its fit starts.

    Parameters
    ----------
    res : Residuals
        `base`'s whitened residuals.
    model : PlantModel
    base : PlantFit
        The fit whose residuals are screened; its couplings are not tried again.
    unit : float
        The drop one fitted parameter makes in pure noise.

    Returns
    -------
    dict
        Per family, ``(effect, drop, start)`` of each member.
    """
    out: dict[str, list[tuple[Effect, float, dict[str, float]]]] = {f: [] for f in COUPLINGS}
    for effect, columns in _columns(res, model, base):
        fitted = [(name, *_project(res.z, pieces)) for name, pieces in columns()]
        if not fitted:
            continue
        out[effect.family].append((effect, sum(d for _, d, _ in fitted) / unit,
                                   {name: coef for name, _, coef in fitted}))
    return out


def _project(z: NDArray[np.complex128], pieces: Sequence[tuple]) -> tuple[float, float]:
    """The drop in chi^2 a real multiple of a whitened column makes in residuals `z` at best,
    and the multiple; the column given by its pieces ``(readback, drive, values)``."""
    proj = sum(float(np.sum((np.conj(z[:, r, j]) * v).real)) for r, j, v in pieces)
    norm = sum(float(np.sum(np.abs(v) ** 2)) for _, _, v in pieces)
    return (proj * proj / norm, proj / norm) if norm > 0 else (0.0, 0.0)


def _columns(res: Residuals, model: PlantModel, base: PlantFit) -> list[tuple]:
    """Each coupling not yet chosen, with a function giving its whitened columns, one per
    parameter, each by its pieces ``(readback, drive, values)``: a readback that also reads
    another (calibrated) one, a drive's flat crosstalk into a readback, a drive that also
    drives another input of its stage (one factor per readback that input reaches,
    :data:`REACHES`); only in elements of at least :data:`MIN_ELEMENT_BINS` coherent
    bins."""
    nr, nd = res.z.shape[1:]
    counted = res.data.mask.sum(axis=0) >= MIN_ELEMENT_BINS  # (readbacks, drives)
    taken = {e.key() for e, _ in base.effects}
    lag = model.lag(base.nuisance)
    X = model.extra_response(base.effects) if model.extra is not None else None
    w, p, G = res.whitener, res.predicted, res.G
    out = []
    for r in np.flatnonzero(counted.any(axis=1)):
        for r2 in (i for i in range(nr) if f"g_{i}" in base.names and i != r):
            out.append((Effect("cross_coupling", (int(r), r2)), lambda r=r, r2=r2: [
                ("epsilon", [(r, j, p[:, r2, j] * w[:, r, j]) for j in range(nd)])]))
    for r, j in zip(*np.nonzero(counted), strict=True):
        out.append((Effect("drive_crosstalk", (int(r), int(j))), lambda r=r, j=j: [
            ("c", [(r, j, lag * w[:, r, j])])]))
    own = np.abs(X).max(axis=0) if X is not None else None  # (readbacks, extra inputs)
    for j in range(nd if X is not None else 0):
        for u in range(X.shape[2]):
            seen = own[:, u] >= REACHES * own[:, u].max()
            out.append((Effect("drive_coupling", (j, u)), lambda j=j, u=u, seen=seen: [
                (f"e{r}", [(r, j, G[:, r, j] * X[:, r, u])])
                for r in np.flatnonzero(counted[:, j] & seen)]))
    return [(e, columns) for e, columns in out if e.key() not in taken]
