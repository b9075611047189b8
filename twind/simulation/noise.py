"""Noise the sensors see without excitation (docs/model.md "Noise"), as shaped white noise.

Each channel is white Gaussian noise through one second-order section, discretised with the
bilinear transform so the shape holds up to a few kHz at the model rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import signal

CHANNELS = ("UL", "UR", "LL", "LR", "SIDE", "x_sp", "y_sp", "phi_sp")


@dataclass(frozen=True)
class NoiseSpec:
    """Amplitude spectral densities (one-sided, per rtHz) of the default twin noise.

    OSEM: ``osem * sqrt(1 + (corner/f)^2)``; suspension point: ``sp * (1 Hz / f)^2`` (m, or rad
    for yaw). docs/model.md floors f at ``floor_hz``; the twin realises the floor with poles there,
    so its spectra are ``osem * |(f + i corner)/(f + i floor)|`` and ``sp / |f - i floor|^2``
    (the same well above the floor, flat below it).
    """

    osem_m: float = 1e-10  # m/rtHz, white level of each OSEM
    osem_corner_hz: float = 1.0  # Hz, where the 1/f part meets the white level
    sp_x_m: float = 2e-9  # m/rtHz at 1 Hz, suspension point along the beam
    sp_y_m: float = 2e-9  # m/rtHz at 1 Hz, sideways
    sp_phi_rad: float = 1e-9  # rad/rtHz at 1 Hz, yaw of the suspension point
    floor_hz: float = 0.05  # Hz, below which the spectra are flat
    enabled: bool = True

    def asd(self, f_hz: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
        """The target ASD of every channel in :data:`CHANNELS` at `f_hz`."""
        f = np.asarray(f_hz, dtype=float)
        osem = self.osem_m * np.sqrt((f**2 + self.osem_corner_hz**2) / (f**2 + self.floor_hz**2))
        sp = 1.0 / (f**2 + self.floor_hz**2)
        out = {c: osem for c in CHANNELS[:5]}
        out.update(x_sp=self.sp_x_m * sp, y_sp=self.sp_y_m * sp, phi_sp=self.sp_phi_rad * sp)
        return out

    def shaping(self, rate_hz: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Discrete shaping sections and white-noise standard deviations.

        Returns
        -------
        sos : ndarray, shape (8, 6)
            One section per channel, unity high-frequency gain for OSEMs.
        sigma : ndarray, shape (8,)
            Standard deviation of the white input of each channel (zero when disabled).
        """
        wc, wf = 2 * np.pi * self.osem_corner_hz, 2 * np.pi * self.floor_hz
        # (s + wc) / (s + wf): white at high f, 1/f above the floor, flat below
        osem = _bilinear_section([-wc], [-wf], 1.0, rate_hz)
        # wf^2 / (s + wf)^2 scaled to 1/f^2 (Hz) above the floor
        sp = _bilinear_section([], [-wf, -wf], (2 * np.pi) ** 2, rate_hz)
        white = np.sqrt(rate_hz / 2)  # one-sided ASD of 1/rtHz at this rate
        sigma = white * np.array([self.osem_m] * 5 + [self.sp_x_m, self.sp_y_m, self.sp_phi_rad])
        sos = np.array([osem] * 5 + [sp] * 3)
        return sos, sigma * float(self.enabled)


def _bilinear_section(zeros: list[float], poles: list[float], k: float, rate_hz: float) -> NDArray:
    z, p, kd = signal.bilinear_zpk(zeros, poles, k, rate_hz)
    sos = signal.zpk2sos(z, p, kd)
    return sos[0]
