"""Are the fit's uncertainties honest?  A Monte-Carlo pull test on the twin.

Many measurements of one drifted optic, differing only in their noise, are fitted; the pull
``(fitted - truth) / sigma`` of every identifiable parameter should then be distributed with
standard deviation 1 (the issue asks 1.0 +- 0.1 over at least 100 realisations).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind import progress
from twind.analysis.identification.fit import fit
from twind.analysis.identification.params import FIT_PARAMS, param_value, with_params
from twind.config import OpticConfig
from twind.analysis.design.information import design_information, det_root
from twind.commissioning.campaign import LocalTwin, tones_only
from twind.commissioning.measurement import DRIFT, SETTLE_S, measure_tfs
from twind.lab.workers import side_by_side


@dataclass
class PullReport:
    """Pulls of each parameter over the realisations (``nan`` where unidentifiable).

    ``pulls`` are ``(fitted - truth) / sigma``; ``log_pulls`` are the same in the fit's own
    coordinates, ``log(fitted / truth) / (sigma / fitted)``, where its Cramer-Rao bound is
    linear. They differ only for a parameter known to tens of percent: a Q fitted half its
    truth has half the sigma, and its pull doubles.
    """

    names: list[str]
    pulls: NDArray[np.float64]  # [realisation, parameter]
    log_pulls: NDArray[np.float64]
    relative_sigma: NDArray[np.float64]
    seconds: float

    def lines(self) -> list[str]:
        """A table per parameter and the pooled figure."""
        out = [f"{'parameter':15s} {'n':>4s} {'pull mean':>10s} {'pull std':>9s} "
               f"{'log-pull std':>13s} {'median sigma':>13s}"]
        for k, n in enumerate(self.names):
            p = self.pulls[:, k][np.isfinite(self.pulls[:, k])]
            if p.size < 2:
                out.append(f"{n:15s} {p.size:4d}   unidentifiable")
                continue
            lp = self.log_pulls[:, k][np.isfinite(self.log_pulls[:, k])]
            out.append(f"{n:15s} {p.size:4d} {p.mean():+10.3f} {p.std(ddof=1):9.3f} "
                       f"{lp.std(ddof=1):13.3f} "
                       f"{100 * np.nanmedian(self.relative_sigma[:, k]):12.3f}%")
        pooled = self.pulls[np.isfinite(self.pulls)]
        std = pooled.std(ddof=1)
        logs = self.log_pulls[np.isfinite(self.log_pulls)]
        # a std estimated from N roughly-normal pulls scatters by std / sqrt(2 (N - 1))
        out.append(f"pooled: {pooled.size} pulls from {len(self.pulls)} realisations, std "
                   f"{std:.3f} +- {std / np.sqrt(2 * (pooled.size - 1)):.3f} (target 1.0 +- 0.1), "
                   f"log-pull std {logs.std(ddof=1):.3f}, |pull| > 3 in "
                   f"{np.mean(np.abs(pooled) > 3):.1%}; {self.seconds:.0f} s")
        return out

    @property
    def pooled_std(self) -> float:
        """Standard deviation of all finite pulls."""
        pooled = self.pulls[np.isfinite(self.pulls)]
        return float(pooled.std(ddof=1))


def pull_test(cfg: OpticConfig, n: int = 100, drift: Mapping[str, float] = DRIFT,
              params: Sequence[str] = FIT_PARAMS, *, bw: float = 0.1, averages: int = 10,
              rms: float = 2.0, seed: int = 0, estimator: str = "welch", workers: int = 1
              ) -> PullReport:
    """Fit `n` noise realisations of `cfg`'s optic drifted by the factors `drift`.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic (the fit's starting model).
    n : int
        Number of realisations.
    drift : mapping of str to float
        Factor applied to each nominal parameter to make the "real" optic.
    params : sequence of str
        Parameters fitted.
    bw, averages, rms : float, int, float
        The simulated measurement: Welch resolution, averages, white EXC RMS (below 30 Hz).
    seed : int
        Realisation ``i`` uses seed ``seed + i``.
    estimator : str
        ``"welch"`` or ``"lpm"`` (over the record of the Welch measurement).
    workers : int
        Processes measuring and fitting realisations side by side (the result does not
        depend on it).

    Returns
    -------
    PullReport
    """
    real = replace(cfg, sus=with_params(cfg.sus, {k: param_value(cfg.sus, k) * v
                                                  for k, v in drift.items()}))
    names = list(params)
    pulls, log_pulls, rel = (np.full((n, len(names)), np.nan) for _ in range(3))
    t0 = time.perf_counter()
    truth = np.array([param_value(real.sus, k) for k in names])
    one = partial(_realisation, real, cfg, names,
                  {"bw": bw, "averages": averages, "rms": rms, "estimator": estimator})
    with side_by_side(workers) as pmap:
        results = pmap(one, range(seed, seed + n))
        for i, (values, sigma) in enumerate(results):
            pulls[i] = (values - truth) / sigma
            rel[i] = sigma / values
            log_pulls[i] = np.log(values / truth) / rel[i]
            _progress(pulls[: i + 1], n)
    return PullReport(names, pulls, log_pulls, rel, time.perf_counter() - t0)


def _realisation(real: OpticConfig, cfg: OpticConfig, names: list[str], measurement: dict,
                 seed: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fitted values and sigmas of one noise realisation (a process pool's task)."""
    r = fit(measure_tfs(real, seed=seed, **measurement), cfg, names)
    return r.values, r.sigma


def _progress(pulls: NDArray[np.float64], n: int) -> None:
    """Realisations done and the pulls' spread so far, on the progress bar."""
    so_far = pulls[np.isfinite(pulls)]
    std = f", pull std so far {so_far.std(ddof=1):.3f}" if so_far.size > 1 else ""
    progress.note(f"realisation {len(pulls)}/{n}{std}")


def information_benchmark(cfg: OpticConfig, drift: Mapping[str, float] = DRIFT,
                          dofs: Sequence[str] = ("POS", "PIT", "YAW"),
                          band: tuple[float, float] = (0.1, 10.0), rms: float = 10.0,
                          period_s: float = 20.0, averages: int = 5, rounds: int = 3,
                          seed: int = 0) -> list[str]:
    """D-optimal multisines against white noise of equal RMS, both measured on the twin.

    Each information round is designed at the previous round's fit (nominal first) and
    fitted on its own data; white noise of the same RMS, band and duration per DOF is
    measured with 50 %-overlap Hann Welch at the same resolution.  Reported: each round's
    ``det(Cov)^(1/p)`` over the parameters both identify, and its ratio to white noise's.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic (the first round's design and every fit's start).
    drift : mapping of str to float
        Factor applied to each nominal parameter to make the "real" optic.
    dofs : sequence of str
        DOFs excited, each measured for the same time.
    band : (float, float)
        The excitations' band (Hz).
    rms : float
        RMS of each DOF's excitation (um or urad at EXC).
    period_s : float
        Multisine period and Welch segment (s): the resolution is ``1 / period_s``.
    averages : int
        Periods measured per DOF.
    rounds : int
        Information rounds, each designed at the previous one's fit.
    seed : int
        Seed of the white noise and of the twin's noise.

    Returns
    -------
    list of str
        The white-noise reference, then one line per round.
    """

    real = replace(cfg, sus=with_params(cfg.sus, {k: param_value(cfg.sus, k) * v
                                                  for k, v in drift.items()}))
    rate = cfg.sus.sample_rate_hz
    duration = averages * period_s
    rng = np.random.default_rng(seed)
    sos = signal.butter(4, band, btype="bandpass", fs=rate, output="sos")
    n = int(round((duration + SETTLE_S) * rate))
    white = {}
    for d in dofs:
        x = signal.sosfilt(sos, rng.standard_normal(n))
        white[d] = x * (rms / np.std(x))
    # 50 % overlap: 2 * averages - 1 Hann segments of one period in the same time
    tfs = measure_tfs(real, dofs, bw=1 / period_s, averages=2 * averages - 1, overlap=0.5,
                      excitation=white, seed=seed)
    ref = fit(tfs, cfg)
    lines = [f"white noise, RMS {rms:g}, {band[0]:g}-{band[1]:g} Hz, {duration:g} s per DOF: "
             f"chi2/nu {ref.chi2_nu:.3f}"]
    twin, current = LocalTwin(real, seed + 1), cfg
    for k in range(1, rounds + 1):
        design = design_information(current, dofs, band, rms, duration, period_s)
        result = fit(tones_only(twin.measure(design, averages), design), current)
        common = np.isfinite(np.diag(result.covariance)) & np.isfinite(np.diag(ref.covariance))
        names = [nm for nm, c in zip(result.names, common, strict=True) if c]
        ratio = det_root(ref.covariance[np.ix_(common, common)]) / det_root(
            result.covariance[np.ix_(common, common)])
        lines.append(f"round {k}: D-optimal multisine (predicted {design.gain:.1f}x), chi2/nu "
                     f"{result.chi2_nu:.3f}: det(Cov)^(1/p) {ratio:.1f}x smaller than white "
                     f"noise over {len(names)} parameters ({', '.join(names)})")
        current = replace(current, sus=with_params(current.sus, result.identified()))
    return lines
