"""Where does a fitted model miss the data?  Residual power per TF element and band.

After :func:`twind.analysis.identification.fit.fit`, each element ``response/excited`` is cut into bands
(three a decade); the residual power of a band, ``U = sum |z|^2 / (2 s^2)`` with ``s`` the
fit's robust noise scale, is compared with its distribution when the model is right.  A
residual divided by a coherence-based sigma from ``n`` averages is not Gaussian: ``|z|^2 / 2``
follows F(2, 2n - 2), heavier-tailed than the exponential, and neighbouring Hann bins are
correlated (variance inflated by ``c = 1 + 2 sum rho_k^2``).  ``U`` is matched in mean and
variance to a scaled chi-square, and the p-values are corrected for the number of bands
looked at (Holm), so that a null measurement locates nothing however many places are examined.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from twind.analysis.estimation.tfset import TFSet
from twind.analysis.identification.data import FitData
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.result import FitResult
from twind.config import OpticConfig

ALPHA = 0.01
"""Family-wise false-alarm probability of the whole search."""
BANDS_PER_DECADE = 3


@dataclass(frozen=True)
class Located:
    """A band of one element where the residual is significant."""

    element: str  # "<response>/<excited>"
    band_hz: tuple[float, float]
    significance: float  # Gaussian-equivalent sigma of the corrected p-value
    p_value: float  # Holm-corrected
    excess: float  # residual power over its expectation

    def line(self, width: int = 9) -> str:
        """One line of a diagnosis's summary, the element's name padded to `width`."""
        return (f"  {self.element:{width}s} {self.band_hz[0]:7.3g}-{self.band_hz[1]:<7.3g} Hz  "
                f"{self.significance:5.1f} sigma, residual power x{self.excess:.3g}")

    def to_json(self) -> dict:
        """``{"element", "band_hz", "significance"}`` as ``twind diagnose`` prints it."""
        return {"element": self.element, "band_hz": list(self.band_hz),
                "significance": self.significance}


def locate(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, result: FitResult,
           alpha: float = ALPHA) -> list[Located]:
    """Bands of elements where `result`'s model misses `tfs`, most significant first.

    Parameters
    ----------
    tfs : TFSet or sequence of TFSet
        The data `result` was fitted to.
    cfg : OpticConfig
        The optic's configuration the fit started from.
    result : FitResult
    alpha : float
        Family-wise false-alarm probability.

    Returns
    -------
    list of Located
    """
    return significant(searched(tfs, cfg, result), alpha)


def searched(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, result: FitResult) -> list:
    """Every band :func:`locate` tests, with its uncorrected p-value (:func:`band_tests`)."""
    sets = [tfs] if isinstance(tfs, TFSet) else list(tfs)
    inflation = 1.0 + 2.0 * sum(r * r for r in result.bin_correlation)
    scale2 = result.noise_scale**2
    tests = []
    for t in sets:
        data = FitData.from_tfset(t, result.min_coherence).span()
        model = ClosedLoopModel.of(cfg, data, result.effect)
        pred = model.for_data(data)(result.as_dict())
        z = np.zeros(data.H.shape, dtype=complex)
        z[data.mask] = (data.H - pred)[data.mask] / data.sigma[data.mask]
        tests += band_tests(data, z, scale2, inflation)
    return tests


def significant(tests: list, alpha: float = ALPHA) -> list[Located]:
    """The bands of :func:`band_tests` whose p-values, Holm-corrected over all of them, are
    below `alpha`, most significant first."""
    if not tests:
        return []
    p = np.array([tt[2] for tt in tests])
    corrected = _holm(p)
    out = [Located(el, band, gaussian_sigma(pc), float(pc), excess)
           for (el, band, _, excess), pc in zip(tests, corrected, strict=True) if pc < alpha]
    return sorted(out, key=lambda x: -x.significance)


def _null_moments(averages: int) -> tuple[float, float]:
    """Mean and variance of one bin's ``|z|^2 / (2 s^2)`` when the model is right.

    ``|z|^2 / 2`` is F(2, 2n - 2) for ``n`` averages; the robust scale puts its median at
    ln 2, the exponential's.
    """
    d2 = 2 * max(averages, 3) - 2
    f = stats.f(2, d2)
    k = math.log(2) / f.median()
    return f.mean() * k, f.var() * k * k


def band_tests(data: FitData, z: np.ndarray, scale2: float, inflation: float) -> list:
    """Each element's residual power band by band (:data:`BANDS_PER_DECADE`) against its
    distribution when the model is right.

    Parameters
    ----------
    data : FitData
        The bins fitted (their mask, frequencies and names).
    z : ndarray of complex, shape of ``data.H``
        Whitened residuals (zero where unused).
    scale2 : float
        The residuals' robust scale, squared.
    inflation : float
        ``1 + 2 sum rho_k^2`` of the bins' correlation.

    Returns
    -------
    list of (element, band, p-value, excess)
        Uncorrected p-values (:func:`significant` corrects them).
    """
    mu, var = _null_moments(data.averages)
    f = data.frequency_hz
    used = f[data.mask.any(axis=(1, 2))]
    if used.size == 0:
        return []
    edges = band_edges(float(used.min()), float(used.max()))
    out = []
    for i, r in enumerate(data.responses):
        for j, e in enumerate(data.excited):
            for a, b in zip(edges[:-1], edges[1:], strict=True):
                k = data.mask[:, i, j] & (f >= a) & (f < b)
                n = int(k.sum())
                if n < 4:
                    continue
                power = float(np.sum(np.abs(z[k, i, j]) ** 2)) / (2 * scale2)
                # a * chi2(d) with the band's mean n mu and variance n var c
                scale = var * inflation / (2 * mu)
                dof = 2 * n * mu * mu / (var * inflation)
                p = float(stats.chi2.sf(power / scale, dof))
                out.append((f"{r}/{e}", (float(a), float(b)), p, power / (n * mu)))
    return out


def smallest_corrected(tests: list) -> float:
    """The smallest Holm-corrected p-value of `tests` (1 when there are none): how near
    the search came to locating a band."""
    return min(1.0, min((t[2] for t in tests), default=1.0) * max(len(tests), 1))


def band_edges(f_min: float, f_max: float, per_decade: int = BANDS_PER_DECADE
               ) -> NDArray[np.float64]:
    """Edges of the bands searched, `per_decade` to a decade on the decades' own grid (1,
    2.15, 4.64, 10 ...), from below `f_min` to above `f_max` (Hz)."""
    lo, hi = math.log10(f_min), math.log10(f_max)
    return 10 ** np.arange(math.floor(lo * per_decade) / per_decade, hi + 1.0 / per_decade,
                           1.0 / per_decade)


def _holm(p: np.ndarray) -> np.ndarray:
    """Holm-Bonferroni adjusted p-values."""
    order = np.argsort(p)
    m = p.size
    adjusted = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adjusted[i] = running
    return adjusted


def gaussian_sigma(p: float) -> float:
    """Two-sided Gaussian-equivalent significance of a p-value."""
    return float(stats.norm.isf(max(p, 1e-300) / 2))
