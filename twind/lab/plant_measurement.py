"""A virtual measurement of a state-space optic: its engine excited as diaggui excites a test
point, Welch's transfer functions written as diaggui saves them, in the site's names.

This is what proves the diagnosis of a plant known by its matrices: the data come from the
time-domain engine (:class:`~twind.simulation.statespace.StateSpaceEngine`) and Welch's
estimate (scipy.signal), never from the frequency-domain model the diagnosis fits, and a
change hidden in them is made to the model's own matrices (:func:`moved`, Brauer's update),
not to its modal form.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import signal
from scipy.optimize import least_squares

from twind.analysis.estimation.diaggui import write_fft_measurement
from twind.config.statespace import StateSpaceOptic
from twind.model.statespace import StateSpace

BW_HZ = 1 / 128
"""diaggui's resolution in KAGRA's SRM measurement (its 0.01 Hz asked, rounded to 2^-7)."""


def moved(model: StateSpace, f_hz: float, factor: float, q: float | None = None
          ) -> tuple[StateSpace, float]:
    """`model` with the pole pair nearest `f_hz` moved to `factor` times its frequency (and
    to quality factor `q`, if given), every other pole where it was.

    Brauer's theorem: for a right eigenvector ``v`` of ``A`` (eigenvalue ``l``) and a left
    one ``u``, ``A + (l' - l) v u^T / (u^T v)`` has ``l'`` in place of ``l`` and the same
    other eigenvalues; with the conjugate pair's update added the matrix stays real. The
    mode's residues keep their shapes (its numerator changes with it, unlike the modal
    refit the diagnosis makes).

    Returns
    -------
    StateSpace
    float
        The mode's new frequency (Hz).
    """
    w, vr = np.linalg.eig(model.a)
    wl, vl = np.linalg.eig(model.a.T)
    k = int(np.argmin(np.abs(np.abs(w) / (2 * math.pi) - f_hz) + (w.imag <= 0)))
    lam = w[k]
    u = vl[:, int(np.argmin(np.abs(wl - lam)))]
    wn = abs(lam) * factor
    qn = q if q is not None else abs(lam) / (-2 * lam.real)
    new = -wn / (2 * qn) + 1j * wn * math.sqrt(max(1 - 1 / (4 * qn * qn), 0.0))
    update = (new - lam) * np.outer(vr[:, k], u) / (u @ vr[:, k])
    return replace(model, a=model.a + 2 * update.real), float(wn / (2 * math.pi))


def measure(optic: StateSpaceOptic, drive: str, path: str | Path, *,
            model: StateSpace | None = None, averages: int = 5, bw_hz: float = BW_HZ,
            rate_hz: float = 512.0, amplitude: float = 1.0, noise: float = 1e-4,
            closed: Sequence[str] | None = (), stop_hz: float = 100.0, seed: int = 0) -> Path:
    """Excite `drive` of `optic` with white noise and write diaggui's FFT measurement.

    Parameters
    ----------
    optic : StateSpaceOptic
    drive : str
        A TEST point (``TM_TEST_P``) or a damping loop (``IM_DAMP_L``): its EXC is channel A.
    path : path
        The XML to write (never overwritten).
    model : StateSpace, optional
        The plant the engine integrates instead of the optic's (a changed one, the truth).
    averages : int
        Welch averages (segments of ``1 / bw_hz``, half overlapped).
    bw_hz : float
        Resolution.
    rate_hz : float
        The engine's rate (its zero-order hold is a delay of half a cycle).
    amplitude : float
        The excitation's RMS (model units).
    noise : float
        Each readback's white noise ASD over the excitation's (per rtHz).
    closed : sequence of str or None
        Damping loops closed (None: every loop with a controller).
    stop_hz : float
        The last frequency written (diaggui's StopFrequency).
    seed : int

    Returns
    -------
    Path
    """
    truth = replace(optic, model=model) if model is not None else optic
    exc_asd = amplitude / math.sqrt(rate_hz / 2)
    engine = truth.engine(rate_hz=rate_hz, noise={r: noise * exc_asd for r in optic.readbacks},
                          seed=seed, closed=closed)
    nper = int(round(rate_hz / bw_hz))
    n = nper * (averages + 1) // 2
    rng = np.random.default_rng(seed + 1)
    settle = int(rate_hz * 100)  # the loops' and the pendulums' transients: 100 s
    x = amplitude * rng.standard_normal(settle + n)
    block = engine.step(settle + n, {f"{drive}_EXC": x})
    names = [c for c in block.channels if c != f"{drive}_EXC" and not c.endswith("_EXC")]
    if drive not in optic.loops:
        names = [c for c in names if c in optic.readbacks]
    exc = block.channels[f"{drive}_EXC"][settle:]
    f, pxx = signal.welch(exc, fs=rate_hz, window="hann", nperseg=nper)
    tfs, cohs = [], []
    for name in names:
        y = block.channels[name][settle:]
        _, pxy = signal.csd(exc, y, fs=rate_hz, window="hann", nperseg=nper)
        _, pyy = signal.welch(y, fs=rate_hz, window="hann", nperseg=nper)
        tfs.append(pxy / pxx)
        with np.errstate(divide="ignore", invalid="ignore"):
            cohs.append(np.nan_to_num(np.abs(pxy) ** 2 / (pxx * pyy)))
    keep = f <= stop_hz
    return write_fft_measurement(path, optic.channel(f"{drive}_EXC"),
                                 [optic.channel(c) for c in names], f[keep], pxx[keep],
                                 np.array(tfs)[:, keep], np.array(cohs)[:, keep], averages,
                                 rate_hz)


def peak(f_hz: NDArray[np.float64], h: NDArray[np.complex128], near_hz: float,
         width: float = 0.1) -> float:
    """An independent fit of a resonance's frequency: a second-order section plus a constant
    and a slope, fitted by least squares to ``h`` within ``width`` (relative) of
    `near_hz`, started at the largest magnitude there and kept inside that window. Knows
    nothing of any model.

    Returns
    -------
    float
        The section's frequency (Hz).
    """
    sel = (f_hz > near_hz * (1 - width)) & (f_hz < near_hz * (1 + width)) & np.isfinite(h)
    f, y = f_hz[sel], h[sel]
    f0 = float(f[np.argmax(np.abs(y))])

    def model(p: NDArray) -> NDArray:
        s = 2j * np.pi * f
        w = 2 * np.pi * p[0]
        return ((p[2] + 1j * p[3]) / (s * s + s * w / p[1] + w * w) + p[4] + 1j * p[5]
                + (p[6] + 1j * p[7]) * (f - f0))

    def res(p: NDArray) -> NDArray:
        r = (model(p) - y) / np.abs(y).max()
        return np.concatenate([r.real, r.imag])

    w0 = 2 * np.pi * f0
    a0 = y[np.argmax(np.abs(y))] * 1j * w0 * w0 / 50
    lo = [f[0], 0.5, -np.inf, -np.inf, -np.inf, -np.inf, -np.inf, -np.inf]
    hi = [f[-1], 1e7, np.inf, np.inf, np.inf, np.inf, np.inf, np.inf]
    sol = least_squares(res, [f0, 50.0, a0.real, a0.imag, 0, 0, 0, 0], bounds=(lo, hi),
                        x_scale="jac")
    return float(sol.x[0])
