"""What to measure next when two fitted hypotheses fit the data alike, and what it costs:
a sine where their closed loops differ most against the IN1 noise, as large as the EXC
limits allow, for as long as :data:`SEPARATION_SIGMA` standard errors take."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from twind import DOFS
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.result import FitResult
from twind.analysis.noise import in1_noise_asd
from twind.config import OpticConfig
from twind.limits import ServiceLimits

SEPARATION_SIGMA = 3.0
"""How far apart, in standard errors, a separating measurement puts two rivals."""
MAX_SECONDS = 86400.0
"""Longer than this, a loop measurement is not a way to tell two rivals apart."""


@dataclass(frozen=True)
class Separation:
    """The measurement that tells two fitted hypotheses apart, and its cost.

    Attributes
    ----------
    excite, measure : str
        The DOF to excite and the response to read.
    frequency_hz : float
        Where their closed loops differ most against the IN1 noise.
    amplitude : float
        The sine's amplitude (EXC units), the most the EXC limits allow.
    seconds : float
        How long to measure for :data:`SEPARATION_SIGMA` standard errors between their
        predictions (inf where they do not differ).
    bin_hz : float
        The measurement's bin width, for the averages it makes.
    """

    excite: str
    measure: str
    frequency_hz: float
    amplitude: float
    seconds: float
    bin_hz: float

    @property
    def separable(self) -> bool:
        """Within :data:`MAX_SECONDS` of loop measurement."""
        return self.seconds <= MAX_SECONDS

    def line(self, a: str, b: str) -> str:
        """The measurement in words."""
        where = (f"excite {self.excite} with a sine of {self.amplitude:.3g} at "
                 f"{self.frequency_hz:.3g} Hz and measure {self.measure}/{self.excite}")
        if not self.separable:
            return (f"to tell {a} from {b}: not separable by loop measurements within the EXC "
                    f"limits ({where}: {SEPARATION_SIGMA:g} sigma would take "
                    f"{self.seconds:.2g} s); measure what differs directly (a ringdown, "
                    "twind freeswing, or the OSEMs without excitation)")
        averages = math.ceil(self.seconds * self.bin_hz) if self.bin_hz > 0 else None
        return (f"to tell {a} from {b}: {where}, {self.seconds:.3g} s for "
                f"{SEPARATION_SIGMA:g} sigma" + (f" ({averages} averages at {self.bin_hz:g} Hz)"
                                                 if averages else ""))

    def to_json(self, a: str, b: str) -> dict:
        """One entry of ``separations`` in ``twind diagnose --json``."""
        return {"effect": a, "rival": b, "excite": self.excite, "measure": self.measure,
                "frequency_hz": self.frequency_hz, "amplitude": self.amplitude,
                "seconds": self.seconds, "separable": self.separable}


def separating_measurement(cfg: OpticConfig, a: FitResult, b: FitResult,
                           limits: ServiceLimits | None = None, bin_hz: float = 0.0
                           ) -> Separation:
    """What to measure next to tell two fitted hypotheses apart: a sine where their closed
    loops differ most relative to the IN1 noise, as large as the EXC limits allow, for as
    long as :data:`SEPARATION_SIGMA` standard errors between their predictions take.

    A sine of amplitude A demodulated over T seconds has an error of ``n / sqrt(T)`` in
    each quadrature, for IN1 noise of ASD ``n``; the predictions differ by ``|dT| A``.

    Parameters
    ----------
    cfg : OpticConfig
        The optic (its noise sets the scale).
    a, b : FitResult
        The two fits, each with its effect.
    limits : ServiceLimits, optional
        The EXC limits (peak and RMS of a test point's excitation); default the twin's.
    bin_hz : float
        The bin width the averages are counted in.

    Returns
    -------
    Separation
    """
    f = np.logspace(-1, 2, 400)
    noise = in1_noise_asd(cfg, f)  # [f, response]
    ta, tb = (ClosedLoopModel(cfg, f, 0.0, r.effect)(r.as_dict()) for r in (a, b))
    contrast = np.abs(ta - tb) / np.maximum(noise[:, :, None], 1e-300)
    k, i, j = np.unravel_index(np.argmax(contrast), contrast.shape)
    limits = limits or ServiceLimits()
    amplitude = min(limits.exc_peak, limits.exc_rms * math.sqrt(2))
    per_root_s = float(contrast[k, i, j]) * amplitude
    seconds = (SEPARATION_SIGMA / per_root_s) ** 2 if per_root_s > 0 else math.inf
    return Separation(DOFS[j], DOFS[i], float(f[k]), amplitude, seconds, bin_hz)
