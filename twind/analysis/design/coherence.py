"""Coherence mode of ``twind excite``: the noise excitation that makes a measurement coherent.

Exciting DOF ``d`` at its ``_EXC`` test point with Gaussian noise of ASD ``A(f)``, the
response ``IN1_r`` holds the signal ``|T_rd| A`` (``T = IN1/EXC``, the closed-loop response
of :meth:`twind.loop.damping.DampingLoop.responses`) and the noise the sensors see without
excitation, suppressed by the loop like any other input:

    IN1 = (I - P K)^-1 (P K EXC + N),   N = InMat (n_OSEM + Sens H F_sp n_sp)

with ``H = (M s^2 + C s + K)^-1`` the pendulum, ``F_sp`` the generalised force per unit
suspension-point motion and ``n_OSEM``, ``n_sp`` the independent noises of
:class:`~twind.simulation.noise.NoiseSpec` (:func:`twind.analysis.noise.in1_noise_asd`, which the engine
reproduces sample by sample).  The true coherence of ``EXC_d`` and ``IN1_r`` is then
``g2 = S / (S + N_r^2)`` with ``S = |T_rd|^2 A^2``, so a coherence ``g2`` needs

    A(f) >= sqrt(g2 / (1 - g2)) N_r(f) / |T_rd(f)|

for every response ``r`` that must be coherent (the excited DOF's own ``IN1`` by default).

Estimator margin
----------------
A measurement does not see the true coherence but a Welch estimate from a finite number of
averages, which scatters (and is biased upward at low coherence).  The excitation is
therefore designed for the true coherence ``g2_design`` at which the estimate from
`averages` independent segments falls below the `target` with probability at most
``1 - confidence`` in any one bin, from the exact distribution of the estimate (Carter,
Knapp & Nuttall 1973, :func:`coherence_cdf`).  E.g. target 0.7, 10 averages, confidence
0.95 gives ``g2_design`` = 0.832.  Welch with 50 % overlap (diaggui's and scipy's default)
gives about twice the segments of the same duration with nearly independent estimates, so
counting `averages` as non-overlapping segments of ``1/bw`` seconds is on the safe side.

Window
------
A bin of a Hann-windowed spectrum does not see its own frequency only: it averages the
spectra over the window's response (main lobe +-2 bins, :func:`hann_power`).  The true
coherence of a bin is that of the windowed Fourier coefficients,
``|<T A^2>|^2 / (<A^2> <|T|^2 A^2 + N^2>)`` with ``<.>`` the window average (negative
frequencies mirrored); this is what the design meets in every bin, and what the
``coherence`` it reports is.  It matters where the noise or ``T`` change within a few bins,
e.g. next to the loop's resonances at a coarse resolution; where ``T`` turns within a bin
(a notch of the damping filter) no level reaches the target, and the design says so.
The textbook (single-frequency) requirement is kept as ``narrowband_asd``.

Shape
-----
The requirement is covered by a low-order, stable, minimum-phase shape: a core ``zpk`` of n
real zeros and n real poles (n = 0 ... `max_order`, the lowest n within 3 % of the lowest
RMS) between a fourth-order Butterworth high-pass below the band and low-pass above it.
For each n the roots and edge frequencies are fitted to the requirement in log magnitude
(``scipy.optimize.least_squares``), then moved to minimise the RMS of the shape scaled to
cover the requirement (``scipy.optimize.minimize``, TNC, soft maximum, analytic
gradients).  The windowed coherence of the result is checked; where a bin falls short the
requirement there is raised and the shape refitted, and a last uniform scale closes any
remaining gap.  The foton design string *is* the excitation ASD (units of ``EXC`` per
rtHz), so the request asks for white noise of RMS ``noise_gain x sqrt(rate / 2)`` shaped
by it (what :class:`~twind.excitation.waveforms.NoiseWave` does with ``amp`` and
``shape``); the RMS and the peak (``NOISE_PEAK_SIGMAS x RMS``) are those
:func:`~twind.excitation.check` computes.
"""

from __future__ import annotations

import dataclasses
import math
import shlex
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize, special, stats

from twind import DOFS
from twind.analysis.noise import in1_noise_asd
from twind.channels import dof_channel
from twind.errors import TwindError
from twind.excitation.checks import DEFAULT_LIMITS, Limits, check
from twind.excitation.design import NOISE_PEAK_SIGMAS, noise_shape
from twind.excitation.request import ExcitationError, ExcitationRequest
from twind.loop.foton import ZPK, parse_design

if TYPE_CHECKING:
    from twind.config import OpticConfig
    from twind.loop.damping import DampingLoop

__all__ = ["CoherenceDesign", "DofDesign", "ExcitationDesignError", "coherence_cdf",
           "design_coherence", "design_coherent"]

RESPONSES = ("own", "all")
"""Which ``IN1`` must be coherent: the excited DOF's own, or every DOF of the design."""

EDGE_ORDER = 4
"""Order of the Butterworth high-pass and low-pass that confine the excitation to the band."""

WINDOW_REACH = 32
"""Bins each side of a bin over which the Hann window's leakage is counted (its power
response there is 1e-10 of the peak, falling as the sixth power of the distance)."""

GRID_STEP = 4
"""Grid points per bin for the window averages."""

MAX_REFITS = 4
"""Fits of the shape, each to the requirement raised where the last one fell short."""

EXACT_AVERAGES = 400
"""Up to this many averages the exact distribution of the coherence estimate is used; above,
its Fisher-z normal approximation (the exact series loses precision, the two agree to 1e-3)."""


class ExcitationDesignError(TwindError):
    """No excitation meets the request (limits, an unreachable response, bad settings)."""


# ============================================================================================
# Noise and coherence statistics
# ============================================================================================
def coherence_cdf(c: float, gamma2: float, averages: int) -> float:
    """Probability that the coherence estimated from `averages` segments is <= `c`.

    Parameters
    ----------
    c : float
        Estimated magnitude-squared coherence, 0..1.
    gamma2 : float
        True magnitude-squared coherence, 0..1.
    averages : int
        Independent (non-overlapping) segments averaged, >= 2.

    Returns
    -------
    float
        ``P(C_hat <= c)`` for jointly Gaussian signals (Carter, Knapp & Nuttall 1973):
        ``c ((1-g)/(1-g c))^n sum_k ((1-c)/(1-g c))^k 2F1(-k, 1-n; 1; g c)``,
        k = 0 .. n-2; above :data:`EXACT_AVERAGES` the Fisher-z approximation
        ``atanh(sqrt C_hat) ~ Normal(atanh(sqrt g), 1/(2 n))``.
    """
    n, g = int(averages), float(gamma2)
    if c <= 0.0:
        return 0.0
    if c >= 1.0:
        return 1.0
    if n > EXACT_AVERAGES:
        z = (math.atanh(math.sqrt(c)) - math.atanh(math.sqrt(min(g, 1 - 1e-15))))
        return float(stats.norm.cdf(z * math.sqrt(2 * n)))
    k = np.arange(n - 1)
    a = (1.0 - g) / (1.0 - g * c)
    b = (1.0 - c) / (1.0 - g * c)
    terms = b**k * special.hyp2f1(-k, 1 - n, 1, g * c)
    return float(min(1.0, max(0.0, c * a**n * np.sum(terms))))


def design_coherence(target: float, averages: int, confidence: float) -> float:
    """True coherence whose estimate from `averages` segments reaches `target` with `confidence`.

    Parameters
    ----------
    target : float
        Coherence the measurement must show, 0 < target < 1.
    averages : int
        Independent segments, >= 2.
    confidence : float
        Probability that one bin's estimate is >= `target`, 0 < confidence < 1.

    Returns
    -------
    float
        The smallest true coherence ``g2`` with ``P(C_hat < target) <= 1 - confidence``.
    """
    alpha = 1.0 - confidence

    def excess(g2: float) -> float:
        return coherence_cdf(target, g2, averages) - alpha

    hi = 1.0 - 1e-12
    if excess(hi) > 0:  # not reachable at any level below coherence 1
        return hi
    if excess(target) <= 0:  # never design below the target itself (no use of the bias)
        return target
    return float(optimize.brentq(excess, target, hi, xtol=1e-12, rtol=1e-10))


# ============================================================================================
# The design
# ============================================================================================
@dataclass(frozen=True)
class DofDesign:
    """The noise excitation of one DOF and what it is predicted to give.

    Attributes
    ----------
    dof : str
        Excited DOF.
    channel : str
        Its ``_EXC`` test point, e.g. ``C1:SUS-ETMX_SUSPOS_EXC``.
    responses : tuple of str
        DOFs whose ``IN1`` must be coherent with the excitation.
    f_hz : ndarray
        Measurement bins in the band (multiples of the resolution `bw`).
    noise_asd : ndarray, shape (len(f_hz), len(responses))
        ``IN1`` noise without excitation (um or urad per rtHz).
    transfer : ndarray, shape (len(f_hz), len(responses))
        ``|IN1_r / EXC_dof|``.
    narrowband_asd : ndarray
        ``sqrt(g2 / (1 - g2)) N_r / |T_r|`` at each bin, the largest over `responses`: the
        requirement if a bin saw only its own frequency.
    required_asd : ndarray
        What the shape covers at each bin: the requirement with the window's leakage (the
        noise and response the Hann window of a bin averages over), raised where a fit fell
        short.
    design_asd : ndarray
        ASD of the designed excitation in each bin (>= `required_asd`).
    coherence : ndarray
        Predicted true coherence of each bin's windowed spectra (the least over
        `responses`); >= the design coherence.
    zpk : ZPK
        The shape, s-plane roots in rad/s: its magnitude is the excitation ASD.
    foton : str
        The same as a foton design string (``ExcitationRequest.shape``).
    order : int
        Real zero/pole pairs of the core fit.
    rms : float
        RMS of the excitation (the request's ``amp``).
    peak : float
        Expected peak, ``NOISE_PEAK_SIGMAS x rms``, as :func:`~twind.excitation.check`
        counts it.
    request : ExcitationRequest
        A noise request ready for ``twind inject`` (accepted by ``check`` within the limits).
    """

    dof: str
    channel: str
    responses: tuple[str, ...]
    f_hz: NDArray[np.float64]
    noise_asd: NDArray[np.float64]
    transfer: NDArray[np.float64]
    narrowband_asd: NDArray[np.float64]
    required_asd: NDArray[np.float64]
    design_asd: NDArray[np.float64]
    coherence: NDArray[np.float64]
    zpk: ZPK
    foton: str
    order: int
    rms: float
    peak: float
    request: ExcitationRequest

    @property
    def ideal_rms(self) -> float:
        """RMS of an excitation exactly at `required_asd` in the band and zero outside: the
        least any shape could have (a rational one must leak out of the band)."""
        bw = float(self.f_hz[1] - self.f_hz[0]) if self.f_hz.size > 1 else 1.0
        return math.sqrt(float(np.sum(self.required_asd**2)) * bw)

    def asd(self, f_hz: ArrayLike) -> NDArray[np.float64]:
        """ASD of the designed excitation (EXC units per rtHz) at any frequencies."""
        return np.abs(self.zpk.response(f_hz))

    def inject_command(self) -> str:
        """The ``twind inject`` command line that starts this excitation."""
        r = self.request
        args = ["twind", "inject", r.channel, "noise", "--amp", f"{r.amp:.6g}", "--shape",
                str(r.shape), "--duration",
                f"{r.duration:g}", "--ramp", f"{r.ramp:g}", "--seed", str(r.seed)]
        return shlex.join(args)

    def to_json(self) -> dict[str, Any]:
        """The design as JSON: shape (foton and zpk), levels, request and per-bin prediction."""
        def roots(r: NDArray[np.complex128]) -> list[list[float]]:
            return [[float(x.real), float(x.imag)] for x in r / (2 * np.pi)]

        return {
            "dof": self.dof, "channel": self.channel, "responses": list(self.responses),
            "foton": self.foton,
            "zpk": {"zeros_hz": roots(self.zpk.zeros), "poles_hz": roots(self.zpk.poles),
                    "gain": self.zpk.gain,
                    "convention": "H(s) = gain * prod(s - 2 pi z) / prod(s - 2 pi p), s in "
                                  "rad/s, roots [re, im] in Hz (foton plane \"f\")"},
            "order": self.order, "rms": self.rms, "peak": self.peak,
            "ideal_rms": self.ideal_rms,
            "request": self.request.to_json(), "inject": self.inject_command(),
            "bins": {"f_hz": self.f_hz.tolist(), "narrowband_asd": self.narrowband_asd.tolist(),
                     "required_asd": self.required_asd.tolist(),
                     "design_asd": self.design_asd.tolist(),
                     "coherence": self.coherence.tolist()},
        }


@dataclass(frozen=True)
class CoherenceDesign:
    """Excitations of one or more DOFs (each measured on its own) reaching a coherence.

    Attributes
    ----------
    optic : str
    band : tuple of float
        Lowest and highest frequency (Hz) that must be coherent.
    target : float
        Coherence the measurement must show in every bin of the band.
    design_coherence : float
        True coherence designed for: `target` plus the estimator margin (module notes).
    averages : int
        Non-overlapping segments of ``1/bw`` seconds the measurement averages.
    bw : float
        Frequency resolution (Hz).
    confidence : float
        Probability that one bin's estimate reaches `target`.
    limits : Limits
        Peak and RMS limits of the ``_EXC`` channels.
    dofs : dict of str to DofDesign
        One design per excited DOF, in the order asked.
    """

    optic: str
    band: tuple[float, float]
    target: float
    design_coherence: float
    averages: int
    bw: float
    confidence: float
    limits: Limits
    dofs: dict[str, DofDesign] = field(default_factory=dict)

    @property
    def measurement_s(self) -> float:
        """Seconds of data the averages need (after the excitation's ramp)."""
        return self.averages / self.bw

    def to_json(self) -> dict[str, Any]:
        """Everything, JSON-ready."""
        return {"mode": "coherence", "optic": self.optic, "band_hz": list(self.band),
                "target": self.target, "design_coherence": self.design_coherence,
                "averages": self.averages, "bw_hz": self.bw, "confidence": self.confidence,
                "measurement_s": self.measurement_s,
                "limits": {"peak": self.limits.peak, "rms": self.limits.rms},
                "dofs": {d: x.to_json() for d, x in self.dofs.items()}}

    def summary(self) -> list[str]:
        """Human-readable lines: one block per DOF."""
        lo, hi = self.band
        lines = [(f"{self.optic}: coherence >= {self.target:g} in {lo:g}-{hi:g} Hz at "
                  f"{self.bw:g} Hz resolution (Hann) with {self.averages} averages "
                  f"({self.measurement_s:g} s); designed for a true coherence of "
                  f"{self.design_coherence:.3f} (each bin reaches {self.target:g} with "
                  f"probability {self.confidence:g})")]
        for d in self.dofs.values():
            worst = int(np.argmin(d.coherence))
            lines += [
                (f"{d.dof} -> IN1 of {', '.join(d.responses)}: RMS {d.rms:.4g} (limit "
                 f"{self.limits.rms:g}), peak {d.peak:.4g} = {NOISE_PEAK_SIGMAS:g} x RMS "
                 f"(limit {self.limits.peak:g})"),
                (f"  predicted coherence >= {d.coherence[worst]:.3f} (at {d.f_hz[worst]:g} Hz); "
                 f"core order {d.order}; RMS {d.rms / d.ideal_rms:.2f} x that of an ideal "
                 "band-limited excitation at the requirement"),
                f"  foton: {d.foton}",
                f"  inject: {d.inject_command()}",
            ]
        return lines


def design_coherent(optic_cfg: OpticConfig, dofs: Sequence[str] | str,
                    band: tuple[float, float], target: float = 0.7, averages: int = 10,
                    bw: float = 0.01, limits: Limits | None = None, *,
                    responses: str = "own", confidence: float = 0.95, ifo: str = "C1",
                    seed: int = 0, max_order: int = 4) -> CoherenceDesign:
    """Design noise excitations that make ``IN1`` coherent with ``EXC`` across a band.

    Parameters
    ----------
    optic_cfg : OpticConfig
        The optic: its loop (the model) and its noise.
    dofs : str or sequence of str
        DOFs to excite, each in its own measurement.
    band : (float, float)
        Lowest and highest frequency (Hz) that must be coherent.
    target : float
        Coherence to reach in every bin of the band, 0 < target < 1.
    averages : int
        Non-overlapping averages of the measurement, >= 2.
    bw : float
        Frequency resolution of the measurement (Hz): Hann-windowed segments of ``1/bw``
        seconds; the bins are its multiples.
    limits : Limits, optional
        The ``_EXC`` limits (default a twin's, :data:`~twind.excitation.checks.DEFAULT_LIMITS`).
    responses : {"own", "all"}
        ``"own"``: the excited DOF's ``IN1`` must be coherent; ``"all"``: the ``IN1`` of every
        DOF in `dofs` (the largest requirement wins).
    confidence : float
        Probability that one bin's estimate reaches `target` (sets the margin, see the
        module notes).
    ifo : str
        Interferometer prefix of the channel names.
    seed : int
        Seed of the noise request.
    max_order : int
        Most real zero/pole pairs in the core of the shape.

    Returns
    -------
    CoherenceDesign

    Raises
    ------
    ExcitationDesignError
        For a bad setting (naming it), disabled noise, a response that does not see the
        excitation, a bin where ``IN1/EXC`` turns too fast for any level to reach the
        target (a notch, a resonance narrower than the resolution), or an excitation that
        would exceed a limit (naming the limit, the level needed and the limit's value).
    """
    if limits is None:
        limits = DEFAULT_LIMITS
    dof_list = [dofs] if isinstance(dofs, str) else list(dofs)
    rate = float(optic_cfg.sus.sample_rate_hz)
    lo, hi = _check_settings(dof_list, band, target, averages, bw, responses, confidence,
                             rate, max_order)
    if not optic_cfg.noise.enabled:
        msg = (f"{optic_cfg.name}: the noise is disabled ({optic_cfg.source}), so any "
               "excitation is fully coherent; there is nothing to design")
        raise ExcitationDesignError(msg)
    g2 = design_coherence(target, averages, confidence)
    k0, k1 = math.ceil(lo / bw - 1e-9), math.floor(hi / bw + 1e-9)
    window = _Window.around(np.arange(k0, k1 + 1) * bw, bw)
    loop = optic_cfg.loop()
    out: dict[str, DofDesign] = {}
    for dof in dof_list:
        resp = (dof,) if responses == "own" else tuple(dof_list)
        out[dof] = _design_dof(optic_cfg, loop, dof, resp, window, (lo, hi), g2, limits,
                               rate, ifo, seed, max_order, averages, target)
    return CoherenceDesign(optic_cfg.name, (lo, hi), target, g2, int(averages), bw, confidence,
                           limits, out)


def _check_settings(dofs: list[str], band: tuple[float, float], target: float, averages: int,
                    bw: float, responses: str, confidence: float, rate: float,
                    max_order: int) -> tuple[float, float]:
    def fail(msg: str) -> ExcitationDesignError:
        return ExcitationDesignError(msg)

    if not dofs:
        raise fail("no DOF to excite; give one or more of " + ", ".join(DOFS))
    for d in dofs:
        if d not in DOFS:
            raise fail(f"unknown DOF {d!r}; expected one of {', '.join(DOFS)}")
    if len(set(dofs)) != len(dofs):
        raise fail(f"a DOF is given twice in {dofs}")
    try:
        lo, hi = (float(x) for x in band)
    except (TypeError, ValueError):
        raise fail(f"band must be two frequencies (Hz), got {band!r}") from None
    if not (0 < lo < hi < rate / 2) or not math.isfinite(hi):
        raise fail(f"band {lo:g}-{hi:g} Hz must satisfy 0 < low < high < Nyquist "
                   f"({rate / 2:g} Hz)")
    if not (0 < target < 1):
        raise fail(f"the target coherence must be between 0 and 1 (exclusive), got {target!r}")
    if not (0 < confidence < 1):
        raise fail(f"confidence must be between 0 and 1 (exclusive), got {confidence!r}")
    if isinstance(averages, bool) or int(averages) != averages or averages < 2:
        raise fail(f"averages must be an integer >= 2 (one segment always shows coherence 1), "
                   f"got {averages!r}")
    if not (bw > 0 and math.isfinite(bw)):
        raise fail(f"the resolution bw must be a positive number of Hz, got {bw!r}")
    if math.floor(hi / bw + 1e-9) < math.ceil(lo / bw - 1e-9):
        raise fail(f"the band {lo:g}-{hi:g} Hz holds no bin of the {bw:g} Hz resolution")
    if lo < bw:
        raise fail(f"the band starts at {lo:g} Hz, below the {bw:g} Hz resolution; lower bw")
    if responses not in RESPONSES:
        raise fail(f"responses must be one of {', '.join(RESPONSES)}, got {responses!r}")
    if not (isinstance(max_order, int) and 0 <= max_order <= 6):
        raise fail(f"max_order must be an integer 0..6, got {max_order!r}")
    return lo, hi


@dataclass(frozen=True)
class _Window:
    """A grid a quarter bin apart around the bins, and the Hann window's leakage on it.

    The Welch estimate at a bin averages the spectra around it with the window's power
    response (:func:`hann_power`); the coherence of the windowed Fourier coefficients, which
    Carter's distribution is about, is therefore
    ``|<T A^2>|^2 / (<A^2> <|T|^2 A^2 + N^2>)`` with ``<.>`` that average.  Negative
    frequencies (reached by the lowest bins) hold the mirror image of the positive ones.
    """

    bins: NDArray[np.float64]
    bw: float
    f: NDArray[np.float64]  # signed grid frequencies
    kernel: NDArray[np.float64]  # normalised to unit sum
    at: NDArray[np.int64]  # grid index of each bin

    @classmethod
    def around(cls, bins: NDArray[np.float64], bw: float) -> _Window:
        reach, step = WINDOW_REACH, GRID_STEP
        n = step * (bins.size - 1 + 2 * reach) + 1
        f = bins[0] - reach * bw + np.arange(n) * (bw / step)
        x = np.arange(-reach * step, reach * step + 1) / step
        kernel = hann_power(x)
        return cls(bins, bw, f, kernel / kernel.sum(),
                   reach * step + step * np.arange(bins.size))

    @property
    def f_abs(self) -> NDArray[np.float64]:
        """|f|, kept off 0 Hz (an eighth of a grid step)."""
        step = self.f[1] - self.f[0]
        return np.maximum(np.abs(self.f), step / 8)

    def smooth(self, v: NDArray) -> NDArray:
        """Window average of `v` (grid along axis 0) at every grid point."""
        v2 = v.reshape(v.shape[0], -1)
        out = np.stack([np.convolve(v2[:, i], self.kernel, mode="same")
                        for i in range(v2.shape[1])], axis=1)
        return out.reshape(v.shape)

    def coherence(self, T: NDArray, N2: NDArray, A2: NDArray) -> tuple[NDArray, NDArray]:
        """Coherence at the bins, and its ceiling without noise (window smearing of T).

        `T` (grid, responses) complex, `N2` noise PSD (grid, responses), `A2` excitation
        PSD (grid,).
        """
        sxx = self.smooth(A2)[self.at, None]
        sxy = self.smooth(T * A2[:, None])[self.at]
        ssig = self.smooth(np.abs(T) ** 2 * A2[:, None])[self.at]
        snn = self.smooth(N2)[self.at]
        c = np.abs(sxy) ** 2 / sxx
        return c / (ssig + snn), c / ssig


def hann_power(x: ArrayLike) -> NDArray[np.float64]:
    """Power response of a Hann window `x` bins from its centre (1 at 0).

    The window's transform is ``0.5 sinc(x) + 0.25 sinc(x - 1) + 0.25 sinc(x + 1)``.
    """
    x = np.asarray(x, dtype=float)
    w = 0.5 * np.sinc(x) + 0.25 * np.sinc(x - 1.0) + 0.25 * np.sinc(x + 1.0)
    return (w / 0.5) ** 2


def _design_dof(optic_cfg: OpticConfig, loop: DampingLoop, dof: str, resp: tuple[str, ...],
                win: _Window, band: tuple[float, float], g2: float, limits: Limits,
                rate: float, ifo: str, seed: int, max_order: int, averages: int,
                target: float) -> DofDesign:
    channel = dof_channel(ifo, optic_cfg.name, dof, "EXC")
    lo, hi = band
    j, rows = DOFS.index(dof), [DOFS.index(r) for r in resp]
    f_abs = win.f_abs
    T = loop.responses(f_abs)["closed_loop_IN1_per_EXC"][:, rows, j]
    T[win.f < 0] = T[win.f < 0].conj()
    N2 = in1_noise_asd(optic_cfg, f_abs, loop)[:, rows] ** 2
    tol = 1e-9 * (hi - lo)
    inband = (win.f >= lo - tol) & (win.f <= hi + tol)
    tmag = np.abs(T[inband])
    bad = tmag <= 1e-12 * max(float(np.abs(T).max(initial=0.0)), 1e-300)
    if np.any(bad):
        i, k = np.argwhere(bad)[0]
        msg = (f"{optic_cfg.name}: IN1 of {resp[k]} does not respond to {dof}_EXC at "
               f"{win.f[inband][i]:g} Hz (|IN1/EXC| = {tmag[i, k]:.3g}); no excitation makes "
               "it coherent (leave it out of the responses or the band)")
        raise ExcitationDesignError(msg)
    snr = g2 / (1.0 - g2)
    # first guess: the textbook requirement with the noise and |T|^2 the window sees
    with np.errstate(divide="ignore", invalid="ignore"):
        need0 = np.sqrt(snr * win.smooth(N2) / win.smooth(np.abs(T) ** 2))[inband].max(axis=1)
    f_band = win.f[inband]
    mult = np.ones(f_band.size)
    for _ in range(MAX_REFITS):
        fit = _fit_shape(f_band, need0 * mult, band, rate, max_order)
        A2 = np.abs(parse_design(fit.foton, rate).response(f_abs)) ** 2
        coh, ceiling = win.coherence(T, N2, A2)
        if np.any(ceiling <= g2):
            i, k = np.unravel_index(int(np.argmin(ceiling)), ceiling.shape)
            msg = (f"{optic_cfg.name}: IN1 of {resp[k]} / {dof}_EXC changes too fast across the "
                   f"{win.bw:g} Hz bin at {win.bins[i]:g} Hz (a zero or a sharp resonance): "
                   f"even without noise its coherence would be {ceiling[i, k]:.3f} < "
                   f"{g2:.3f}; use a finer resolution (--bw) or leave it out of the band")
            raise ExcitationDesignError(msg)
        # the uniform scale that brings each bin to g2: coh(c) = ceiling / (1 + r / c^2)
        r = ceiling / coh - 1.0
        scale = np.sqrt(r / (ceiling / g2 - 1.0)).max(axis=1)
        if np.all(scale <= 1.02):  # the last few percent by the uniform scale below
            break
        mult *= np.interp(f_band, win.bins, np.maximum(scale, 1.0) * 1.001)
    if scale.max() > 1.0:
        # short by a little (or, after the last refit, by more): scale the whole shape up
        fit = dataclasses.replace(fit, gain=_round_up(fit.gain * float(scale.max()) * 1.0001))
    foton = fit.foton
    zpk = parse_design(foton, rate)
    A2 = np.abs(zpk.response(f_abs)) ** 2
    coh = win.coherence(T, N2, A2)[0].min(axis=1)
    shape = noise_shape(foton, rate)
    rms = shape.gain_rms * math.sqrt(rate / 2.0)  # makes |zpk| the ASD of the excitation
    peak = NOISE_PEAK_SIGMAS * rms
    bins = win.bins
    noise = np.sqrt(N2[win.at])
    tb = np.abs(T[win.at])
    narrow = math.sqrt(snr) * noise / tb
    ruling = resp[int(np.argmax(narrow[int(np.argmax(narrow.max(axis=1)))]))]
    what = (f"{dof}: coherence {target:g} of IN1 {ruling} in {lo:g}-{hi:g} Hz (true "
            f"coherence {g2:.3f} for {averages} averages)")
    if rms > limits.rms:
        msg = (f"{what} needs an RMS of {rms:.4g} at {channel}, above its RMS limit "
               f"{limits.rms:.4g}; narrow the band, lower the target or raise --rms")
        raise ExcitationDesignError(msg)
    if peak > limits.peak:
        msg = (f"{what} needs an RMS of {rms:.4g}, i.e. a peak of {peak:.4g} "
               f"({NOISE_PEAK_SIGMAS:g} x RMS for Gaussian noise) at {channel}, above its "
               f"peak limit {limits.peak:.4g}; narrow the band, lower the target or raise "
               "--peak")
        raise ExcitationDesignError(msg)
    ramp = _ramp_s(zpk, loop, band)
    bw = win.bw
    req = ExcitationRequest(channel=channel, waveform="noise", amp=rms, shape=foton,
                            duration=round(averages / bw + 2 * ramp, 6), ramp=ramp, seed=seed)
    try:
        check(req, limits, rate)
    except ExcitationError as err:  # pragma: no cover - the levels were checked above
        msg = f"{what}: the designed request is refused: {err}"
        raise ExcitationDesignError(msg) from None
    required = np.interp(bins, f_band, need0 * mult)
    return DofDesign(dof, channel, resp, bins, noise, tb, narrow.max(axis=1), required,
                     np.sqrt(A2[win.at]), coh, zpk, foton, fit.order, rms, peak, req)


def _ramp_s(zpk: ZPK, loop: DampingLoop, band: tuple[float, float]) -> float:
    """Taper (s) long enough for the shaping filter and the loop to settle: five time
    constants of the slowest pole of the shape, at least 2 s, in whole seconds."""
    slowest = float(np.min(-zpk.poles.real)) if zpk.poles.size else 2 * np.pi * band[0]
    return float(max(2.0, math.ceil(5.0 / slowest)))


# ============================================================================================
# Fitting the shape
# ============================================================================================
@dataclass(frozen=True)
class _Fit:
    order: int
    zeros_hz: tuple[float, ...]
    poles_hz: tuple[float, ...]
    f_hp: float
    f_lp: float
    gain: float
    rms: float

    @property
    def foton(self) -> str:
        return _foton(self.zeros_hz, self.poles_hz, self.f_hp, self.f_lp, self.gain)


def _num(x: float) -> str:
    return f"{float(x):.6g}"


def _round_up(x: float, digits: int = 7) -> float:
    """`x` > 0 rounded up to `digits` significant digits."""
    e = math.floor(math.log10(x)) - digits + 1
    return math.ceil(x / 10.0**e) * 10.0**e


def _foton(zeros: Sequence[float], poles: Sequence[float], f_hp: float, f_lp: float,
           gain: float) -> str:
    """``zpk(core, "n") butter(HighPass) butter(LowPass) gain(g)``: roots in Hz, stable."""
    parts = []
    if zeros or poles:
        parts.append(f"zpk([{';'.join(map(_num, zeros))}],[{';'.join(map(_num, poles))}],1,"
                     '"n")')
    parts.append(f'butter("HighPass",{EDGE_ORDER},{_num(f_hp)})')
    parts.append(f'butter("LowPass",{EDGE_ORDER},{_num(f_lp)})')
    parts.append(f"gain({gain:.7g})")
    return "".join(parts)


def _log_shape(f: NDArray, x: NDArray, n: int, jac: bool = False
               ) -> tuple[NDArray, NDArray | None]:
    """log10 |shape| at `f` for x = [log10 zeros (n), log10 poles (n), log10 f_hp, log10 f_lp].

    Unit gain: the core has DC gain 1, the edge filters a unity pass band.  With `jac`, also
    the derivatives by each parameter, shape (len(f), 2n + 2).
    """
    z, p = 10.0 ** x[:n], 10.0 ** x[n:2 * n]
    m = 2 * EDGE_ORDER
    uz = (f[:, None] / z[None, :]) ** 2
    up = (f[:, None] / p[None, :]) ** 2
    hp = (f / 10.0 ** x[2 * n]) ** m
    lp = (f / 10.0 ** x[2 * n + 1]) ** m
    value = (0.5 * (np.sum(np.log10(1.0 + uz), axis=1) - np.sum(np.log10(1.0 + up), axis=1))
             + 0.5 * (np.log10(hp / (1.0 + hp)) - np.log10(1.0 + lp)))
    if not jac:
        return value, None
    d = np.empty((f.size, 2 * n + 2))
    d[:, :n] = -uz / (1.0 + uz)
    d[:, n:2 * n] = up / (1.0 + up)
    d[:, 2 * n] = -0.5 * m / (1.0 + hp)
    d[:, 2 * n + 1] = 0.5 * m * lp / (1.0 + lp)
    return value, d


def _fit_shape(f: NDArray, need: NDArray, band: tuple[float, float], rate: float,
               max_order: int) -> _Fit:
    """Lowest-RMS shape of 0..max_order core pairs that covers `need` at `f` (in the band).

    For each order: a least-squares fit of the log magnitude to the requirement (from two
    starts, zeros or poles first), then a minimisation of the RMS once scaled to cover the
    requirement, with a soft maximum for the scale (TNC with analytic gradients: L-BFGS-B
    spends most of its time in threaded BLAS calls on 10 x 10 problems); the exact maximum
    over every point of `f` scales the result.  Orders stop once two more pairs of roots
    lowered the RMS by less than 3 %.
    """
    lo, hi = band
    target = np.log10(need)
    # where the requirement is evaluated while fitting; the final scale uses every point of f
    ff = np.geomspace(lo, hi, 240)
    tf = np.interp(np.log(ff), np.log(f), target)
    # RMS integral grid: the ASD falls as f^4 below and as f^-4 above the band
    fi = np.geomspace(lo / 300, min(rate / 2, hi * 300), 700)
    dlnf = math.log(fi[1] / fi[0])
    ln_lo, ln_hi = math.log10(lo), math.log10(hi)
    fits: list[_Fit] = []
    for n in range(max_order + 1):
        # roots from a decade below to a decade above the band; edges outside the band
        lower = np.array([ln_lo - 1] * 2 * n + [ln_lo - 1.5, ln_hi])
        upper = np.array([ln_hi + 1] * 2 * n + [ln_lo, ln_hi + 1.5])

        def objective(x: NDArray, beta: float, n: int = n) -> tuple[float, NDArray]:
            """log10 of the RMS once scaled to cover the requirement (soft max), gradient."""
            s, ds = _log_shape(ff, x, n, jac=True)
            e = beta * (tf - s)
            w = np.exp(e - e.max())
            scale = (e.max() + math.log(w.sum())) / beta
            w /= w.sum()
            si, dsi = _log_shape(fi, x, n, jac=True)
            p = 10.0 ** (2 * (si - si.max())) * fi
            value = scale + si.max() + 0.5 * math.log10(float(p.sum()) * dlnf)
            grad = -(w @ ds) + (p / p.sum()) @ dsi
            return value, grad

        starts = []
        mid = np.linspace(ln_lo, ln_hi, 2 * n + 2)[1:-1]
        edges = [ln_lo - 0.2, ln_hi + 0.2]
        for first in (0, 1) if n else (0,):
            x0 = np.concatenate([mid[first::2], mid[1 - first::2], edges])
            if n:
                ls = optimize.least_squares(
                    lambda x, n=n: _log_shape(ff, x[:-1], n)[0] + x[-1] - tf,
                    np.concatenate([x0, [float(np.mean(tf))]]),
                    jac=lambda x, n=n: np.hstack([_log_shape(ff, x[:-1], n, jac=True)[1],
                                                  np.ones((ff.size, 1))]),
                    bounds=(np.append(lower, -np.inf), np.append(upper, np.inf)),
                    max_nfev=200)
                x0 = ls.x[:-1]
            x = x0
            for beta in (30.0, 300.0):  # in 1/decade: coarse, then within ~0.01 decade
                res = optimize.minimize(objective, x, args=(beta,), jac=True,
                                        method="TNC", bounds=list(zip(lower, upper)),
                                        options={"maxfun": 600})
                x = res.x
            starts.append(x)
        for x in starts:
            # frequencies to 6 significant digits (a readable design string), then the gain
            # that covers the requirement with them, rounded up
            x = np.log10([float(f"{v:.6g}") for v in 10.0 ** x])
            scale = float(np.max(target - _log_shape(f, x, n)[0]))
            gain = _round_up(10.0 ** scale * (1.0 + 1e-5))
            s_int = _log_shape(fi, x, n)[0] + math.log10(gain)
            rms = math.sqrt(float(np.sum(10.0 ** (2 * s_int) * fi)) * dlnf)
            fits.append(_Fit(n, tuple(sorted(10.0 ** x[:n])),
                             tuple(sorted(10.0 ** x[n:2 * n])),
                             10.0 ** x[2 * n], 10.0 ** x[2 * n + 1], gain, rms))
        best = [min(ft.rms for ft in fits if ft.order == k) for k in range(n + 1)]
        if n >= 2 and min(best[-2:]) > 0.97 * min(best[:-2]):
            break  # two more pairs of roots bought nothing
    least = min(ft.rms for ft in fits)
    # the lowest order within 3 % of the best RMS: fewer roots, same excitation
    return min((ft for ft in fits if ft.rms <= 1.03 * least), key=lambda ft: (ft.order, ft.rms))
