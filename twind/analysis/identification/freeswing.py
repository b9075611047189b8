"""The free-swinging health check: an optic's modes, their Qs and the OSEM input matrix from a
ringdown, as the 40m measures them.

With the damping loops off, a kicked optic rings down in its normal modes; every OSEM sees
each mode with an amplitude fixed by the mode's shape and the OSEM's own gain. The five OSEM
signals are low-passed and decimated, and the matrix pencil method (Hua & Sarkar 1990) over
all of them at once gives each mode's frequency and decay time (so its Q) and its complex
amplitude in every OSEM. From those amplitudes come the input matrix that puts each mode in
one DOF (what the 40m's diagonalisation scripts compute) and each OSEM's gain relative to the
others (an OSEM imbalance), given the mode shapes of the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, signal
from scipy.optimize import least_squares, minimize_scalar

from twind import DOFS, OSEMS
from twind.analysis.identification.modes import FITTED, fit_modes, modes_hz, normal_modes, with_params
from twind.config import OpticConfig
from twind.errors import TwindError
from twind.model.plant import Plant
from twind.simulation.engine import Engine

DECIMATED_HZ = 4.0
"""Rate the OSEM signals are analysed at: above twice the highest pendulum mode, far below
the bounce and roll modes the decimation filters out."""

ORDER = 40
"""Poles the pencil fits: the four modes' conjugate pairs and room for the noise."""

EDGE_S = 20.0
"""Seconds cut at each end of the band-passed signals (the filter's transients)."""

REALISATIONS = 400
"""Simulated noise realisations the standard errors of the frequencies and Qs come from
(their own relative precision is about ``1 / sqrt(2 * REALISATIONS)``, 3.5 %)."""

HALF_S = 200.0
"""The shortest half of a ringdown fitted apart to check that the modes held still (s)."""

HALVES_SIGMA = 3.0
"""A difference between the halves beyond this many standard errors is reported."""

LINE_WIDTHS = 10.0
"""Half-width of a mode's line, in line widths ``f / Q``, for the standard errors: where its
noise-driven motion is measured, and what the sensor noise's spectrum bridges."""

SMOOTH_BINS = 31
"""Frequency bins averaged for the sensor noise's cross-spectral matrices."""

BAND = (0.25, 1.6)
"""The band kept around the pendulum modes (Hz): the drifts below and the noise above go."""


@dataclass(frozen=True)
class FreeSwing:
    """Modes of an optic from its free ringdown.

    Attributes
    ----------
    optic : str
    frequency_hz, q : dict of str to float
        Each mode's frequency and quality factor, by the DOF it was matched to.
    frequency_sigma_hz, q_sigma : dict of str to float
        Their standard errors, from the ringdown's own noise (:func:`analyse`).
    amplitude : ndarray, shape (5, 4)
        Complex amplitude of each mode (columns, in DOFS order) in each OSEM (rows, OSEMS).
    input_matrix : ndarray, shape (4, 5)
        The OSEM-to-DOF matrix that puts each mode in its DOF alone, each row scaled like the
        configured one (``configured``).
    configured : ndarray, shape (4, 5)
    osem_gains : dict of str to float
        Each face OSEM's gain relative to their mean, from the model's mode shapes (the
        SIDE OSEM sees one mode only, so its gain and that mode's amplitude are one number).
    model_hz : dict of str to float
        The configured model's eigenfrequencies.
    halves : dict of str to (float, float), or None
        Per mode, the first half's frequency and Q minus the second's, in their combined
        standard errors: beyond :data:`HALVES_SIGMA` the modes moved during the ringdown
        (drift, amplitude dependence, a glitch) and the standard errors understate the
        errors. None for a ringdown too short to halve.
    """

    optic: str
    frequency_hz: dict[str, float]
    q: dict[str, float]
    frequency_sigma_hz: dict[str, float]
    q_sigma: dict[str, float]
    amplitude: NDArray[np.complex128]
    input_matrix: NDArray[np.float64]
    configured: NDArray[np.float64]
    osem_gains: dict[str, float]
    model_hz: dict[str, float]
    halves: dict[str, tuple[float, float]] | None = None

    def lines(self) -> list[str]:
        """The modes, the OSEM gains and both input matrices, for a person."""
        rows = [f"{self.optic} free-swinging modes: DOF, frequency (Hz) +- sigma (mHz), Q +- "
                "sigma, the model's frequency (Hz) and the difference (mHz)"]
        for d in DOFS:
            f, model = self.frequency_hz[d], self.model_hz[d]
            rows.append(f"  {d:4} {f:.6f} +- {1e3 * self.frequency_sigma_hz[d]:<7.2g} "
                        f"Q {self.q[d]:4.0f} +- {self.q_sigma[d]:<5.2g} model {model:.6f} "
                        f"({1e3 * (f - model):+.4f})")
        if self.halves is not None:
            rows.append("  first half - second, in sigma: " + ", ".join(
                f"{d} f {x[0]:+.1f} Q {x[1]:+.1f}" for d, x in self.halves.items()))
            if max(abs(x) for pair in self.halves.values() for x in pair) > HALVES_SIGMA:
                rows.append(f"  the halves differ beyond {HALVES_SIGMA:g} sigma: the modes "
                            "moved during the ringdown (drift, amplitude dependence, a "
                            "glitch); the standard errors understate the errors")
        rows.append("  OSEM gains (face mean = 1): " + ", ".join(
            f"{o} {g:.3f}" for o, g in self.osem_gains.items()))
        rows.append("  input matrix, diagonalising | configured, each row over the configured "
                    f"row's largest entry ({', '.join(OSEMS)})")
        for i, d in enumerate(DOFS):
            scale = np.abs(self.configured[i]).max()
            rows.append(f"  {d:4} " + " ".join(f"{x / scale:6.3f}" for x in self.input_matrix[i])
                        + " | " + " ".join(f"{x / scale:5.2f}" for x in self.configured[i]))
        return rows

    def to_json(self) -> dict:
        """The ``twind freeswing --json`` object."""
        return {"optic": self.optic, "frequency_hz": self.frequency_hz, "q": self.q,
                "frequency_sigma_hz": self.frequency_sigma_hz, "q_sigma": self.q_sigma,
                "model_hz": self.model_hz,
                "halves_sigma": None if self.halves is None else {
                    d: {"frequency": x[0], "q": x[1]} for d, x in self.halves.items()},
                "osem_gains": self.osem_gains, "osems": list(OSEMS), "dofs": list(DOFS),
                "input_matrix": self.input_matrix.tolist(),
                "configured_input_matrix": self.configured.tolist()}


def ringdown(optic: OpticConfig, duration_s: float = 1000.0, seed: int = 0,
             kick_ct_s: float = 1500.0, plant: Plant | None = None
             ) -> tuple[NDArray[np.float64], float]:
    """A free-swinging measurement on the twin: the damping on, a step into every DOF's EXC
    kicks the optic through its velocity damping (the step times the DOF's gain is
    `kick_ct_s` per coil the DOF drives, so SIDE's one coil kicks as hard as the four face
    coils together), then every damping gain goes to zero and the optic rings down for
    `duration_s` with its noise.

    Parameters
    ----------
    optic : OpticConfig
        The optic, as configured.
    duration_s : float
        Seconds of ringdown.
    seed : int
        Seed of the twin's noise.
    kick_ct_s : float
        The kick per coil (ct s).
    plant : Plant, optional
        Replaces the configured plant (an optic with physics the model leaves out).

    Returns
    -------
    sen : ndarray, shape (5, n)
        The OSEM signals (um) of the ringdown, rows UL, UR, LL, LR, SIDE.
    rate_hz : float
    """
    loop = optic.loop()
    if plant is not None:
        loop.plant = plant
    engine = Engine([loop], {optic.name: optic.noise}, seed=seed,
                    rate_hz=optic.sus.sample_rate_hz)
    rate = engine.rate_hz
    n_kick = int(0.5 * rate)
    coils = np.count_nonzero(loop.plant.output_matrix, axis=0)  # per DOF
    steps = [kick_ct_s * coils.max() / (n * abs(optic.damping[d].gain))
             for d, n in zip(DOFS, coils, strict=True)]
    exc = np.repeat(np.array(steps)[None, :, None], n_kick, axis=2)
    engine.step(n_kick, exc=exc)
    for dof in DOFS:
        engine.set_gain(optic.name, dof, 0.0, 0.0)
    n = int(round(duration_s * rate))
    block = int(16 * rate)
    sen = np.empty((len(OSEMS), n))
    for a in range(0, n, block):
        b = min(n, a + block)
        sen[:, a:b] = engine.step(b - a).sen[0]
    return sen, rate


def analyse(optic: OpticConfig, sen: NDArray[np.float64], rate_hz: float) -> FreeSwing:
    """The modes, Qs, input matrix and OSEM gains of a ringdown.

    Parameters
    ----------
    optic : OpticConfig
        The model the modes are matched to (their names, the configured input matrix).
    sen : ndarray, shape (5, n)
        The five OSEM signals (um), rows UL, UR, LL, LR, SIDE: :func:`ringdown`'s, or a
        real optic's.
    rate_hz : float
        Their rate; any above :data:`DECIMATED_HZ`.

    Returns
    -------
    FreeSwing
        Frequencies and Qs with standard errors, the two halves' differences, the OSEM
        gains and the input matrix that diagonalises them.

    Raises
    ------
    TwindError
        If `sen` is not five signals, the ringdown is too short, or a mode cannot be found.
    """
    sen = np.asarray(sen, dtype=float)
    if sen.ndim != 2 or sen.shape[0] != len(OSEMS):
        msg = f"expected the {len(OSEMS)} OSEM signals ({', '.join(OSEMS)}), got shape {sen.shape}"
        raise TwindError(msg)
    y, dt = _decimate(sen, rate_hz)
    sos = signal.butter(4, BAND, btype="band", fs=1 / dt, output="sos")
    edge = int(EDGE_S / dt)
    if y.shape[1] - 2 * edge < 20 * ORDER:
        msg = (f"a ringdown of {sen.shape[1] / rate_hz:.0f} s is too short to resolve the modes "
               f"(at least {2 * EDGE_S + 20 * ORDER * dt + 10:.0f} s)")
        raise TwindError(msg)
    y = signal.sosfiltfilt(sos, y, axis=1)[:, edge:-edge]  # the band-pass's transients cut
    # every OSEM at one scale, so that SIDE, which one OSEM sees, weighs like the face modes
    scaled = y / y.std(axis=1, keepdims=True)
    z = _pencil(scaled, ORDER)
    z = z[np.abs(z) < 1]  # growing poles are the pencil's room for noise, and overflow
    model = modes_hz(optic)
    plant = optic.loop().plant
    every = _fit(y, z)[0]
    chosen = _match(z, dt, model, plant.input_matrix @ every)
    poles = _refine(scaled, np.array([z[k] for k in chosen.values()]))
    amp = _fit(y, poles)[0]
    f, q = (dict(zip(DOFS, x.tolist(), strict=True)) for x in _modes(poles, dt))
    f_sigma, q_sigma = (dict(zip(DOFS, x.tolist(), strict=True))
                        for x in _sigmas(scaled, poles, dt))
    # the mode shapes of the geometry that gives the measured POS, PIT, YAW: a drifted
    # optic's POS-PIT mixing is not the nominal one's
    solved = fit_modes(optic, {d: f[d] for d in FITTED})
    shapes = _shapes(with_params(optic, solved.after), plant.sensing)
    gains = _osem_gains(amp, shapes)
    return FreeSwing(optic.name, f, q, f_sigma, q_sigma, amp,
                     _input_matrix(amp, plant.input_matrix), plant.input_matrix, gains,
                     model, _halves(scaled, poles, dt))


def _halves(y: NDArray, z: NDArray, dt: float) -> dict[str, tuple[float, float]] | None:
    """Each mode's frequency and Q fitted on the first and on the second half of `y` apart:
    their differences in combined standard errors (None when a half is shorter than
    :data:`HALF_S`)."""
    n = y.shape[1] // 2
    if n * dt < HALF_S:
        return None
    fits = []
    for half in (y[:, :n], y[:, n:]):
        poles = _refine(half, z)
        fits.append((*_modes(poles, dt), *_sigmas(half, poles, dt)))
    (f1, q1, sf1, sq1), (f2, q2, sf2, sq2) = fits
    pulls = zip((f1 - f2) / np.hypot(sf1, sf2), (q1 - q2) / np.hypot(sq1, sq2), strict=True)
    return {d: (float(a), float(b)) for d, (a, b) in zip(DOFS, pulls, strict=True)}


def _decimate(sen: NDArray, rate_hz: float) -> tuple[NDArray, float]:
    """Zero-phase low-pass and decimation to about :data:`DECIMATED_HZ`; the first and last
    few seconds (the filters' transients) dropped."""
    y = sen - sen.mean(axis=1, keepdims=True)
    rate = rate_hz
    while rate / DECIMATED_HZ >= 2:
        q = min(8, int(rate / DECIMATED_HZ))
        y = signal.decimate(y, q, ftype="fir", axis=1, zero_phase=True)
        rate /= q
    edge = int(5 * rate)
    return y[:, edge:-edge], 1.0 / rate


def _pencil(y: NDArray, order: int) -> NDArray[np.complex128]:
    """Signal poles of all channels at once (matrix pencil, Hua & Sarkar 1990)."""
    n = y.shape[1]
    L = min(n // 3, 20 * order)
    rows = np.vstack([np.lib.stride_tricks.sliding_window_view(ch, L + 1) for ch in y])
    _, _, vh = np.linalg.svd(rows, full_matrices=False)
    v = vh[:order].conj().T
    return np.linalg.eigvals(np.linalg.pinv(v[:-1]) @ v[1:])


def _match(z: NDArray, dt: float, model: dict[str, float], in_dof: NDArray) -> dict[str, int]:
    """For each model mode, the decaying pole within 15 % of its frequency that the DOF's
    row of the input matrix sees strongest (`in_dof`: DOF x pole amplitudes)."""
    f = np.angle(z) / (2 * np.pi * dt)
    decay = -np.log(np.abs(z)) / dt
    usable = (f > 0) & (decay > 0)
    chosen: dict[str, int] = {}
    for i, d in enumerate(DOFS):
        cands = [k for k in np.flatnonzero(usable & (np.abs(f - model[d]) < 0.15 * model[d]))
                 if k not in chosen.values()]
        if not cands:
            msg = f"no free mode found near {d}'s {model[d]:.3f} Hz"
            raise TwindError(msg)
        chosen[d] = int(max(cands, key=lambda k: abs(in_dof[i, k])))
    return chosen


def _refine(y: NDArray, z: NDArray) -> NDArray[np.complex128]:
    """The chosen poles fitted again with the four modes alone (variable projection: the
    amplitudes solved linearly at each trial), so that the pencil's extra poles no longer
    share their energy."""
    def residual(p: NDArray) -> NDArray:
        return (y - _fit(y, np.exp(p[: len(z)] + 1j * p[len(z):]))[1]).ravel()

    start = np.concatenate([np.log(np.abs(z)), np.angle(z)])
    fit = least_squares(residual, start, x_scale=np.abs(start) * 1e-3 + 1e-9)
    return np.exp(fit.x[: len(z)] + 1j * fit.x[len(z):])


def _fit(y: NDArray, z: NDArray) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    """Least squares of the channels `y` on the modes `z` and their conjugates: each mode's
    complex amplitude in each channel (channels x modes) and the fitted signals."""
    t = np.arange(y.shape[1])[:, None]
    basis = np.hstack([z[None, :] ** t, np.conj(z)[None, :] ** t])
    coef, *_ = np.linalg.lstsq(basis, y.T.astype(complex), rcond=None)
    return coef[: len(z)].T, np.real(basis @ coef).T


def _modes(z: NDArray, dt: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Frequencies (Hz) and Qs of discrete poles `z` sampled every `dt` seconds."""
    f = np.angle(z) / (2 * np.pi * dt)
    return f, np.pi * f / (-np.log(np.abs(z)) / dt)


def _sigmas(y: NDArray, z: NDArray, dt: float) -> tuple[NDArray, NDArray]:
    """Standard errors of the frequencies and Qs of the modes `z` fitted to `y`, with the
    levels of the ringdown's own noise.

    The fit is the optic's free response from its state at the start; what it leaves is the
    sensor noise and each mode's response to the forces after the start, which grows from
    nothing as the mode takes it up and sits in the mode's line, where the fit absorbs most
    of it (so the residual's own spectrum, resampled, gives errors several times too small).
    The noise is therefore simulated as the physics has it: each mode driven from rest by
    white forces seen in the OSEMs with the mode's measured pattern, its level the one that
    best explains (Whittle likelihood) the residual's spectrum in the mode's line, after the
    fit; and the sensor noise with the residual's cross-spectral matrices away from the
    lines. Each of
    :data:`REALISATIONS` realisations passes through the fit, linearised about the solution
    (the errors are far inside a line width).
    """
    n = y.shape[1]
    amp, fitted = _fit(y, z)
    resid = y - fitted
    jac = _jacobian(amp, z, n)
    solve = np.linalg.pinv(jac)
    pattern = _patterns(amp)
    project = np.linalg.pinv(pattern)  # (modes, channels): each mode's motion from the OSEMs
    f = np.fft.rfftfreq(n, dt)
    f_mode, q_mode = _modes(z, dt)
    lines = np.abs(f[None, :] - f_mode[:, None]) < LINE_WIDTHS * (f_mode / q_mode)[:, None]
    rng = np.random.default_rng(0)

    def through_fit(noise: NDArray) -> tuple[NDArray, NDArray]:
        """The fit's linear step and the residual's per-mode periodograms, per realisation."""
        flat = noise.reshape(REALISATIONS, -1).T
        step = solve @ flat
        left = (flat - jac @ step).T.reshape(noise.shape)
        return step[: 2 * len(z)], np.abs(np.fft.rfft(project @ left, axis=2)) ** 2

    sensor = _gaussian(_off_lines(np.fft.rfft(resid, axis=1), lines.any(axis=0)), n, rng)
    step, sensor_power = through_fit(sensor)
    sensor_power = sensor_power.mean(axis=0)
    observed = np.abs(np.fft.rfft(project @ resid, axis=1)) ** 2
    for k, zk in enumerate(z):
        ar = [1.0, -2 * zk.real, abs(zk) ** 2]
        drive = signal.lfilter([1.0], ar, rng.standard_normal((REALISATIONS, 1, n)), axis=2)
        unit_step, unit_power = through_fit(pattern[:, k][None, :, None] * drive)
        level = _whittle_level(observed[k, lines[k]], unit_power.mean(axis=0)[k, lines[k]],
                               sensor_power[k, lines[k]])
        step += np.sqrt(level) * unit_step
    moved = np.exp(np.log(z)[:, None] + step[: len(z)] + 1j * step[len(z):])
    f_sur, q_sur = _modes(moved, dt)
    return f_sur.std(axis=1, ddof=1), q_sur.std(axis=1, ddof=1)


def _real(amp: NDArray) -> NDArray[np.float64]:
    """Each mode's amplitudes over the channels (columns) made real: turned by the phase of
    the channel that sees the mode most."""
    phase = np.exp(-1j * np.angle(amp[np.argmax(np.abs(amp), axis=0), range(amp.shape[1])]))
    return np.real(amp * phase[None, :])


def _patterns(amp: NDArray) -> NDArray[np.float64]:
    """Each mode's real pattern over the channels (:func:`_real`, columns of unit length)."""
    real = _real(amp)
    return real / np.linalg.norm(real, axis=0, keepdims=True)


def _off_lines(coef: NDArray, lines: NDArray) -> NDArray[np.complex128]:
    """The channels' cross-spectral matrices (bins x channels x channels) from their Fourier
    coefficients `coef` (channels x bins), averaged over neighbouring bins outside the
    `lines` and bridged across them: the sensor noise, correlations included (the cage's
    motion reaches the face OSEMs together), under the modes."""
    outside = np.flatnonzero(~lines)
    cross = coef.T[:, :, None] * np.conj(coef.T[:, None, :])
    smooth = ndimage.uniform_filter1d(cross[outside].real, SMOOTH_BINS, axis=0, mode="nearest") \
        + 1j * ndimage.uniform_filter1d(cross[outside].imag, SMOOTH_BINS, axis=0, mode="nearest")
    bins = np.arange(coef.shape[1])
    flat = smooth.reshape(outside.size, -1)
    bridged = np.array([np.interp(bins, outside, col.real) + 1j * np.interp(bins, outside, col.imag)
                        for col in flat.T]).T
    return bridged.reshape(cross.shape)


def _gaussian(spectrum: NDArray, n: int, rng: np.random.Generator) -> NDArray:
    """:data:`REALISATIONS` Gaussian series whose expected periodograms and cross-periodograms
    are `spectrum` (bins x channels x channels): shape (REALISATIONS, channels, n)."""
    value, vector = np.linalg.eigh(spectrum)
    root = vector * np.sqrt(np.clip(value, 0.0, None))[:, None, :]  # root @ root^H = spectrum
    shape = (REALISATIONS, spectrum.shape[0], spectrum.shape[1])
    white = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / np.sqrt(2)
    coef = np.einsum("bij,sbj->sib", root, white)
    return np.fft.irfft(coef, n=n, axis=2)


def _whittle_level(observed: NDArray, unit: NDArray, floor: NDArray) -> float:
    """The level q of a mode's forces whose expected periodogram ``q unit + floor`` best
    explains the `observed` one (Whittle's likelihood)."""
    def minus_log_likelihood(log_q: float) -> float:
        expected = np.exp(log_q) * unit + floor
        return float(np.sum(np.log(expected) + observed / expected))

    guess = np.log(max(np.sum(observed - floor), 1e-30 * np.sum(floor)) / np.sum(unit))
    fit = minimize_scalar(minus_log_likelihood, bracket=(guess - 1, guess + 1))
    return float(np.exp(fit.x))


def _jacobian(amp: NDArray, z: NDArray, n: int) -> NDArray[np.float64]:
    """Derivatives of the `n` samples of the fitted channels (flattened channel by channel)
    with respect to each mode's log|z| and angle z, then each mode's real and imaginary
    amplitude in each channel: the fitted signal of channel c is ``2 Re sum_k a_ck z_k**t``
    (`amp`: channels x modes)."""
    n_ch = amp.shape[0]
    power = z[None, :] ** np.arange(n)[:, None]  # (t, modes)
    rate = 2 * amp[:, None, :] * (np.arange(n)[:, None] * power)[None]  # (ch, t, modes)
    columns = [np.real(rate), -np.imag(rate)]
    for part in (2 * np.real(power), -2 * np.imag(power)):
        block = np.zeros((n_ch, n, n_ch * len(z)))
        for c in range(n_ch):
            block[c, :, c * len(z):(c + 1) * len(z)] = part
        columns.append(block)
    return np.concatenate(columns, axis=2).reshape(n_ch * n, -1)


def _shapes(optic: OpticConfig, sensing: NDArray) -> NDArray[np.float64]:
    """The model's amplitude pattern of each mode over the OSEMs (5 x 4, DOFS order)."""
    modes = normal_modes(optic)
    return sensing @ np.array([modes[d][1] for d in DOFS]).T


def _osem_gains(amp: NDArray, shapes: NDArray) -> dict[str, float]:
    """Each OSEM's gain g_j in ``amp[j, k] = g_j shapes[j, k] c_k`` (alternating least
    squares over the gains and the modes' complex amplitudes), face mean 1."""
    g = np.ones(amp.shape[0])
    for _ in range(200):
        u = g[:, None] * shapes
        c = np.sum(np.conj(u) * amp, axis=0) / np.maximum(np.sum(np.abs(u) ** 2, axis=0), 1e-300)
        v = shapes * c[None, :]
        g = np.sum(np.real(np.conj(v) * amp), axis=1) / np.maximum(
            np.sum(np.abs(v) ** 2, axis=1), 1e-300)
        g = g / g[:4].mean()
    return dict(zip(OSEMS[:4], g[:4].tolist(), strict=True))


def _input_matrix(amp: NDArray, configured: NDArray) -> NDArray[np.float64]:
    """The matrix that maps the measured mode amplitudes (made real by each mode's own
    phase) to one DOF each, rows scaled to the configured matrix's largest entries."""
    m = np.linalg.pinv(_real(amp))  # (modes, OSEMs): m @ real = I
    for i in range(m.shape[0]):
        big = np.argmax(np.abs(configured[i]))
        m[i] *= configured[i, big] / m[i, big]
    return m


def eigenmodes(optic: OpticConfig, plant: Plant | None = None
               ) -> tuple[dict[str, float], dict[str, float]]:
    """The damped frequencies and Qs of the optic's free modes (no damping loop), from the
    eigenvalues of its plant: what a ringdown measures, each matched to the nearest of the
    model's undamped modes.

    Parameters
    ----------
    optic : OpticConfig
    plant : Plant, optional
        Default: the configured one.

    Returns
    -------
    frequency_hz, q : dict of str to float
        By DOF.
    """
    plant = optic.loop().plant if plant is None else plant
    poles = np.linalg.eigvals(plant.osem_state_space()[0])
    poles = poles[poles.imag > 0]
    chosen = {d: poles[np.argmin(np.abs(poles.imag / (2 * np.pi) - f))]
              for d, f in modes_hz(optic).items()}
    return ({d: float(p.imag / (2 * np.pi)) for d, p in chosen.items()},
            {d: float(abs(p) / (-2 * p.real)) for d, p in chosen.items()})
