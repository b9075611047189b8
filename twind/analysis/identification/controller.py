"""The damping loop's own controller, measured: each DOF's ``OUT/IN2`` against the filter
module the configuration believes, before anything is read as suspension physics.

A filter module's OUT is its IN2 through the switched-on stages and the gain, sample by
sample, so ``(OUT/EXC) / (IN2/EXC)`` of one DOF is its controller K, whichever EXC drives
it, up to the spectral window's leakage, whose errors are of the size the coherence gives.
A filter engaged that the configuration does not have, a wrong gain or a flipped sign makes
every closed-loop response differ from the model; read through the plant, that difference
looks like a misfit of the suspension. Here it is named as what it is, fitted (a gain, the
bank's other modules switched on or off, or a stage of its own), and the configuration is
given the measured controller for the rest of the analysis.

The test: the log of the ratio ``c = K_measured / K_configured`` (its real part the gain in
nepers, its imaginary part the phase), averaged with inverse-variance weights over the
bands the residuals are searched in; each band's mean against its own scatter (an F test of
two components, unequal weights and the bins' correlation paid for), Bonferroni over every
band of every DOF at :data:`ALPHA`. The method: docs/diagnose.md, "The controller".
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy import optimize, signal, stats

from twind import DOFS
from twind.analysis.estimation.tfset import TFSet
from twind.config import OpticConfig
from twind.analysis.identification.locate import band_edges, gaussian_sigma
from twind.config.reader import ModuleConfig
from twind.loop.filtermodule import Stage
from twind.loop.foton import n_plane_design

ALPHA = 0.01
"""Family-wise false-alarm probability of calling a controller different (every band of
every DOF checked)."""
MAX_SREL = 0.3
"""Bins whose ratio's relative standard error is larger are not used (its log is not
Gaussian there)."""
NOTCH_SLOPE = 0.2
"""Bins where the configured controller changes by more than this fraction across two
bins (a notch's) are not used: there the window's leakage, not K, sets the ratio."""
DYNAMIC_RANGE = 1e-6
"""Bins where the configured controller is smaller than this fraction of its largest are
not used: there OUT holds the arithmetic's rounding (a recorded float32 test point keeps
about seven digits), not a filter anyone designs."""
COHERENCE_AGREE = 0.9
"""Bins where OUT's coherence with EXC is below this fraction of IN2's are not used: where
OUT is IN2 through a filter, the two coherences are equal, estimate by estimate, whatever the
filter; where OUT's is lower, OUT holds what no filter of IN2 makes (the arithmetic's own
noise where the filter has rolled off by many decades, a limiter)."""
MIN_BINS = 4
"""Bins a band needs to be tested."""


@dataclass(frozen=True)
class Ratio:
    """One DOF's measured controller over its configured one, at the bins that measure it.

    Attributes
    ----------
    dof : str
    frequency_hz : ndarray
    log_ratio : ndarray of complex
        ``ln(K_measured / K_configured)``: gain in nepers, phase in radians.
    sigma : ndarray
        Standard error of its real and of its imaginary part.
    correlation : float
        Of neighbouring bins' errors (Hann-windowed estimates share half a window).
    """

    dof: str
    frequency_hz: NDArray[np.float64]
    log_ratio: NDArray[np.complex128]
    sigma: NDArray[np.float64]
    correlation: float


@dataclass(frozen=True)
class Difference:
    """A band where a DOF's controller differs from the configuration's.

    Attributes
    ----------
    dof : str
    band_hz : (float, float)
    db, deg : float
        The band's mean difference in gain (dB) and phase (degrees), measured over
        configured.
    significance : float
        Gaussian-equivalent sigma of its p-value (Bonferroni over every band tested).
    p_value : float
        Corrected.
    """

    dof: str
    band_hz: tuple[float, float]
    db: float
    deg: float
    significance: float
    p_value: float

    def line(self) -> str:
        """The difference in words."""
        lo, hi = self.band_hz
        return (f"{self.dof}'s damping filter differs from the configuration: "
                f"{self.db:+.2f} dB, {self.deg:+.1f} deg near {math.sqrt(lo * hi):.3g} Hz "
                f"({lo:.3g}-{hi:.3g} Hz, {self.significance:.1f} sigma)")

    def to_json(self) -> dict:
        """One entry of ``controller.differences``."""
        return {"dof": self.dof, "band_hz": list(self.band_hz), "db": self.db,
                "deg": self.deg, "significance": self.significance, "p_value": self.p_value}


@dataclass(frozen=True)
class Correction:
    """What a DOF's measured controller is, as a change of its configured module.

    Attributes
    ----------
    dof : str
    kind : str
        ``"gain"`` (the gain differs, its sign among it), ``"modules"`` (other stages of the
        bank switched on or off, and the gain), or ``"stage"`` (stages of its own, as foton
        designs, with the gain).
    gain : float
        Measured over configured gain.
    on : tuple of int
        The FMs switched on in the measurement.
    designs : tuple of str
        ``"stage"``: the foton designs of the stages the configuration lacks.
    chi2_nu : float
        Of the ratio's residuals after the correction (1: within the noise; the
        coherence's errors are conservative here, about 0.5 on twin nulls).
    explained : bool
        No band beyond the noise remains.
    peak_hz, peak_db, peak_deg : float
        Where in the measured bins the correction is largest, and its gain (dB) and phase
        (degrees) there.
    """

    dof: str
    kind: str
    gain: float
    on: tuple[int, ...]
    designs: tuple[str, ...] = ()
    chi2_nu: float = math.nan
    explained: bool = True
    peak_hz: float = math.nan
    peak_db: float = math.nan
    peak_deg: float = math.nan
    applied: bool = True
    """False when the configured bank has no room for it: the plant is read through the
    configured module."""

    def short(self) -> str:
        """The correction in a few words."""
        return {"gain": f"gain x{self.gain:.3g}",
                "modules": f"FM{','.join(map(str, self.on)) or ' none'} on",
                "stage": f"{self.peak_db:+.1f} dB at {self.peak_hz:.3g} Hz"}[self.kind]

    def line(self) -> str:
        """The correction in words."""
        text = {"gain": f"its gain is {self.gain:.4g} times the configured",
                "modules": f"FM{','.join(map(str, self.on)) or ' none'} on, gain "
                           f"{self.gain:.4g} times the configured",
                "stage": f"a stage the configuration lacks, {' '.join(self.designs)}, gain "
                         f"{self.gain:.4g} times the configured"}[self.kind]
        rest = "" if self.explained else "; beyond it the difference is not modelled"
        if not self.applied:
            rest += "; the bank has no room for it, so the configured module is kept"
        return f"{self.dof}: {text} (chi2/nu {self.chi2_nu:.2f}){rest}"

    def to_json(self) -> dict:
        """One entry of ``controller.corrections``."""
        return {"dof": self.dof, "kind": self.kind, "gain": self.gain, "on": list(self.on),
                "designs": list(self.designs), "chi2_nu": self.chi2_nu,
                "explained": self.explained, "applied": self.applied,
                "peak_hz": self.peak_hz,
                "peak_db": self.peak_db, "peak_deg": self.peak_deg}


@dataclass
class ControllerCheck:
    """The measured controllers against the configured ones.

    Attributes
    ----------
    checked : list of str
        DOFs whose OUT/IN2 was measured in enough bins.
    differences : list of Difference
        Bands beyond the noise, most significant first.
    corrections : list of Correction
        For each DOF that differs, what its controller is.
    config : OpticConfig
        The configuration with the measured controllers: what the plant is read through.
    """

    checked: list[str]
    differences: list[Difference]
    corrections: list[Correction]
    config: OpticConfig
    ratios: dict[str, Ratio] = field(default_factory=dict, repr=False)

    @property
    def same(self) -> bool:
        """True when every controller checked is the configuration's, within the noise."""
        return not self.differences

    def largest(self, dof: str) -> Difference:
        """`dof`'s difference beyond the noise that is largest in size (gain and phase)."""
        return max((d for d in self.differences if d.dof == dof),
                   key=lambda d: math.hypot(d.db * math.log(10) / 20, math.radians(d.deg)))

    def lines(self) -> list[str]:
        """A summary for a person."""
        if not self.checked:
            return ["controller: not checked (no DOF's OUT/IN2 measured in enough bins)"]
        if self.same:
            return [f"controller: {', '.join(self.checked)} as configured (OUT/IN2 within "
                    f"the noise, family-wise level {ALPHA:g})"]
        out = []
        for c in self.corrections:
            band = self.largest(c.dof)
            out += [f"{c.dof}'s damping filter differs from the configuration: "
                    f"{c.peak_db:+.2f} dB, {c.peak_deg:+.1f} deg at {c.peak_hz:.3g} Hz "
                    f"({band.significance:.1f} sigma in {band.band_hz[0]:.3g}-"
                    f"{band.band_hz[1]:.3g} Hz)",
                    f"  measured: {c.line()}"
                    + ("; the plant is read through it" if c.applied else "")]
        return out

    def to_json(self) -> dict:
        """``controller`` in ``twind diagnose --json`` and ``twind fit --json``."""
        return {"checked": self.checked, "same": self.same, "alpha": ALPHA,
                "differences": [d.to_json() for d in self.differences],
                "corrections": [c.to_json() for c in self.corrections]}


def measured_ratio(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, dof: str) -> Ratio | None:
    """`dof`'s measured controller over its configured one, from every column of `tfs`
    that holds its OUT and IN2, combined bin by bin with inverse-variance weights.

    Parameters
    ----------
    tfs : TFSet or sequence of TFSet
    cfg : OpticConfig
        The configured controller.
    dof : str

    Returns
    -------
    Ratio or None
        None when fewer than :data:`MIN_BINS` bins measure it.
    """
    sets = [tfs] if isinstance(tfs, TFSet) else list(tfs)
    f_all, d_all, s_all, rho = [], [], [], []
    for t in sets:
        if dof not in t.responses:
            continue
        i = t.responses.index(dof)
        out, in2 = t.tf["OUT"][:, i, :], t.tf["IN2"][:, i, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            srel2 = ((t.sigma("OUT")[:, i, :] / np.abs(out)) ** 2
                     + (t.sigma("IN2")[:, i, :] / np.abs(in2)) ** 2)
            linear = t.coherence["OUT"][:, i, :] >= COHERENCE_AGREE * t.coherence["IN2"][:, i, :]
            w = np.where(np.isfinite(srel2) & (srel2 > 0) & linear, 1.0 / srel2, 0.0)
            ratio = np.sum(w * np.nan_to_num(out / in2), axis=1) / np.sum(w, axis=1)
            srel = 1.0 / np.sqrt(np.sum(w, axis=1))
        keep = np.flatnonzero((srel < MAX_SREL) & np.isfinite(ratio) & (ratio != 0)
                              & (t.frequency_hz > 0))
        if keep.size < MIN_BINS:
            continue
        f, ratio, srel = t.frequency_hz[keep], ratio[keep], srel[keep]
        k = _response(cfg.damping[dof], f, cfg.rate_hz)
        with np.errstate(divide="ignore", invalid="ignore"):
            c = ratio / k  # k is 0 at a notch's zeros
        use = (np.isfinite(c) & (np.abs(k) > DYNAMIC_RANGE * np.abs(k).max())
               & _smooth(cfg.damping[dof], f, cfg.rate_hz, t.frequency_hz))
        if use.sum() < MIN_BINS:
            continue
        d = np.log(c[use])
        f_all.append(f[use])
        d_all.append(d)
        s_all.append(srel[use])
        rho.append(_neighbours(d, srel[use]))
    if not f_all:
        return None
    return Ratio(dof, np.concatenate(f_all), np.concatenate(d_all), np.concatenate(s_all),
                 float(max(np.mean(rho), 0.0)))


def _stage_responses(module: ModuleConfig, f: NDArray[np.float64], rate_hz: float
                     ) -> dict[int, NDArray[np.complex128]]:
    """Each defined stage's digital response at `f`: what the front end runs, which above
    a few hundred Hz is not its continuous design's."""
    return {i + 1: signal.sosfreqz(s.sections(rate_hz), worN=f, fs=rate_hz)[1]
            for i, s in enumerate(module.stages) if s is not None}


def _response(module: ModuleConfig, f: NDArray[np.float64], rate_hz: float,
              on: Sequence[int] | None = None) -> NDArray[np.complex128]:
    """`module`'s digital IN2 -> OUT response with `on` (default its own) switched on."""
    stages = _stage_responses(module, f, rate_hz)
    h = np.full(f.shape, module.gain, dtype=complex)
    for fm in module.on if on is None else on:
        h = h * stages[fm]
    return h


def _smooth(module: ModuleConfig, f: NDArray[np.float64], rate_hz: float,
            bins: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Of `f`, where the configured controller is smooth over two of `bins` either side."""
    df = float(np.median(np.diff(bins))) if bins.size > 1 else 0.0
    lo = _response(module, np.maximum(f - 2 * df, 1e-6), rate_hz)
    hi = _response(module, f + 2 * df, rate_hz)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(hi / lo - 1) < NOTCH_SLOPE


def _neighbours(d: NDArray[np.complex128], s: NDArray[np.float64], width: int = 21) -> float:
    """Correlation of neighbouring bins' whitened deviations from their running mean over
    `width` bins (the lag-one correlation that subtracting the mean induces,
    ``-1 / (width - 1)``, given back)."""
    if d.size < 2 * width:
        return 0.0
    u = d / s
    u = (u - np.convolve(u, np.ones(width) / width, mode="same"))[width:-width]
    a, b = u[:-1], u[1:]
    den = math.sqrt(float(np.sum(np.abs(a) ** 2)) * float(np.sum(np.abs(b) ** 2))) or 1.0
    return float(np.real(np.sum(a * np.conj(b)))) / den + 1.0 / (width - 1)


def band_tests(ratio: Ratio, residual: NDArray[np.complex128] | None = None
               ) -> list[tuple[tuple[float, float], complex, float]]:
    """Each band's weighted mean of `residual` (default the log ratio) and its uncorrected
    p-value against zero, from the band's own scatter.

    Returns
    -------
    list of (band, mean, p-value)
    """
    d = ratio.log_ratio if residual is None else residual
    f, w = ratio.frequency_hz, 1.0 / ratio.sigma**2
    inflation = 1.0 + 2.0 * ratio.correlation
    edges = band_edges(float(f.min()), float(f.max()))
    out = []
    for a, b in itertools.pairwise(edges):
        k = (f >= a) & (f < b)
        if int(k.sum()) < MIN_BINS:
            continue
        wk, dk = w[k], _on_branch(d[k], w[k])
        n = float(np.sum(wk)) ** 2 / float(np.sum(wk**2))  # Kish: unequal weights count less
        mean = complex(np.sum(wk * dk) / np.sum(wk))
        spread = float(np.sum(wk**2 * np.abs(dk - mean) ** 2)) / float(np.sum(wk)) ** 2
        var = spread * n / max(n - inflation, 1.0) * inflation  # of the mean, both components
        dof = max(2.0 * (n / inflation - 1.0), 2.0)
        p = float(stats.f.sf(abs(mean) ** 2 / max(var, 1e-300), 2, dof))
        out.append(((float(a), float(b)), mean, p))
    return out


def _on_branch(d: NDArray[np.complex128], w: NDArray[np.float64]) -> NDArray[np.complex128]:
    """`d` with each phase moved by whole turns to within half a turn of their circular
    mean: a flipped sign (a phase near +-pi) must not average to zero."""
    centre = float(np.angle(np.sum(w * np.exp(1j * d.imag))))
    return d - 2j * math.pi * np.round((d.imag - centre) / (2 * math.pi))


def check_controller(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig,
                     alpha: float = ALPHA) -> ControllerCheck:
    """Every DOF's measured controller against `cfg`'s; those that differ corrected.

    Parameters
    ----------
    tfs : TFSet or sequence of TFSet
        Measurements holding OUT and IN2 of the damping loop.
    cfg : OpticConfig
        What the configuration believes.
    alpha : float
        Family-wise false-alarm probability over every band of every DOF.

    Returns
    -------
    ControllerCheck
    """
    ratios = {d: r for d in DOFS if (r := measured_ratio(tfs, cfg, d)) is not None}
    tests = {d: band_tests(r) for d, r in ratios.items()}
    m = sum(len(t) for t in tests.values())
    differences = [Difference(d, band, 20 * mean.real / math.log(10), math.degrees(mean.imag),
                              gaussian_sigma(p * m), min(1.0, p * m))
                   for d, t in tests.items() for band, mean, p in t if p * m < alpha]
    differences.sort(key=lambda x: -x.significance)
    corrections = [correct(ratios[d], cfg.damping[d], cfg.rate_hz, alpha / max(m, 1))
                   for d in dict.fromkeys(x.dof for x in differences)]
    damping = dict(cfg.damping)
    for i, c in enumerate(corrections):
        try:
            damping[c.dof] = corrected_module(cfg.damping[c.dof], c)
        except ValueError:
            corrections[i] = replace(c, applied=False)
    return ControllerCheck(list(ratios), differences, corrections,
                           replace(cfg, damping=damping), ratios)


def correct(ratio: Ratio, module: ModuleConfig, rate_hz: float, alpha_band: float
            ) -> Correction:
    """The simplest change of `module` that leaves no band of `ratio` beyond the noise (each
    band at `alpha_band`): its gain; other stages of its bank on or off, with the gain; one
    stage of its own, then two. The best tried when none does."""
    tried = []
    for kind, fitter in (("gain", _fit_gain), ("modules", _fit_modules),
                         ("stage", _fit_stages)):
        for c, model in fitter(ratio, module, rate_hz):
            left = [p for _, _, p in band_tests(ratio, ratio.log_ratio - model)]
            chi2_nu = _chi2_nu(ratio, model)
            i = int(np.argmax(np.abs(model)))
            c = replace(c, kind=kind, chi2_nu=chi2_nu,
                        explained=all(p >= alpha_band for p in left),
                        peak_hz=float(ratio.frequency_hz[i]),
                        peak_db=float(20 * model[i].real / math.log(10)),
                        peak_deg=float(math.degrees(model[i].imag)))
            if c.explained:
                return c
            tried.append(c)
    return min(tried, key=lambda c: c.chi2_nu)


def corrected_module(module: ModuleConfig, c: Correction) -> ModuleConfig:
    """`module` changed as `c` measured it: its gain, the FMs on, and each stage it lacks
    in a free slot (a full bank's last switched-on stage takes it as a further factor)."""
    stages, on = list(module.stages), list(c.on)
    for design in c.designs:
        free = [i for i, s in enumerate(stages) if s is None]
        if free:
            stages[free[0]] = Stage("measured", design=design)
            on.append(free[0] + 1)
            continue
        last = max(on) - 1 if on else None
        if last is None or stages[last].design is None:
            msg = (f"{c.dof}: the bank has no free slot for the measured stage {design} "
                   "and no switched-on design to add it to")
            raise ValueError(msg)
        stages[last] = Stage(stages[last].name, design=f"{stages[last].design}{design}")
    return replace(module, gain=module.gain * c.gain, stages=tuple(stages),
                   on=tuple(sorted(set(on))))


def _chi2_nu(ratio: Ratio, model: NDArray[np.complex128]) -> float:
    z = (ratio.log_ratio - model) / ratio.sigma
    return float(np.sum(np.abs(z) ** 2)) / (2 * z.size) / (1 + 2 * ratio.correlation)


def _gain(ratio: Ratio, log_shape: NDArray[np.complex128]) -> float:
    """The real gain (its sign among it) that best scales `log_shape` onto the ratio."""
    w = 1.0 / ratio.sigma**2
    r = ratio.log_ratio - log_shape
    phase = np.angle(np.sum(w * np.exp(1j * r.imag)))
    sign = -1.0 if abs(phase) > math.pi / 2 else 1.0
    return sign * math.exp(float(np.sum(w * r.real) / np.sum(w)))


def _with_gain(ratio: Ratio, log_shape: NDArray[np.complex128], g: float
               ) -> NDArray[np.complex128]:
    """``log(g) + log_shape``, the phase of a negative gain wrapped nearest the data."""
    model = math.log(abs(g)) + log_shape + (1j * math.pi if g < 0 else 0)
    # unwrap the model's phase onto the data's branch, bin by bin
    turns = np.round((ratio.log_ratio.imag - model.imag) / (2 * math.pi))
    return model + 2j * math.pi * turns


def _fit_gain(ratio: Ratio, module: ModuleConfig, rate_hz: float):  # noqa: ANN202, ARG001
    zero = np.zeros_like(ratio.log_ratio)
    g = _gain(ratio, zero)
    yield Correction(ratio.dof, "gain", g, tuple(module.on)), _with_gain(ratio, zero, g)


def _fit_modules(ratio: Ratio, module: ModuleConfig, rate_hz: float):  # noqa: ANN202
    """The set of the bank's defined stages switched on, other than the configured, that
    fits best, with its gain."""
    f = ratio.frequency_hz
    logs = {fm: np.log(h) for fm, h in _stage_responses(module, f, rate_hz).items()}
    k0 = sum((logs[fm] for fm in module.on), np.zeros(f.shape, complex))
    best = None
    for n in range(len(logs) + 1):
        for on in itertools.combinations(sorted(logs), n):
            if set(on) == set(module.on):
                continue
            shape = sum((logs[fm] for fm in on), np.zeros(f.shape, complex)) - k0
            g = _gain(ratio, shape)
            model = _with_gain(ratio, shape, g)
            chi2 = _chi2_nu(ratio, model)
            if best is None or chi2 < best[0]:
                best = (chi2, Correction(ratio.dof, "modules", g, on), model)
    if best:
        yield best[1], best[2]


def _biquad(f: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.complex128]:
    """``log`` of zero2(fz, Qz) pole2(fp, Qp), unity at DC; `p` = ln fz, ln Qz, ln fp, ln Qp."""
    fz, qz, fp, qp = np.exp(p)
    s = 1j * f
    zero = 1 + s / (fz * qz) - (f / fz) ** 2
    pole = 1 + s / (fp * qp) - (f / fp) ** 2
    return np.log(zero / pole)


def _fit_stages(ratio: Ratio, module: ModuleConfig, rate_hz: float):  # noqa: ANN202, ARG001
    """One stage of its own, then two, each started at the band that differs most."""
    f, w = ratio.frequency_hz, 1.0 / ratio.sigma
    params: list[NDArray[np.float64]] = []
    for _ in range(2):
        shape = sum((_biquad(f, p) for p in params), np.zeros_like(ratio.log_ratio))
        g0 = _gain(ratio, shape)
        rest = ratio.log_ratio - _with_gain(ratio, shape, g0)
        (a, b), mean, _ = min(band_tests(ratio, rest), key=lambda t: t[2])
        f0, boost = math.sqrt(a * b), math.exp(mean.real)
        start = np.log([f0, 1.0, f0, max(boost, 1 / boost) if boost > 1 else 1.0])
        if boost < 1:
            start[1] = math.log(1 / boost)
        x0 = np.concatenate([*params, start, [math.log(abs(g0))]])
        sign = 1.0 if g0 > 0 else -1.0

        def resid(x: NDArray[np.float64], sign: float = sign) -> NDArray[np.float64]:
            sh = sum(_biquad(f, x[4 * i: 4 * i + 4]) for i in range(len(x) // 4))
            r = (ratio.log_ratio - _with_gain(ratio, sh, sign * math.exp(x[-1]))) * w
            return np.concatenate([r.real, r.imag])

        lo = np.tile(np.log([f.min() / 10, 0.05, f.min() / 10, 0.05]), len(x0) // 4)
        hi = np.tile(np.log([f.max() * 10, 1e3, f.max() * 10, 1e3]), len(x0) // 4)
        x0 = np.clip(x0, np.append(lo, -50) + 1e-9, np.append(hi, 50) - 1e-9)
        fit = optimize.least_squares(resid, x0, bounds=(np.append(lo, -50), np.append(hi, 50)))
        params = [fit.x[4 * i: 4 * i + 4] for i in range(len(fit.x) // 4)]
        g = sign * math.exp(fit.x[-1])
        shape = sum(_biquad(f, p) for p in params)
        designs = tuple(_design(p) for p in params)
        yield (Correction(ratio.dof, "stage", g, tuple(module.on), designs),
               _with_gain(ratio, shape, g))


def _design(p: NDArray[np.float64]) -> str:
    """A fitted stage as foton writes it: one zpk, so foton adds no poles to its zeros."""
    fz, qz, fp, qp = np.exp(p)
    wz, wp = 2 * np.pi * fz, 2 * np.pi * fp
    return n_plane_design(np.roots([1, wz / qz, wz**2]), np.roots([1, wp / qp, wp**2]))
