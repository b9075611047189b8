"""Violin modes: each wire segment a string under tension with bending stiffness, coupled to
the optic through the transverse force at its break-off point.

Model
-----
Segment ``i`` runs from its clamp (``s = 0``) to its break-off point (``s = L``) under
tension ``T``. Its transverse displacement along a direction ``e`` normal to the wire is the
straight line the break-off's motion ``xi = e . d_i(q)`` draws, plus the string's modes::

    u(s) = xi s / L + sum_n a_n sin(n pi s / L)

With linear density ``mu`` the string's kinetic energy adds ``mu L / 3`` of mass to ``xi``,
``mu L / 2`` to each ``a_n`` and couples them through ``mu L (-1)^(n+1) / (n pi)``; its
potential energy adds ``(mu L / 2) w_n^2`` to each ``a_n`` and nothing between them, while its
``T xi^2 / (2 L)`` is the pendulum stiffness the rigid model already holds. ``w_n`` is the
stiff string's (Gonzalez, CQG 17, 4409 (2000)) with ``k_e = sqrt(T / (E I))``::

    f_n = n / (2 L) sqrt(T / mu) [1 + 2 / (k_e L) + (1 + n^2 pi^2 / 2) / (k_e L)^2]

and its loss is the wire's, diluted by tension (same source)::

    1 / Q_n = phi_wire (2 / (k_e L)) (1 + n^2 pi^2 / (2 k_e L))

The segments' tensions come from the optic's mass and the geometry, each its own: an
asymmetric load splits a pair of violin frequencies as the square root of their tensions.
The suspension point's motion drives the strings only through the optic here.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from twind.model.mechanics import Mechanics

if TYPE_CHECKING:  # named only: the parameters hold a Wire, so they import this module
    from twind.model.params import SOSParams

DIRECTIONS = ("x", "y")
"""The two transverse directions of a segment: along the beam, and normal to it and the wire."""


@dataclass(frozen=True)
class Wire:
    """The suspension wire's material and size (configuration ``[suspension.wire]``).

    Attributes
    ----------
    diameter_m : float
        0.0017 in (43.2 um) steel music wire: at the SOS tension it puts the first violin mode
        at 650 Hz, where the 40m measured ETMX's (631 and 691 Hz, elog 9290).
    density_kgpm3 : float
        C70 steel, 7800 kg/m^3 (GWINC's aLIGO parameters, ``Suspension.C70Steel.Rho``).
    youngs_modulus_Pa : float
        212 GPa (GWINC, ``C70Steel.Y``, measured on one set of wires).
    loss_angle : float
        2e-4 (GWINC, ``C70Steel.Phi``).
    modes : int
        Violin modes kept per segment and direction (0: rigid wires, the model of
        LIGO-T000134 and of the golden responses).
    """

    diameter_m: float = 43.18e-6
    density_kgpm3: float = 7800.0
    youngs_modulus_Pa: float = 212e9
    loss_angle: float = 2e-4
    modes: int = 0

    @property
    def linear_density_kgpm(self) -> float:
        """Mass per length ``mu = rho pi d^2 / 4``."""
        return self.density_kgpm3 * math.pi * self.diameter_m**2 / 4

    @property
    def bending_stiffness_Nm2(self) -> float:
        """``E I`` with ``I = pi d^4 / 64``."""
        return self.youngs_modulus_Pa * math.pi * self.diameter_m**4 / 64

    def check(self) -> list[tuple[str, str]]:
        """``(key, problem)`` pairs for impossible values (empty when fine)."""
        problems = [(k, f"must be positive, got {getattr(self, k)}")
                    for k in ("diameter_m", "density_kgpm3", "youngs_modulus_Pa", "loss_angle")
                    if not getattr(self, k) > 0]
        if not (isinstance(self.modes, int) and 0 <= self.modes <= 20):
            problems.append(("modes", f"must be a whole number 0..20, got {self.modes}"))
        return problems


def violin_frequencies_hz(tension_N: float, length_m: float, wire: Wire,
                          n: int | NDArray[np.int64]) -> NDArray[np.float64]:
    """The stiff string's mode frequencies (Hz) of a segment: the module's formula."""
    n, kl = np.asarray(n, dtype=float), _kl(tension_N, length_m, wire)
    f = n / (2 * length_m) * math.sqrt(tension_N / wire.linear_density_kgpm)
    return f * (1 + 2 / kl + (1 + n**2 * math.pi**2 / 2) / kl**2)


def violin_q(tension_N: float, length_m: float, wire: Wire,
             n: int | NDArray[np.int64]) -> NDArray[np.float64]:
    """The modes' quality factors: the wire's loss angle diluted by the tension."""
    n, kl = np.asarray(n, dtype=float), _kl(tension_N, length_m, wire)
    return 1 / (wire.loss_angle * (2 / kl) * (1 + n**2 * math.pi**2 / (2 * kl)))


def _kl(tension_N: float, length_m: float, wire: Wire) -> float:
    """``k_e L``, the segment's length in units of the bending length ``sqrt(E I / T)``."""
    return math.sqrt(tension_N / wire.bending_stiffness_Nm2) * length_m


@dataclass(frozen=True)
class Segment:
    """One wire segment as the violin modes see it.

    Attributes
    ----------
    name : str
        ``"+y"`` or ``"-y"`` (the side of the optic).
    tension_N, length_m : float
    break_off : ndarray, shape (3, n)
        Lab displacement (x, y, z) of its break-off point per coordinate of the mechanics.
    axis : ndarray, shape (3,)
        Unit vector along the wire.
    """

    name: str
    tension_N: float
    length_m: float
    break_off: NDArray[np.float64]
    axis: NDArray[np.float64]

    def transverse(self) -> dict[str, NDArray[np.float64]]:
        """The two directions normal to the wire: along the beam (x) as near as the wire
        allows, and normal to that and the wire (y)."""
        ex = np.array([1.0, 0.0, 0.0]) - self.axis[0] * self.axis
        ex /= np.linalg.norm(ex)
        return {"x": ex, "y": np.cross(self.axis, ex)}


def rigid_break_off(dofs: tuple[str, ...], y_m: float, z_m: float) -> NDArray[np.float64]:
    """Lab displacement (x, y, z) of a point at (0, `y_m`, `z_m`) from the centre of mass per
    coordinate (OSEM convention: a face point moves along x by POS + z PIT + y YAW)."""
    per = {"POS": (1.0, 0.0, 0.0), "PIT": (z_m, 0.0, 0.0), "YAW": (y_m, 0.0, 0.0),
           "SIDE": (0.0, 1.0, 0.0), "VERT": (0.0, 0.0, 1.0), "ROLL": (0.0, -z_m, y_m)}
    return np.array([per.get(d, (0.0, 0.0, 0.0)) for d in dofs]).T


def sos_segments(p: SOSParams, dofs: tuple[str, ...]) -> list[Segment]:
    """The two segments of the ideal SOS (LIGO-T000134): clamps at ``(0, +-R1, b + l)``,
    break-offs at ``(0, +-R2, b)``, each holding half the optic's weight along its slant.

    Parameters
    ----------
    p : SOSParams
    dofs : tuple of str
        The coordinates of the mechanics the segments are coupled to.
    """
    l, b = p.wire_length_m, p.b_m
    length = math.hypot(l, p.R2_m - p.R1_m)
    tension = p.mass_kg * p.g_mps2 * length / (2 * l)
    return [Segment(name, tension, length, rigid_break_off(dofs, side * p.R2_m, b),
                    np.array([0.0, side * (p.R1_m - p.R2_m), l]) / length)
            for name, side in (("+y", 1.0), ("-y", -1.0))]


def with_violin_modes(mech: Mechanics, segments: list[Segment], wire: Wire) -> Mechanics:
    """`mech` with `wire.modes` violin modes of each segment in each transverse direction
    as coordinates of their own (named ``VIOLIN<segment><direction><n>``, e.g.
    ``VIOLIN+yx1``, metres of the mode's sine shape at its antinode).

    Parameters
    ----------
    mech : Mechanics
        The optic's rigid-body dynamics.
    segments : list of Segment
        Its wire segments, their break-off motion over `mech`'s coordinates.
    wire : Wire

    Returns
    -------
    Mechanics
        `mech` itself when ``wire.modes`` is 0.
    """
    if wire.modes == 0:
        return mech
    mu, n0 = wire.linear_density_kgpm, mech.n
    orders = np.arange(1, wire.modes + 1)
    names, m_a, k_a, c_a, couplings = [], [], [], [], []
    extra_mass = np.zeros((n0, n0))
    for seg in segments:
        L = seg.length_m
        w = 2 * np.pi * violin_frequencies_hz(seg.tension_N, L, wire, orders)
        q = violin_q(seg.tension_N, L, wire, orders)
        for direction, e in seg.transverse().items():
            J = e @ seg.break_off  # (n0,): this direction's break-off motion per coordinate
            extra_mass += mu * L / 3 * np.outer(J, J)
            for k, n in enumerate(orders):
                names.append(f"VIOLIN{seg.name}{direction}{n}")
                m_a.append(mu * L / 2)
                k_a.append(mu * L / 2 * w[k] ** 2)
                c_a.append(mu * L / 2 * w[k] / q[k])
                couplings.append(mu * L * (-1) ** (n + 1) / (n * np.pi) * J)
    na = len(names)
    M = np.zeros((n0 + na, n0 + na))
    M[:n0, :n0] = mech.M + extra_mass
    M[n0:, n0:] = np.diag(m_a)
    M[n0:, :n0] = np.array(couplings)
    M[:n0, n0:] = M[n0:, :n0].T
    K, C = np.zeros_like(M), np.zeros_like(M)
    K[:n0, :n0], C[:n0, :n0] = mech.K, mech.C
    K[n0:, n0:], C[n0:, n0:] = np.diag(k_a), np.diag(c_a)
    return Mechanics((*mech.dofs, *names), M, C, K)


def violin_modes(mech: Mechanics) -> list[tuple[str, float, float]]:
    """The violin modes of `mech` as coupled to the optic, lowest first.

    Returns
    -------
    list of (str, float, float)
        Each mode's name (its direction and order, and the segment that moves, e.g. ``x1 of
        +y``), frequency (Hz) and Q; empty for rigid wires.
    """
    violin = [i for i, d in enumerate(mech.dofs) if d.startswith("VIOLIN")]
    if not violin:
        return []
    A, _ = mech.state_space()
    lam, V = np.linalg.eig(A)
    modes = []
    for k in np.flatnonzero(lam.imag > 0):
        shape = np.abs(V[:mech.n, k])
        if shape[violin].max() >= shape.max():
            w = abs(lam[k])
            modes.append((_mode_name(mech.dofs, shape, violin), w / (2 * np.pi),
                          w / (-2 * lam[k].real)))
    return sorted(modes, key=lambda m: m[1])


def segment_modes(segments: list[Segment], wire: Wire, below_hz: float
                  ) -> list[tuple[str, int, float, float]]:
    """Each segment's violin modes below `below_hz` by the stiff-string formula, as the
    optic's coupling leaves them within 1e-5: ``(segment, n, frequency (Hz), Q)``, lowest
    first."""
    modes = []
    for seg in segments:
        f1 = float(violin_frequencies_hz(seg.tension_N, seg.length_m, wire, 1))
        n = np.arange(1, max(1, int(below_hz / f1)) + 2)
        f = violin_frequencies_hz(seg.tension_N, seg.length_m, wire, n)
        q = violin_q(seg.tension_N, seg.length_m, wire, n)
        modes += [(seg.name, int(k), float(fk), float(qk))
                  for k, fk, qk in zip(n, f, q, strict=True) if fk < below_hz]
    return sorted(modes, key=lambda m: m[2])


def _mode_name(dofs: tuple[str, ...], shape: NDArray[np.float64], violin: list[int]) -> str:
    """``<direction><n> of <segment>`` for the violin coordinate a mode moves most, or ``of
    both`` when the other segment's like mode moves with it (equal tensions: their sum and
    difference)."""
    top = dofs[violin[int(np.argmax(shape[violin]))]]
    segment, rest = top[len("VIOLIN"):len("VIOLIN") + 2], top[len("VIOLIN") + 2:]
    other = "VIOLIN" + ("-y" if segment == "+y" else "+y") + rest
    both = other in dofs and shape[dofs.index(other)] > 0.5 * shape[dofs.index(top)]
    return f"{rest} of {'both segments' if both else segment}"


@dataclass(frozen=True)
class PairReading:
    """What a measured pair of first violin modes (one per segment) says of the wires, read
    the two ways the ideal SOS allows (:func:`read_pair`).

    Attributes
    ----------
    split : float
        ``|f_a - f_b| / (f_a + f_b)``.
    length_difference_m : float
        Read as equal tensions and unequal lengths (``f ~ 1/L``, a raised clamp): how much
        longer the lower segment is.
    delta_m : float
        Then docs/model.md's ``wire_asymmetry``: the pendulum centre's offset from the centre
        of mass, ``R2 split`` (the lower segment's side), which couples POS and YAW.
    tension_ratio : float
        Read as equal lengths and unequal tensions (``f ~ sqrt(T)``, the centre of mass off to
        one side): the higher segment's tension over the lower's. The wires then form a
        parallelogram and couple POS and YAW not at all.
    """

    split: float
    length_difference_m: float
    delta_m: float
    tension_ratio: float

    def lines(self) -> list[str]:
        """The two readings, for a person."""
        return [f"violin pair split {100 * self.split:.2f} %: either the lower segment is "
                f"{1e3 * self.length_difference_m:.2f} mm longer (wire_asymmetry delta_m "
                f"{1e3 * self.delta_m:.3f} mm, a POS-YAW coupling), or its tension is "
                f"{self.tension_ratio:.3f} times less (no POS-YAW coupling); a fitted "
                "wire_asymmetry tells the two apart"]

    def weigh(self, delta_m: float, sigma_m: float | None) -> PairWeighing:
        """Which reading a fitted ``wire_asymmetry`` delta (m) and its standard error allow
        (:class:`PairWeighing`): its size within :data:`WEIGH_SIGMA` of this pair's
        ``delta_m`` (a length difference), of zero (a tension difference), of both, or of
        neither."""
        verdict = "undetermined"
        if sigma_m is not None and sigma_m > 0:
            length = abs(abs(delta_m) - self.delta_m) <= WEIGH_SIGMA * sigma_m
            tension = abs(delta_m) <= WEIGH_SIGMA * sigma_m
            verdict = {(True, False): "length", (False, True): "tension",
                       (True, True): "either"}.get((length, tension), "neither")
        return PairWeighing(self, delta_m, sigma_m, verdict)


WEIGH_SIGMA = 2.0
"""Standard errors within which a fitted delta agrees with a reading of a violin pair."""

_VERDICTS = {
    "length": "a length difference (the fit's POS-YAW coupling is the pair's)",
    "tension": "a tension difference (the fit finds no POS-YAW coupling; a length "
               "difference would make one)",
    "either": "either: the fit's error is too large to tell (it must be below a quarter of "
              "the length reading's delta)",
    "neither": "neither alone: the fit's coupling is not the pair's length reading, nor "
               "none (both differ, or another cause couples POS and YAW)",
    "undetermined": "undetermined: the fit leaves delta without a standard error"}


@dataclass(frozen=True)
class PairWeighing:
    """A violin pair's two readings against a fitted ``wire_asymmetry``.

    Attributes
    ----------
    reading : PairReading
    fitted_delta_m : float
        The fitted delta (m).
    fitted_sigma_m : float or None
        Its standard error.
    verdict : str
        ``"length"``, ``"tension"``, ``"either"``, ``"neither"`` or ``"undetermined"``
        (:meth:`PairReading.weigh`).
    """

    reading: PairReading
    fitted_delta_m: float
    fitted_sigma_m: float | None
    verdict: str

    def lines(self) -> list[str]:
        """The readings and the verdict, for a person."""
        sigma = "?" if self.fitted_sigma_m is None else f"{1e6 * self.fitted_sigma_m:.2g}"
        return [*self.reading.lines(),
                f"fitted wire_asymmetry delta_m {1e6 * self.fitted_delta_m:.3g} +- {sigma} um: "
                f"the pair is {_VERDICTS[self.verdict]}"]

    def to_json(self) -> dict:
        """``violin_pair`` of ``twind diagnose --json``."""
        return {**asdict(self.reading), "fitted_delta_m": self.fitted_delta_m,
                "fitted_sigma_m": self.fitted_sigma_m, "verdict": self.verdict}


def read_pair(f_a_hz: float, f_b_hz: float, length_m: float, half_separation_m: float
              ) -> PairReading:
    """A measured pair of first violin modes (one per segment of a loop) read as a length
    difference and as a tension difference (:class:`PairReading`): an independent handle on
    ``wire_asymmetry``, which a damping-loop fit reads from the POS-YAW coupling.

    Parameters
    ----------
    f_a_hz, f_b_hz : float
        The two segments' first violin modes.
    length_m : float
        The segments' mean length.
    half_separation_m : float
        ``R2``: half the break-offs' separation.
    """
    split = abs(f_a_hz - f_b_hz) / (f_a_hz + f_b_hz)
    return PairReading(split, 2 * length_m * split, half_separation_m * split,
                       (max(f_a_hz, f_b_hz) / min(f_a_hz, f_b_hz)) ** 2)
