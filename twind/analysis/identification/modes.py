"""Free-swinging modes: the model's eigenfrequencies by DOF, and the suspension geometry that
puts them where an optic's were measured.

The 40m measures its optics' health from their free-swinging peaks (damping off, the optic
kicked and left to ring down). In the T000134 model POS is set mostly by the wire length,
PIT by the break-off height and YAW by the clamp separation, so those three are solved for
the measured POS, PIT and YAW; SIDE follows (``g/(l + b)``) and is compared, not fitted. A
measured mode the model cannot reach is reported as such, with how far it stays.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import scipy.linalg
from scipy.optimize import least_squares

from twind import DOFS
from twind.config import OpticConfig
from twind.errors import TwindError
from twind.model.mechanics import Mechanics

FITTED = {"POS": "wire_length_m", "PIT": "b_m", "YAW": "R1_m"}
"""The parameter solved for each measured mode."""

TOLERANCE_HZ = 0.005
"""How closely a mode must land on its measurement: the measured table's +-5 mHz."""


def normal_modes(optic: OpticConfig) -> dict[str, tuple[float, np.ndarray]]:
    """The undamped normal modes of the optic's configured model, each labelled by the DOF
    that holds most of its kinetic energy: frequency (Hz) and shape over the model's
    coordinates.

    Raises
    ------
    TwindError
        If two modes fall in one DOF (a coupling strong enough to mix them).
    """
    return mechanics_modes(optic.mechanics(), optic.name)


def mechanics_modes(mech: Mechanics, name: str = "") -> dict[str, tuple[float, np.ndarray]]:
    """:func:`normal_modes` of given rigid-body dynamics (`name` for messages).

    Parameters
    ----------
    mech : Mechanics
        The rigid-body dynamics.
    name : str
        The optic's name, for messages.

    Returns
    -------
    dict of str to (float, ndarray)
        Frequency (Hz) and shape of each POS, PIT, YAW and SIDE mode, labelled by the DOF
        that holds most of its kinetic energy.

    Raises
    ------
    TwindError
        If two modes fall in one DOF.
    """
    w2, vectors = scipy.linalg.eigh(mech.K, mech.M)
    energy = (vectors**2) * np.diag(mech.M)[:, None]
    found: dict[str, tuple[float, np.ndarray]] = {}
    for k in range(len(w2)):
        dof = mech.dofs[int(np.argmax(energy[:, k]))]
        if dof in found:
            msg = f"{name}: two modes are mostly {dof}; the labels are ambiguous"
            raise TwindError(msg)
        found[dof] = (float(np.sqrt(max(w2[k], 0.0)) / (2 * np.pi)), vectors[:, k])
    return {d: found[d] for d in DOFS if d in found}


def modes_hz(optic: OpticConfig) -> dict[str, float]:
    """The frequencies of :func:`normal_modes` (Hz), by DOF."""
    return {d: f for d, (f, _) in normal_modes(optic).items()}


@dataclass(frozen=True)
class ModeFit:
    """An optic's measured modes beside the model's, before and after solving its geometry.

    Attributes
    ----------
    optic : str
    measured, nominal, fitted : dict of str to float
        Mode frequencies (Hz) by DOF: measured; the configured model's; with the solved
        parameters.
    before, after : dict of str to float
        The solved parameters as configured and as solved (SI units).
    """

    optic: str
    measured: dict[str, float]
    nominal: dict[str, float]
    fitted: dict[str, float]
    before: dict[str, float]
    after: dict[str, float]

    def missed(self) -> dict[str, float]:
        """Modes the solved model still misses by more than :data:`TOLERANCE_HZ` (Hz,
        model minus measured)."""
        return {d: self.fitted[d] - f for d, f in self.measured.items()
                if abs(self.fitted[d] - f) > TOLERANCE_HZ}

    def lines(self) -> list[str]:
        """One row for a person (mHz: measured / as configured / solved), then the solved
        parameters and what the model cannot reach."""
        cells = [f"{1e3 * f:5.0f} {1e3 * self.nominal[d]:5.0f} {1e3 * self.fitted[d]:5.0f}"
                 + (" *" if d in self.missed() else "  ") for d, f in self.measured.items()]
        rows = [f"{self.optic:5} " + " | ".join(cells),
                "      " + ", ".join(f"{k} {self.before[k]:.5g} -> {self.after[k]:.5g}"
                                     for k in self.after)]
        if "SIDE" in self.missed() and "POS" in self.measured:
            apart = 1e3 * (self.measured["SIDE"] - self.measured["POS"])
            model = 1e3 * (self.fitted["SIDE"] - self.fitted["POS"])
            rows.append(f"      * SIDE measured {apart:+.0f} mHz from POS, modelled {model:+.0f}"
                        " mHz: T000134 keeps SIDE = sqrt(g/(l+b)) just below POS whatever the "
                        "geometry, so this is physics the model leaves out")
        return rows

    @staticmethod
    def header(dofs: list[str]) -> str:
        """The column heads of :meth:`lines`."""
        return ("optic " + " | ".join(f"{d:^19}" for d in dofs) + "\n      "
                + " | ".join(f"{'meas  conf solved':19}" for _ in dofs) + "   (mHz)")

    def to_json(self) -> dict:
        """The ``twind modes --json`` object."""
        return {"optic": self.optic, "measured_hz": self.measured, "nominal_hz": self.nominal,
                "fitted_hz": self.fitted, "params_before": self.before,
                "params_after": self.after, "missed_hz": self.missed()}


def fit_modes(optic: OpticConfig, measured: dict[str, float]) -> ModeFit:
    """Solve the wire length, break-off height and clamp separation for the measured POS,
    PIT and YAW (those given); the other modes follow and are compared.

    Parameters
    ----------
    optic : OpticConfig
        The optic as configured (the starting point and every parameter not solved).
    measured : dict of str to float
        Measured mode frequencies (Hz) by DOF.

    Returns
    -------
    ModeFit
    """
    unknown = sorted(set(measured) - set(DOFS))
    if unknown:
        msg = f"{optic.name}: no mode {', '.join(unknown)}; modes are {', '.join(DOFS)}"
        raise TwindError(msg)
    after, _, _ = solve_geometry(optic, measured)
    return ModeFit(optic.name, dict(measured), modes_hz(optic), modes_hz(with_params(optic, after)),
                   {n: getattr(optic.sus, n) for n in after}, after)


Stiffen = Callable[[OpticConfig, float], Mechanics]
"""``(optic, value) -> mechanics``: an optic's dynamics with one more stiffness in."""


def solve_geometry(optic: OpticConfig, measured: Mapping[str, float],
                   stiffen: Stiffen | None = None, free: bool = False
                   ) -> tuple[dict[str, float], float, Mechanics]:
    """The wire length, break-off height and clamp separation that put the modes of
    `stiffen(optic, value)` (default: the optic's own model) on the measured POS, PIT and
    YAW; with `free`, `value` (a stiffness, N/m) is solved with them for SIDE too.

    Least squares on the log of the frequencies; a trial whose modes cannot be labelled (two
    mostly one DOF) or do not oscillate is steered away from.

    Parameters
    ----------
    optic : OpticConfig
        The optic as configured (the starting point and every parameter not solved).
    measured : mapping of str to float
        Measured mode frequencies (Hz) by DOF; POS, PIT and YAW among them are solved for.
    stiffen : callable, optional
        ``(optic, value) -> Mechanics``: the dynamics of a trial optic (default: its own).
    free : bool
        Solve `value` for SIDE too (SIDE must be in `measured`).

    Returns
    -------
    geometry : dict of str to float
        The solved parameters (m), by :data:`FITTED`'s names.
    value : float
        The solved stiffness (0 without `free`).
    mechanics : Mechanics
        The solved optic's dynamics.
    """
    stiffen = stiffen or (lambda trial, _: trial.mechanics())
    names = [FITTED[d] for d in FITTED if d in measured]
    dofs = [d for d in FITTED if d in measured] + (["SIDE"] if free else [])
    start = np.array([getattr(optic.sus, n) for n in names])
    unit = optic.sus.mass_kg * optic.sus.g_mps2 / optic.sus.wire_length_m  # m g / l

    def trial(x: np.ndarray) -> tuple[dict[str, float], float, Mechanics]:
        geometry = dict(zip(names, (start * np.exp(x[:len(names)])).tolist(), strict=True))
        value = unit * x[-1] if free else 0.0
        return geometry, value, stiffen(with_params(optic, geometry), value)

    def residual(x: np.ndarray) -> np.ndarray:
        try:
            modes = mechanics_modes(trial(x)[2], optic.name)
        except TwindError:
            return np.ones(len(dofs))
        if any(modes[d][0] <= 0 for d in dofs):
            return np.ones(len(dofs))
        return np.array([np.log(modes[d][0] / measured[d]) for d in dofs])

    x0 = np.zeros(len(names) + (1 if free else 0))
    return trial(least_squares(residual, x0, xtol=1e-12, ftol=1e-12).x)


def with_params(optic: OpticConfig, params: dict[str, float]) -> OpticConfig:
    """`optic` with some suspension parameters changed.

    Parameters
    ----------
    optic : OpticConfig
    params : dict of str to float
        New values by :class:`~twind.model.params.SOSParams` field name (SI units).

    Returns
    -------
    OpticConfig
    """
    return replace(optic, sus=optic.sus.updated(**params))


def read_mode_table(path: str | Path) -> dict[str, dict[str, float]]:
    """Measured mode frequencies by optic from a CSV file: a header ``optic`` and some of
    ``POS, PIT, YAW, SIDE`` (Hz); lines starting with ``#`` are comments (the source)."""
    path = Path(path)
    try:
        lines = [ln for ln in path.read_text().splitlines() if ln.strip() and
                 not ln.lstrip().startswith("#")]
    except OSError as err:
        msg = f"{path}: {err.strerror}"
        raise TwindError(msg) from None
    rows = list(csv.DictReader(lines, skipinitialspace=True))
    if not rows or "optic" not in rows[0]:
        msg = f"{path}: expected a CSV table with a header 'optic' and some of {', '.join(DOFS)}"
        raise TwindError(msg)
    table = {}
    for n, row in enumerate(rows, start=2):
        try:
            table[row["optic"]] = {d: float(row[d]) for d in DOFS if row.get(d)}
        except ValueError as err:
            msg = f"{path}: row {n} ({row['optic']}): {err}"
            raise TwindError(msg) from None
    return table
