"""A CDS standard filter module: IN1, EXC, IN2 = IN1 + EXC, FM1..FM10, gain with ramp, limit, OUT.

The continuous response (for the model) comes from each stage's foton design; the discrete
second-order sections (for the engine) from the same design, or from a foton file's
coefficients when the stage has no design.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from twind.errors import FotonError
from twind.loop.foton import design_to_sos, implementation, parse_design
from twind.loop.foton_file import N_STAGES

IDENTITY_SECTION = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 0.0])


@dataclass(frozen=True)
class Stage:
    """One filter stage (FMn): a name and its foton design, or raw sections from a file."""

    name: str
    design: str | None = None
    sos: NDArray[np.float64] | None = None  # discrete sections at `rate_hz` from a foton file
    rate_hz: float | None = None

    def sections(self, rate_hz: float) -> NDArray[np.float64]:
        """Discrete second-order sections at `rate_hz`, shape (n, 6).

        A foton file's coefficients are what the front end runs, so they win over its design.
        """
        if self.sos is not None:
            if self.rate_hz != rate_hz:
                msg = f"stage {self.name!r} has coefficients for {self.rate_hz} Hz, not {rate_hz} Hz"
                raise FotonError(msg)
            return np.atleast_2d(self.sos)
        if self.design is None:
            msg = f"stage {self.name!r} has neither a design nor coefficients"
            raise FotonError(msg)
        return design_sections(self.design, rate_hz).copy()

    def response(self, f_hz: NDArray[np.float64]) -> NDArray[np.complex128]:
        """Response at `f_hz` of what runs: a foton file's coefficients (its design may be
        stale), else the continuous design, read at the stage's rate when it has one."""
        if self.sos is not None:
            _, h = signal.sosfreqz(self.sos, worN=np.asarray(f_hz), fs=self.rate_hz)
            return h
        return parse_design(self.design, self.rate_hz).response(f_hz)


def design_sections(design: str, rate_hz: float) -> NDArray[np.float64]:
    """A foton design's discrete sections at `rate_hz`, computed once per design: the
    service checks every live filter or parameter change against them, and parsing and
    discretising the designs is most of that check's work. Do not modify the result.

    Parameters
    ----------
    design : str
        A foton design string (e.g. ``zpk([1],[10],1,"n")``).
    rate_hz : float
        The model's sample rate (Hz).

    Returns
    -------
    ndarray, shape (n, 6)
        Read-only, shared by every caller.
    """
    return _sections(design, rate_hz, implementation())


@lru_cache(maxsize=1024)
def _sections(design: str, rate_hz: float, reader: str) -> NDArray[np.float64]:
    sos = design_to_sos(design, rate_hz, reader)
    sos.flags.writeable = False
    return sos


@dataclass
class FilterModule:
    """Settings of one filter module; the engine runs it, :meth:`response` models it.

    Attributes
    ----------
    stages : list of Stage or None
        FM1..FM10 (index 0 is FM1); None where a slot is empty.
    on : set of int
        FM numbers (1-based, as on the MEDM screen) switched on.
    gain : float
        Module gain (ct per input unit).
    ramp_s : float
        Gain ramp time used by later gain changes.
    limit : float
        Output limit in counts; 0 means no limit.
    """

    stages: list[Stage | None]
    on: set[int]
    gain: float = 1.0
    ramp_s: float = 0.0
    limit: float = 0.0

    def __post_init__(self) -> None:
        if len(self.stages) > N_STAGES:
            msg = f"a filter module has at most {N_STAGES} stages, got {len(self.stages)}"
            raise FotonError(msg)
        self.stages = list(self.stages) + [None] * (N_STAGES - len(self.stages))
        for fm in self.on:
            if not 1 <= fm <= N_STAGES or self.stages[fm - 1] is None:
                msg = f"FM{fm} is switched on but holds no filter"
                raise FotonError(msg)

    def response(self, f_hz: NDArray[np.float64]) -> NDArray[np.complex128]:
        """Continuous IN2 -> OUT response of the switched-on stages and the gain."""
        h = np.full(np.shape(f_hz), self.gain, dtype=complex)
        for fm in sorted(self.on):
            h = h * self.stages[fm - 1].response(f_hz)
        return h

    def section_layout(self, rate_hz: float) -> tuple[NDArray[np.float64], dict[int, slice]]:
        """All defined stages' sections in FM order, and which rows belong to each FM.

        Every defined stage keeps its rows, switched on or not, so that switching in the
        engine is a swap between these coefficients and :data:`IDENTITY_SECTION`.
        """
        rows, where, start = [], {}, 0
        for i, stage in enumerate(self.stages):
            if stage is None:
                continue
            sos = stage.sections(rate_hz)
            where[i + 1] = slice(start, start + len(sos))
            rows.append(sos)
            start += len(sos)
        return (np.vstack(rows) if rows else np.zeros((0, 6))), where
