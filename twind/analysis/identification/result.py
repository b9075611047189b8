"""A fit's result: values, sigmas, what the data cannot fix and the combinations it does."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from twind.analysis.identification.data import MIN_COHERENCE
from twind.analysis.identification.params import param_label
from twind.model.effects import effect_scale


NULL_COMPONENT = 0.05


# ------------------------------------------------------------------------------ result
@dataclass
class FitResult:
    """Fitted parameters with calibrated uncertainties.

    Attributes
    ----------
    names : list of str
    values : ndarray
        Fitted values (nominal for unidentifiable ones).
    sigma : ndarray
        One-sigma uncertainties; ``nan`` where unidentifiable.
    covariance : ndarray
        Of ``log(value)``; rows and columns of unidentifiable parameters are ``nan``.
    unidentifiable : list of str
        Parameters or combinations (``"coil_N_per_ct/osem_lever_m"``) the data cannot fix.
    determined : dict
        For each unidentifiable pair, the combination that is determined, ``{value, sigma}``.
    chi2, nu : float, int
        Weighted residual sum of squares and degrees of freedom.
    noise_scale : float
        How much the residuals' scatter (median-based) exceeds the coherence-based errors.
    bin_correlation : list of float
        Correlation of residuals 1, 2, 3 bins apart.
    null, determined_covariance : ndarray
        The unidentifiable coordinate directions (columns) and :attr:`covariance` before
        their rows are blanked, for :meth:`combination_covariance`.
    """

    optic: str
    names: list[str]
    values: NDArray[np.float64]
    sigma: NDArray[np.float64]
    covariance: NDArray[np.float64]
    unidentifiable: list[str]
    determined: dict[str, dict[str, float]]
    chi2: float
    nu: int
    noise_scale: float
    bin_correlation: list[float]
    bins: int
    nominal: NDArray[np.float64] = field(repr=False)
    effect: str | None = None
    min_coherence: float = MIN_COHERENCE  # of the bins fitted (FitData.from_tfset)
    null: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 0)), repr=False)
    determined_covariance: NDArray[np.float64] = field(
        default_factory=lambda: np.zeros((0, 0)), repr=False)

    @property
    def bic(self) -> float:
        """``chi2 + k ln(n)`` with ``k`` = :attr:`rank` over ``n`` real residuals."""
        return self.chi2 + self.rank * math.log(max(2 * self.bins, 1))

    @property
    def rank(self) -> int:
        """Parameter directions the data determined (a coil imbalance's four gains count
        two: their common mode is the coil strength's, their butterfly moves nothing)."""
        return 2 * self.bins - self.nu

    @property
    def chi2_nu(self) -> float:
        """Reduced chi-square of the fit."""
        return self.chi2 / max(self.nu, 1)

    def combination_covariance(self, combos: Sequence[Mapping[str, float]]
                               ) -> NDArray[np.float64]:
        """Covariance of the combinations ``sum w_n p_n`` over an effect's parameters (or
        ``sum w_n log p_n`` over nominal ones), one per mapping ``{name: w_n}`` of `combos`.

        Rows and columns are ``nan`` for a combination that leans on a direction the data
        cannot determine: an imbalance's pitch-like part of four face gains has a sigma, no
        single gain has.
        """
        scale = effect_scale(self.effect) if self.effect else {}
        W = np.array([[c.get(n, 0.0) * scale.get(n, 1.0) for n in self.names] for c in combos])
        cov = W @ self.determined_covariance @ W.T
        if self.null.size:
            leans = (np.linalg.norm(W @ self.null, axis=1)
                     > NULL_COMPONENT * np.linalg.norm(W, axis=1))
            cov[leans, :] = np.nan
            cov[:, leans] = np.nan
        return cov

    def as_dict(self) -> dict[str, float]:
        """``{name: value}``."""
        return dict(zip(self.names, self.values.tolist(), strict=True))

    def identified(self) -> dict[str, float]:
        """``{name: value}`` of the parameters with a finite sigma (what to pass on)."""
        return {n: float(v) for n, v, s in zip(self.names, self.values, self.sigma,
                                               strict=True) if math.isfinite(s)}

    def to_json(self) -> dict:
        """The ``twind fit --json`` object (unidentifiable sigmas are null)."""
        params = {n: {"value": float(v), "sigma": None if math.isnan(s) else float(s),
                      "start": float(p0), "label": param_label(n)}
                  for n, v, s, p0 in zip(self.names, self.values, self.sigma, self.nominal,
                                         strict=True)}
        return {"optic": self.optic, "effect": self.effect, "params": params,
                "unidentifiable": self.unidentifiable,
                "determined": self.determined, "chi2_nu": self.chi2_nu, "nu": self.nu,
                "noise_scale": self.noise_scale, "bin_correlation": self.bin_correlation,
                "bins": self.bins, "min_coherence": self.min_coherence}

    def pulls(self, truth: Mapping[str, float]) -> str:
        """``name (fitted - truth) / sigma`` of the identified parameters `truth` gives."""
        return ", ".join(f"{n} {(v - truth[n]) / s:+.2f}" for n, v, s in
                         zip(self.names, self.values, self.sigma, strict=True)
                         if n in truth and math.isfinite(s))

    def lines(self) -> list[str]:
        """A human-readable table."""
        out = [f"{self.optic}: {self.bins} bins (coherence >= {self.min_coherence:g}), "
               f"chi2/nu = {self.chi2_nu:.3f} "
               f"(noise scale {self.noise_scale:.2f}, bin correlation "
               f"{', '.join(f'{c:+.2f}' for c in self.bin_correlation)})"]
        for n, v, s, p0 in zip(self.names, self.values, self.sigma, self.nominal, strict=True):
            if math.isnan(s):  # held at its start: no fitted value to show
                out.append(f"  {n:15s} {'':12s} {'unidentifiable, held':26s} start {p0:.6g}")
            else:
                out.append(f"  {n:15s} {v:12.6g} {f'+- {s:.4g} ({100 * s / v:.2g} %)':26s} "
                           f"start {p0:.6g}")
        for combo, d in self.determined.items():
            out.append(f"  determined: {combo} = {d['value']:.6g} +- {d['sigma']:.3g}")
        if self.unidentifiable:
            out.append(f"  unidentifiable: {', '.join(self.unidentifiable)}")
        return out


def name_null(names: list[str], null: NDArray, values: NDArray, cov: NDArray,
               log: NDArray[np.bool_]) -> tuple[list[str], dict[str, dict[str, float]]]:
    """Name each unidentifiable direction; for a pair, also the product that is determined.

    Parameters
    ----------
    names : list of str
        The fitted parameters.
    null : ndarray, shape (len(names), k)
        Orthonormal basis of the unidentifiable directions in the fit's coordinates.
    values : ndarray
        The fitted values, by `names`.
    cov : ndarray, shape (len(names), len(names))
        Covariance of the fit's coordinates (log of a physical parameter, scaled offset of
        an effect's).
    log : ndarray of bool
        Which coordinates are logarithms (physical parameters).

    Returns
    -------
    unidentifiable : list of str
        One name per direction: a product of powers (``a*b/c^0.5``) or, with an effect's
        parameter in it, a sum (``a - b``).
    determined : dict of str to dict
        For each pair of physical parameters, the product the data fix: its ``value`` and
        ``sigma``.
    """
    unident, determined = [], {}
    for v in null.T:
        involved = list(np.flatnonzero(np.abs(v) > NULL_COMPONENT * np.abs(v).max()))
        v = v / v[involved[0]]  # the first parameter, to the power one, leads the name
        if not log[involved].all():  # an effect's parameters enter linearly: a sum
            unident.append(_linear([names[i] for i in involved], v[involved]))
            continue
        unident.append(_monomial([names[i] for i in involved], v[involved]))
        if len(involved) == 2:
            # the direction orthogonal to v within the pair is what the data fix
            i, j = involved
            u = np.zeros(len(names))
            u[i], u[j] = v[j], -v[i]
            u /= u[i]
            var = float(u @ cov @ u)  # u is orthogonal to the null direction
            # the pair's own values: another parameter may be negative (an effect's)
            value = float(np.exp(u[[i, j]] @ np.log(values[[i, j]])))
            determined[_monomial([names[i], names[j]], u[[i, j]])] = {
                "value": value, "sigma": value * math.sqrt(max(var, 0.0))}
    return unident, determined


def _linear(names: list[str], coefs: NDArray) -> str:
    """``a - b + 0.5*c``-style name of ``sum coef_i name_i``."""
    text = ""
    for n, c in zip(names, coefs, strict=True):
        size = "" if abs(abs(c) - 1) < 0.05 else f"{abs(c):.2g}*"
        text += f" {'-' if c < 0 else '+'} {size}{n}"
    return text[3:] if text.startswith(" + ") else text.strip()


def _monomial(names: list[str], powers: NDArray) -> str:
    """``a*b/c^0.5``-style name of ``prod name_i^power_i``."""
    def term(n: str, p: float) -> str:
        p = abs(p)
        return n if abs(p - 1) < 0.05 else f"{n}^{p:.2g}"

    num = [term(n, p) for n, p in zip(names, powers, strict=True) if p > 0]
    den = [term(n, p) for n, p in zip(names, powers, strict=True) if p < 0]
    text = "*".join(num) or "1"
    return text + ("/" + "/".join(den) if den else "")
