"""A fit's model on its measurement's grid, beside the measurement: what a fit figure, a
report or a Rerun file draws, computed once here so that drawing needs no model."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind.analysis.estimation.tfset import TFSet
from twind.analysis.identification.data import FitData
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.result import FitResult
from twind.config import OpticConfig


@dataclass(frozen=True)
class FitCurves:
    """Measured ``IN1/EXC`` and the models of a fit, over the span of the bins it used.

    Attributes
    ----------
    optic : str
    model : str
        The fitted model in words: ``"nominal"`` or ``"nominal + <effect>"``.
    chi2_nu : float
        The fit's reduced chi-square.
    frequency_hz : ndarray, shape (nf,)
    responses, excited : list of str
        The DOFs read (rows) and excited (columns).
    H, sigma : ndarray, shape (nf, nr, ne)
        Measured ``IN1/EXC`` and the standard error of its real and imaginary parts.
    used : ndarray of bool, shape (nf, nr, ne)
        The bins the fit used.
    coherence : ndarray, shape (nf, nr, ne)
        Of each measured element.
    curves : dict of str to ndarray, shape (nf, nr, ne)
        The model the fit started from (or the baseline fit), then the fitted model, by label.
    caption : str
        The measurement's channels, GPS span and estimate (:meth:`TFSet.caption`).
    """

    optic: str
    model: str
    chi2_nu: float
    frequency_hz: NDArray[np.float64]
    responses: list[str]
    excited: list[str]
    H: NDArray[np.complex128]
    sigma: NDArray[np.float64]
    used: NDArray[np.bool_]
    coherence: NDArray[np.float64]
    curves: dict[str, NDArray[np.complex128]]
    caption: str

    @property
    def fitted(self) -> NDArray[np.complex128]:
        """The fitted model's curve (the last of :attr:`curves`)."""
        return list(self.curves.values())[-1]


def fit_curves(tfs: TFSet, cfg: OpticConfig, result: FitResult,
               baseline: FitResult | None = None) -> FitCurves:
    """`result`'s model and the one it started from on `tfs`'s grid, over the span of the
    bins the fit used: a recording reaches Nyquist, its excitation does not.

    Parameters
    ----------
    tfs : TFSet
        The measurement fitted.
    cfg : OpticConfig
        The configuration the fit started from.
    result : FitResult
    baseline : FitResult, optional
        Drawn in place of the configuration the fit started from: the nominal model
        refitted, beside the nominal model with an effect.

    Returns
    -------
    FitCurves
    """
    used = FitData.from_tfset(tfs, result.min_coherence).mask  # FitError if no bin is used
    f_used = tfs.frequency_hz[used.any(axis=(1, 2))]
    used = used[(tfs.frequency_hz >= f_used[0]) & (tfs.frequency_hz <= f_used[-1])]
    tfs = tfs.band(f_used[0], f_used[-1])
    data = FitData.from_tfset(tfs, min_coherence=0.0)
    used &= data.mask  # the band's edges: a neighbour-averaged coherence cut short there

    def curve(fitted: FitResult | None) -> NDArray[np.complex128]:
        model = ClosedLoopModel.of(cfg, data, (fitted or result).effect).for_data(data)
        return model(fitted.as_dict() if fitted else {})

    model = f"nominal + {result.effect}" if result.effect else "nominal"
    start = "nominal, refitted" if baseline else "configuration (the fit's start)"
    return FitCurves(result.optic, model, result.chi2_nu, data.frequency_hz,
                     list(data.responses), list(data.excited), data.H, data.sigma, used,
                     tfs.coherence["IN1"],  # FitData keeps tfs's rows and columns
                     {start: curve(baseline), f"{model}, fitted": curve(result)}, tfs.caption())
