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
from scipy import signal
from scipy.optimize import least_squares

from twind import DOFS
from twind.analysis.modes import FITTED, fit_modes, modes_hz, normal_modes, with_params
from twind.config import OpticConfig
from twind.loop.plant import Plant
from twind.model.effects import with_effect
from twind.errors import TwindError
from twind.model.osem import OSEMS
from twind.simulation.engine import Engine

DECIMATED_HZ = 4.0
"""Rate the OSEM signals are analysed at: above twice the highest pendulum mode, far below
the bounce and roll modes the decimation filters out."""

ORDER = 40
"""Poles the pencil fits: the four modes' conjugate pairs and room for the noise."""

EDGE_S = 20.0
"""Seconds cut at each end of the band-passed signals (the filter's transients)."""

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
    """

    optic: str
    frequency_hz: dict[str, float]
    q: dict[str, float]
    amplitude: NDArray[np.complex128]
    input_matrix: NDArray[np.float64]
    configured: NDArray[np.float64]
    osem_gains: dict[str, float]
    model_hz: dict[str, float]

    def lines(self) -> list[str]:
        """The modes, the OSEM gains and both input matrices, for a person."""
        rows = [f"{self.optic} free-swinging modes: DOF, frequency (Hz), Q, the model's (Hz)"]
        for d in DOFS:
            rows.append(f"  {d:4} {self.frequency_hz[d]:.5f}  Q {self.q[d]:6.0f}  model "
                        f"{self.model_hz[d]:.5f}")
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
                "model_hz": self.model_hz,
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
    `duration_s` with its noise. `plant` replaces the configured one
    (an optic with physics the model leaves out).

    Returns
    -------
    sen : ndarray, shape (5, n)
        The OSEM signals (um) of the ringdown.
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
    """The modes, Qs, input matrix and OSEM gains of a ringdown (:func:`ringdown`'s, or the
    five OSEM signals of a real one, um, any rate above :data:`DECIMATED_HZ`)."""
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
    model = modes_hz(optic)
    plant = optic.loop().plant
    every = _amplitudes(y, z)
    chosen = _match(z, dt, model, plant.input_matrix @ every)
    poles = _refine(scaled, np.array([z[k] for k in chosen.values()]))
    amp = _amplitudes(y, poles)
    f = {d: float(np.angle(p) / (2 * np.pi * dt)) for d, p in zip(DOFS, poles, strict=True)}
    decay = {d: float(-np.log(abs(p)) / dt) for d, p in zip(DOFS, poles, strict=True)}
    q = {d: float(np.pi * f[d] / decay[d]) for d in DOFS}
    # the mode shapes of the geometry that gives the measured POS, PIT, YAW: a drifted
    # optic's POS-PIT mixing is not the nominal one's
    solved = fit_modes(optic, {d: f[d] for d in FITTED})
    shapes = _shapes(with_params(optic, solved.after), plant.sensing)
    gains = _osem_gains(amp, shapes)
    return FreeSwing(optic.name, f, q, amp,
                     _input_matrix(amp, plant.input_matrix), plant.input_matrix, gains,
                     model)


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
        trial = np.exp(p[: len(z)] + 1j * p[len(z):])
        basis_t = np.arange(y.shape[1])[:, None]
        basis = np.hstack([trial[None, :] ** basis_t, np.conj(trial)[None, :] ** basis_t])
        coef, *_ = np.linalg.lstsq(basis, y.T.astype(complex), rcond=None)
        return (y.T - np.real(basis @ coef)).ravel()

    start = np.concatenate([np.log(np.abs(z)), np.angle(z)])
    fit = least_squares(residual, start, x_scale=np.abs(start) * 1e-3 + 1e-9)
    return np.exp(fit.x[: len(z)] + 1j * fit.x[len(z):])


def _amplitudes(y: NDArray, z: NDArray) -> NDArray[np.complex128]:
    """Each mode's complex amplitude in each channel (channels x modes): least squares on the
    modes and their conjugates."""
    t = np.arange(y.shape[1])
    basis = np.hstack([z[None, :] ** t[:, None], np.conj(z)[None, :] ** t[:, None]])
    coef, *_ = np.linalg.lstsq(basis, y.T.astype(complex), rcond=None)
    return coef[: len(z)].T


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
    phase = np.exp(-1j * np.angle(amp[np.argmax(np.abs(amp), axis=0), range(amp.shape[1])]))
    real = np.real(amp * phase[None, :])
    m = np.linalg.pinv(real)  # (modes, OSEMs): m @ real = I
    for i in range(m.shape[0]):
        big = np.argmax(np.abs(configured[i]))
        m[i] *= configured[i, big] / m[i, big]
    return m


def benchmark(optic: OpticConfig, n: int = 8, duration_s: float = 1000.0, seed: int = 0
              ) -> list[str]:
    """:func:`analyse` on the ringdowns of `n` random optics: each drifted from `optic`
    (wire length +-4 %, break-off +-20 %, clamp separation +-10 %, Qs 250-800) with face
    OSEM gains off by up to +-10 %, analysed with the nominal model. Lines: per optic, the
    worst frequency error against the drifted optic's eigenfrequencies (mHz), the worst Q
    error (%) and the worst OSEM gain error (% of each imbalance); then the worst of all."""
    rng = np.random.default_rng(seed)
    rows, worst = [], np.zeros(3)
    for k in range(n):
        sus = optic.sus.updated(
            wire_length_m=optic.sus.wire_length_m * rng.uniform(0.96, 1.04),
            b_m=optic.sus.b_m * rng.uniform(0.8, 1.2), R1_m=optic.sus.R1_m * rng.uniform(0.9, 1.1),
            Q={d: float(rng.uniform(250, 800)) for d in DOFS})
        real = OpticConfig(optic.name, sus, optic.damping, optic.noise, optic.model, optic.source)
        imbalance = {f"gain_{o}": float(rng.uniform(-0.1, 0.1)) for o in OSEMS[:4]}
        plant = with_effect(real.loop().plant, sus, "osem_imbalance", imbalance)
        sen, rate = ringdown(real, duration_s, seed=seed + k, plant=plant)
        found = analyse(optic, sen, rate)
        truth = modes_hz(real)
        df = max(abs(found.frequency_hz[d] - truth[d]) for d in DOFS)
        q_err = {d: abs(found.q[d] / sus.Q[d] - 1) for d in DOFS}
        worst_q = max(q_err, key=q_err.get)
        dq = q_err[worst_q]
        true_g = np.array([1 + imbalance[f"gain_{o}"] for o in OSEMS[:4]])
        true_g /= true_g.mean()
        got = np.array([found.osem_gains[o] for o in OSEMS[:4]])
        dg = np.max(np.abs((got - 1) - (true_g - 1)) / np.abs(true_g - 1))
        worst = np.maximum(worst, [df, dq, dg])
        gap = 1e3 * abs(truth["POS"] - truth["SIDE"])
        rows.append(f"optic {k + 1}: frequencies within {1e3 * df:.3f} mHz, Qs within "
                    f"{100 * dq:.1f} % ({worst_q}), OSEM gain imbalances within "
                    f"{100 * dg:.0f} %; POS-SIDE {gap:.1f} mHz apart")
    rows.append(f"worst of {n}: {1e3 * worst[0]:.3f} mHz (target 1), Q {100 * worst[1]:.1f} % "
                f"(target 20), OSEM gains {100 * worst[2]:.0f} % (target 35)")
    return rows
