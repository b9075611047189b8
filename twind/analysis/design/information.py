"""Information-mode excitation design (Pintelon & Schoukens, *System Identification*, ch. 5):
a multisine whose power allocation over tones maximises det(Fisher) of chosen parameters at
a fixed RMS per excited DOF (D-optimal design).

A tone of power ``p`` (``amp^2 / 2``) at frequency ``f`` held for ``T`` seconds measures
``IN1_r/EXC_d`` with complex variance ``S_r(f) / (p T)``, ``S_r`` the IN1 noise PSD of response
``r``.  The Fisher information is therefore linear in the tone powers,
``F = sum_k p_k F_k`` with ``F_k = 2 T sum_r Re(g_rk^H g_rk) / S_r(f_k)`` and ``g = dT/dlog(theta)``,
and ``log det F`` is concave in ``p``: the multiplicative algorithm (Titterington 1976)
``p_k <- p_k tr(F^-1 F_k) / m`` converges to the optimum.  Parameters the band cannot inform
at any allocation are named unidentifiable and left out first, so the Fisher matrix it
inverts is never singular (the seed's script died on exactly that).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.params import FIT_PARAMS, check_names, param_value
from twind.analysis.noise import in1_noise_asd
from twind.config import OpticConfig
from twind.analysis.design.coherence import ExcitationDesignError
from twind.excitation.design import schroeder_phases

_STEP = 1e-4
MIN_SHARE = 1e-3
"""Tones given less than this share of their DOF's power are dropped (crest factor)."""


@dataclass
class InformationDesign:
    """A D-optimal multisine per excited DOF and the uncertainty it predicts.

    Attributes
    ----------
    period_s : float
        Multisine period: tones lie on multiples of ``1 / period_s``; measure with
        ``bw = 1 / period_s``.
    tones : dict of str to ndarray
        Tone frequencies (Hz) per DOF.
    amps : dict of str to ndarray
        Peak amplitude of each tone (um or urad at EXC).
    rms : dict of str to float
    params, unidentifiable : list of str
    sigma, sigma_white : ndarray
        Predicted relative one-sigma uncertainty of `params` from this design and from white
        noise of equal RMS over the same band, both for `duration_s` of measurement.
    """

    optic: str
    period_s: float
    duration_s: float
    tones: dict[str, NDArray[np.float64]]
    amps: dict[str, NDArray[np.float64]]
    rms: dict[str, float]
    params: list[str]
    unidentifiable: list[str]
    covariance: NDArray[np.float64]
    covariance_white: NDArray[np.float64]

    @property
    def sigma(self) -> NDArray[np.float64]:
        """Predicted relative uncertainty of each parameter."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def gain(self) -> float:
        """``det(Cov_white)^(1/p) / det(Cov)^(1/p)``: how much better than white noise."""
        return det_root(self.covariance_white) / det_root(self.covariance)

    def waveform(self, dof: str, n: int, rate_hz: float) -> NDArray[np.float64]:
        """`n` samples of the DOF's multisine (Schroeder phases, exactly periodic).

        Parameters
        ----------
        dof : str
            One of the designed DOFs, e.g. ``POS``.
        n : int
            Number of samples; the period repeats as often as it takes.
        rate_hz : float
            Sample rate of the EXC test point (Hz).

        Returns
        -------
        numpy.ndarray
            The samples, um or urad at EXC.
        """
        m = int(round(self.period_s * rate_hz))
        f, a = self.tones[dof], self.amps[dof]
        k = np.rint(f * self.period_s).astype(int)
        spec = np.zeros(m // 2 + 1, dtype=complex)
        spec[k] = 0.5 * m * a * np.exp(1j * (schroeder_phases(f, self.period_s) - math.pi / 2))
        period = np.fft.irfft(spec, m)
        return np.resize(period, n)

    def peak(self, dof: str, rate_hz: float) -> float:
        """Largest |sample| of the DOF's multisine, to check against the twin's peak limit.

        Parameters
        ----------
        dof : str
            One of the designed DOFs, e.g. ``POS``.
        rate_hz : float
            Sample rate of the EXC test point (Hz).

        Returns
        -------
        float
            Over one period, um or urad at EXC.
        """
        return float(np.max(np.abs(self.waveform(dof, int(round(self.period_s * rate_hz)),
                                                 rate_hz))))

    def to_json(self) -> dict:
        """The ``twind excite --mode information --json`` object."""
        return {"optic": self.optic, "mode": "information", "period_s": self.period_s,
                "duration_s": self.duration_s, "bw_hz": 1 / self.period_s,
                "excitations": {d: {"freqs": self.tones[d].tolist(),
                                    "amps": self.amps[d].tolist(), "rms": self.rms[d]}
                                for d in self.tones},
                "params": self.params, "unidentifiable": self.unidentifiable,
                "predicted_sigma": dict(zip(self.params, self.sigma.tolist(), strict=True)),
                "predicted_sigma_white": dict(zip(
                    self.params, np.sqrt(np.diag(self.covariance_white)).tolist(), strict=True)),
                "det_cov_gain_over_white": self.gain}

    def summary(self) -> list[str]:
        """Human-readable summary."""
        out = [f"{self.optic}: D-optimal multisine, period {self.period_s:g} s, "
               f"{self.duration_s:g} s of measurement"]
        for d in self.tones:
            share = self.amps[d] ** 2 / np.sum(self.amps[d] ** 2)
            top = np.argsort(share)[::-1][:6]
            tones = ", ".join(f"{self.tones[d][i]:.3g} Hz ({100 * share[i]:.0f} %)" for i in top)
            out.append(f"  {d}: RMS {self.rms[d]:g}, {len(self.tones[d])} tone(s): {tones}"
                       + (" ..." if len(self.tones[d]) > 6 else ""))
        white = np.sqrt(np.diag(self.covariance_white))
        for n, s, w in zip(self.params, self.sigma, white, strict=True):
            out.append(f"  {n:15s} predicted {100 * s:8.4f} %   (white noise {100 * w:8.4f} %)")
        if self.unidentifiable:
            out.append(f"  unidentifiable in this band: {', '.join(self.unidentifiable)}")
        out.append(f"  det(Cov)^(1/p) {self.gain:.1f}x smaller than white noise of equal RMS")
        return out


def tone_fisher(cfg: OpticConfig, params: Sequence[str], dofs: Sequence[str],
                f_hz: NDArray[np.float64], duration_s: float) -> NDArray[np.float64]:
    """Fisher matrix per unit tone power, ``[dof, tone, p, p]``, over log-parameters.

    Parameters
    ----------
    cfg : OpticConfig
        The optic at the parameters to linearise about.
    params : sequence of str
        The parameters (names as ``twind fit`` reports them).
    dofs : sequence of str
        The excited DOFs.
    f_hz : numpy.ndarray
        Tone frequencies (Hz).
    duration_s : float
        Seconds each tone is held.

    Returns
    -------
    numpy.ndarray
        ``F[d, k]``: the information a unit power at EXC of DOF ``d`` and tone ``k`` gives,
        summed over every IN1 response against its noise PSD.
    """
    model = ClosedLoopModel(cfg, f_hz)
    base = {n: param_value(cfg.sus, n) for n in params}
    cols = [DOFS.index(d) for d in dofs]
    grads = []
    for n in params:
        up = model({**base, n: base[n] * math.exp(_STEP)})
        down = model({**base, n: base[n] * math.exp(-_STEP)})
        grads.append((up - down)[:, :, cols] / (2 * _STEP))
    g = np.stack(grads, axis=-1)  # [f, response, dof, p]
    noise_psd = in1_noise_asd(cfg, f_hz) ** 2  # [f, response]
    w = 2.0 * duration_s / np.maximum(noise_psd, np.finfo(float).tiny)
    F = np.einsum("fr,frdp,frdq->dfpq", w, np.conj(g), g).real
    return F


def design_information(cfg: OpticConfig, dofs: Sequence[str], band: tuple[float, float],
                       rms: float | Sequence[float], duration_s: float, period_s: float = 20.0,
                       params: Sequence[str] = FIT_PARAMS, iterations: int = 2000
                       ) -> InformationDesign:
    """D-optimal multisines for `params` of `cfg`'s optic.

    Parameters
    ----------
    cfg : OpticConfig
        The optic at the current best parameters (nominal, or the last fit's).
    dofs : sequence of str
        Excited DOFs, each measured for `duration_s` at its own RMS.
    band : (float, float)
        Hz; candidate tones are the multiples of ``1 / period_s`` inside it.
    rms : float or sequence of float
        RMS of each DOF's excitation (um or urad at EXC).
    duration_s : float
        Measurement time per DOF.
    period_s : float
        Multisine period (the measurement's resolution is ``1 / period_s``).
    params : sequence of str
        Parameters to inform; those no allocation can inform are reported unidentifiable.
    iterations : int
        Of the multiplicative algorithm.

    Returns
    -------
    InformationDesign
    """
    names = check_names(params)
    dofs = list(dofs)
    if not dofs or any(d not in DOFS for d in dofs):
        msg = f"DOFs must be among {', '.join(DOFS)}, got {dofs}"
        raise ExcitationDesignError(msg)
    rms_d = np.broadcast_to(np.asarray(rms, dtype=float), (len(dofs),)).copy()
    lo, hi = band
    f = np.arange(math.ceil(lo * period_s), math.floor(hi * period_s) + 1) / period_s
    f = f[f > 0]
    if f.size < 2 or not np.all(rms_d > 0) or not duration_s > 0:
        msg = (f"need >= 2 tones of 1/{period_s:g} s in {lo:g}-{hi:g} Hz, positive RMS and "
               f"duration; got {f.size} tones, RMS {rms_d.tolist()}, {duration_s:g} s")
        raise ExcitationDesignError(msg)
    F = tone_fisher(cfg, names, dofs, f, duration_s)
    power = (rms_d**2)[:, None] * np.ones((1, f.size)) / f.size  # white: equal tones
    keep = _informed(np.einsum("dk,dkpq->pq", power, F))
    lost = [n for n, k in zip(names, keep, strict=True) if not k]
    F = F[:, :, keep][:, :, :, keep]
    white_cov = np.linalg.inv(np.einsum("dk,dkpq->pq", power, F))
    p = _d_optimal(F, power, rms_d**2, iterations)
    cov = np.linalg.inv(np.einsum("dk,dkpq->pq", p, F))
    tones, amps = {}, {}
    for i, d in enumerate(dofs):
        used = p[i] > MIN_SHARE * p[i].max()
        tones[d], amps[d] = f[used], np.sqrt(2 * p[i, used])
        amps[d] *= rms_d[i] / np.sqrt(np.sum(amps[d] ** 2) / 2)  # dropped tones' power back
    return InformationDesign(cfg.name, period_s, duration_s, tones, amps,
                             dict(zip(dofs, rms_d.tolist(), strict=True)),
                             [n for n, k in zip(names, keep, strict=True) if k], lost, cov,
                             white_cov)


def _informed(M: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Parameters with information enough (log-sigma below 1) once the others are fitted too.

    Parameters are removed worst first until the rest's Fisher matrix is well conditioned.
    """
    keep = np.ones(M.shape[0], dtype=bool)
    while keep.any():
        sub = M[np.ix_(keep, keep)]
        w, v = np.linalg.eigh(sub)
        if w[0] >= 1.0:  # every direction known better than a factor e
            break
        worst = np.flatnonzero(keep)[np.argmax(np.abs(v[:, 0]))]
        keep[worst] = False
    return keep


def _d_optimal(F: NDArray[np.float64], start: NDArray[np.float64], budget: NDArray[np.float64],
               iterations: int) -> NDArray[np.float64]:
    """Tone powers ``[dof, tone]`` maximising ``det(sum p F)`` with ``sum_k p[d] = budget[d]``."""
    p = start.copy()
    for _ in range(iterations):
        M_inv = np.linalg.inv(np.einsum("dk,dkpq->pq", p, F))
        d = np.einsum("pq,dkqp->dk", M_inv, F)  # tr(M^-1 F_k): the variance function
        mean = np.sum(p * d, axis=1) / budget  # per DOF, the power-weighted mean of d
        if np.all(d.max(axis=1) <= (1 + 1e-3) * mean):
            break  # Kiefer-Wolfowitz: at the optimum no tone's d exceeds its DOF's mean
        p = p * d / mean[:, None]
    return p


def det_root(cov: NDArray[np.float64]) -> float:
    """``det(cov)^(1/p)``: the geometric-mean variance (inf for a singular matrix)."""
    sign, logdet = np.linalg.slogdet(cov)
    return float(np.exp(logdet / cov.shape[0])) if sign > 0 else math.inf

