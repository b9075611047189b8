"""What an optic's ``IN1`` shows without excitation: the OSEM and suspension-point noise of
its configuration through the closed damping loop (the noise the engine generates)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from twind.config import OpticConfig
from twind.loop.damping import DampingLoop
from twind.simulation.noise import CHANNELS


def in1_noise_asd(optic_cfg: OpticConfig, f_hz: ArrayLike,
                  loop: DampingLoop | None = None) -> NDArray[np.float64]:
    """ASD of each DOF's ``IN1`` without excitation: sensor and suspension-point noise.

    Parameters
    ----------
    optic_cfg : OpticConfig
        The optic; its ``noise`` gives the OSEM and suspension-point ASDs.
    f_hz : array_like
        Frequencies (Hz), > 0.
    loop : DampingLoop, optional
        The optic's loop (default ``optic_cfg.loop()``).

    Returns
    -------
    ndarray, shape (len(f), 4)
        um or urad per rtHz, columns POS, PIT, YAW, SIDE; zeros when the noise is disabled.

    Notes
    -----
    ``N = InMat (n_OSEM + Sens H F_sp n_sp)`` enters at ``IN1``; closed loop
    ``IN1 = (I - P K)^-1 N``.  The eight noise channels are independent, so the PSD of
    ``IN1_r`` is ``sum_c |G_rc|^2 n_c^2`` with ``G`` the closed-loop map of channel c.
    """
    f = np.atleast_1d(np.asarray(f_hz, dtype=float))
    loop = optic_cfg.loop() if loop is None else loop
    plant = loop.plant
    mech = plant.mechanics
    r = loop.responses(f)
    sens = r["closed_loop_IN2_per_EXC"]
    H = mech.admittance(2j * np.pi * f)
    osem = np.broadcast_to(plant.input_matrix, (f.size, 4, 5))
    sp = plant.input_matrix @ plant.sensing @ H @ mech.suspension_point_forces()
    G = sens @ np.concatenate([osem, sp], axis=2)  # (f, 4 DOFs, 8 channels)
    asd = optic_cfg.noise.asd(f)
    n = np.stack([asd[c] for c in CHANNELS], axis=1) * float(optic_cfg.noise.enabled)
    return np.sqrt(np.sum(np.abs(G) ** 2 * n[:, None, :] ** 2, axis=2))
