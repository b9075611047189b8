"""Geometric rigid-body model of a small optic suspension: a rigid optic hung by straight wires.

The optic is a rigid body (mass ``m``, inertia tensor ``I`` about its centre of mass) hung by
``n`` straight wire segments. Segment ``i`` is an axial spring (stiffness ``k_i``, unstretched
length ``L0_i``) from a clamp point ``c_i`` fixed to the suspension frame to an attachment
(break-off) point fixed on the optic at ``r_i`` (body frame, relative to the centre of mass).
Nothing here assumes the ideal SOS geometry: any clamp and attachment points are allowed.

Model
-----
Pose: centre-of-mass position ``t`` and orientation ``R``; attachment point ``p_i = t + R r_i``.
Potential energy (wires only pull, so a segment shorter than ``L0_i`` stores nothing)::

    V = m g t_z + sum_i 1/2 k_i max(|p_i - c_i| - L0_i, 0)^2

1. **Equilibrium**: ``V`` is minimised by a Levenberg-Marquardt-damped Newton iteration with the
   analytic gradient and Hessian below, on ``(t, w)`` with lab-frame small rotations
   ``R -> exp([w]x) R``. At the minimum every wire must be taut (:class:`SlackWireError`
   otherwise) and the pose must be near the nominal one and stable
   (:class:`NoEquilibriumError` otherwise).
2. **Linearisation**: with ``a_i = R r_i`` (lab-frame lever arm), ``u_i = (p_i - c_i)/L_i``,
   tension ``T_i = k_i (L_i - L0_i)`` and the wire's 3x3 stiffness
   ``H_i = k_i u_i u_i^T + (T_i/L_i)(1 - u_i u_i^T)`` (axial + geometric, the latter is what makes
   a pendulum), the Hessian of ``V`` is::

       K_tt = sum H_i
       K_tw = -sum H_i [a_i]x
       K_ww = sum [a_i]x^T H_i [a_i]x + sum ( 1/2 (g_i a_i^T + a_i g_i^T) - (g_i . a_i) 1 )

   with ``g_i = T_i u_i``; the last term is the rotation of the loaded lever arms (it gives the
   ``m g b`` of pitch and the ``-T (R2 - R1) R2 / L`` that turns ``R2^2`` into ``R1 R2`` in yaw).
   Gravity acts at the centre of mass, so it contributes no second derivative in these
   coordinates. Mass matrix: ``m 1`` for ``t`` and ``R I R^T`` for ``w``.
3. **Coordinates** (the OSEM convention of docs/model.md, x along the beam, y sideways, z up):
   ``POS = t_x, PIT = w_y, YAW = -w_z, SIDE = t_y, VERT = t_z, ROLL = w_x``, so a face point at
   ``(y, z)`` moves along x by ``POS + z PIT + y YAW`` and the face-coil torques are
   ``tau_PIT = sum z F``, ``tau_YAW = sum y F`` exactly as in :mod:`twind.model.osem`.
4. **Damping**: ``C = diag(M_ii w_i / Q_i)`` as in the analytical model. For the four pendulum
   coordinates ``w_i^2 = Kc_ii / M_ii`` with ``Kc`` the stiffness after static condensation of
   the stiff wire-stretch coordinates (VERT, ROLL); for VERT and ROLL ``w_i^2 = K_ii / M_ii``.
   Condensation changes nothing for a coordinate that does not couple to VERT or ROLL (POS, PIT,
   YAW of the ideal SOS, which then get exactly the analytical damping), but without it SIDE,
   which stretches the V-shaped wires, would get ``w`` from a diagonal inflated by the axial
   stiffness (2.2 Hz instead of 1.0 Hz).

Ideal SOS (:meth:`WireGeometry.from_params`)
---------------------------------------------
POS, PIT and YAW reproduce T000134 exactly (``g/l``, ``m g b (l+b)/(I l)``, ``m g R1 R2/(I l)``)
and VERT is ``sqrt(k_v/m)`` by construction. The trapezoidal wires (R1 < R2) make the optic roll
about the crossing point of the wire lines (0.30 m up) as it swings sideways, so SIDE and ROLL
form one coupled pair: SIDE comes out 0.23 % below ``g/(l+b)`` (the roll inertia adds
``I_roll/H^2``, 0.8 %, to the swinging mass) and ROLL 0.47 % above ``sqrt(k_v R2^2/I_roll)``.

Sign quirk of the analytical model
----------------------------------
docs/model.md (after T000134) writes ``K_x_theta = -m g b / l``. With the OSEM kinematics above
(PIT positive moves the top of the face toward +x) a consistent rigid body gives
``K_POS,PIT = +m g b / l``: the break-off point at height ``b`` moves by ``x + b PIT`` and the
wire pulls it back with ``-(m g / l)(x + b PIT)``. T000134's ``theta`` is therefore the opposite
pitch sign from the OSEM kinematics. This model stays physically consistent in the OSEM
convention; magnitudes and eigenfrequencies agree with the analytical model, only the sign of the
POS<->PIT off-diagonal (stiffness and admittance) differs.

``wire_asymmetry`` of docs/model.md
-------------------------------
For near-vertical wires the POS<->YAW stiffness is ``K_POS,YAW = sum_i (T_i / L_i) y_i``
(``y_i`` the lab-frame lateral lever arm of break-off ``i``), i.e. ``-(m g / l) delta`` with
``delta`` the sideways offset of the centre of mass from the wires' pendulum centre (the
``T/L``-weighted mean of the ``y_i``). That is docs/model.md's ``K_xphi = -m g delta / l`` in the OSEM
convention, with ``delta`` measured along SIDE. Two consequences of a consistent rigid body:

- a centre of mass off the wire plane *along x* cannot couple POS and YAW at all (the geometry
  keeps its y -> -y mirror symmetry, under which POS is even and YAW odd); it pitches the optic to
  ``atan(delta / b)`` instead;
- a centre of mass displaced *sideways* couples almost nothing either: equal-length wires form a
  parallelogram, the tensions redistribute so that ``sum T_i y_i = 0`` and only the unequal wire
  stretch is left (``~ m g / (2 k l)``, 0.4 % of ``m g delta / l``). The coupling needs wires of
  unequal length (e.g. one clamp higher), which moves the pendulum centre off the centre of mass.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from twind.errors import TwindError
from twind.model.mechanics import Mechanics
from twind.model.params import ALL_DOFS, SOSParams
from twind.model.violin import Segment

DOFS: tuple[str, ...] = ALL_DOFS  # POS, PIT, YAW, SIDE, VERT, ROLL

# q = S x with x = (t_x, t_y, t_z, w_x, w_y, w_z): POS=t_x, PIT=w_y, YAW=-w_z, SIDE=t_y, VERT=t_z,
# ROLL=w_x. The minus on YAW makes a face point at +y move toward +x for positive YAW (docs/model.md).
_S = np.zeros((6, 6))
for _row, (_col, _sign) in enumerate([(0, 1), (4, 1), (5, -1), (1, 1), (2, 1), (3, 1)]):
    _S[_row, _col] = _sign

_PENDULUM = ("POS", "PIT", "YAW", "SIDE")
_STIFF = ("VERT", "ROLL")  # coordinates held by the axial wire stiffness

_MAX_ITER = 200
_MAX_ROTATION_RAD = 0.5  # beyond this the optic has tumbled, not settled near its nominal pose


class GeometryError(TwindError):
    """A wire geometry is malformed or cannot hold the optic."""


class SlackWireError(GeometryError):
    """A wire segment would be slack at equilibrium (wires only pull)."""


class NoEquilibriumError(GeometryError):
    """The wires have no stable equilibrium near the nominal pose of the optic."""


@dataclass(frozen=True)
class WireGeometry:
    """Declarative description of a rigid optic hung by straight, axially elastic wires.

    Attributes
    ----------
    clamp_m : ndarray, shape (n, 3)
        Clamp points in the suspension frame (m), x along the beam, y sideways, z up.
    attach_m : ndarray, shape (n, 3)
        Attachment (break-off) points in the body frame relative to the centre of mass (m).
    unstretched_m : ndarray, shape (n,)
        Unstretched length of each segment (m).
    axial_stiffness_Npm : ndarray, shape (n,)
        Axial stiffness ``E A / L0`` of each segment (N/m).
    mass_kg : float
        Optic mass.
    inertia_kgm2 : ndarray, shape (3, 3)
        Inertia tensor about the centre of mass in the body frame (axes x, y, z at the nominal
        pose).
    Q : dict
        Free-swinging quality factor per coordinate of :data:`DOFS`.
    names : tuple of str
        One name per wire segment, used in error messages.
    g_mps2 : float
        Gravitational acceleration.
    """

    clamp_m: NDArray[np.float64]
    attach_m: NDArray[np.float64]
    unstretched_m: NDArray[np.float64]
    axial_stiffness_Npm: NDArray[np.float64]
    mass_kg: float
    inertia_kgm2: NDArray[np.float64]
    Q: Mapping[str, float] = field(default_factory=lambda: {d: 500.0 for d in DOFS})
    names: tuple[str, ...] = ()
    g_mps2: float = 9.81

    def __post_init__(self) -> None:
        clamp = np.atleast_2d(np.asarray(self.clamp_m, dtype=float))
        n = clamp.shape[0]
        arrays = {
            "clamp_m": clamp,
            "attach_m": np.atleast_2d(np.asarray(self.attach_m, dtype=float)),
            "unstretched_m": np.atleast_1d(np.asarray(self.unstretched_m, dtype=float)),
            "axial_stiffness_Npm": np.atleast_1d(np.asarray(self.axial_stiffness_Npm, dtype=float)),
            "inertia_kgm2": np.asarray(self.inertia_kgm2, dtype=float),
        }
        for key, value in arrays.items():
            object.__setattr__(self, key, value)
        names = tuple(self.names) or tuple(f"wire {i}" for i in range(n))
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "Q", dict(self.Q))
        _validate(self)

    @property
    def n_wires(self) -> int:
        """Number of wire segments."""
        return self.clamp_m.shape[0]

    @classmethod
    def from_params(
        cls,
        p: SOSParams,
        *,
        attach_offsets: ArrayLike | None = None,
        clamp_offsets: ArrayLike | None = None,
        com_offset: ArrayLike | None = None,
    ) -> WireGeometry:
        """Build the SOS geometry of T000134 (one wire loop = two segments), optionally perturbed.

        Nominal geometry (centre of mass at the origin): clamps at ``(0, +-R1, b + l)``,
        break-offs at ``(0, +-R2, b)``, so the vertical extent of each segment is ``l``. The
        axial stiffness per segment is chosen so that the vertical stiffness of the nominal
        geometry is ``vertical_stiffness_Npm`` (that is ``k_v / 2 / cos^2(alpha)`` less a tiny
        geometric term, 1.5 % above ``k_v / 2`` for the inclined wires; VERT is then exactly
        ``sqrt(k_v / m)``). Each segment is cut so that, at the nominal pose and with the
        nominal tension ``m g L / (2 l)``, it spans its clamp and break-off points *including*
        the offsets: raising a clamp by ``d`` makes that wire ``d`` longer instead of lifting
        one side of the optic.

        Parameters
        ----------
        p : SOSParams
            Suspension parameters.
        attach_offsets : array_like, shape (2, 3), optional
            Displacement (m) of the break-off points (+y segment first) on the optic.
        clamp_offsets : array_like, shape (2, 3), optional
            Displacement (m) of the clamp points (+y segment first) in the frame.
        com_offset : array_like, shape (3,), optional
            Displacement (m) of the centre of mass in the optic (e.g. ``(delta, 0, 0)``: off the
            wire plane along the beam). The wires are unchanged; the optic settles to a new pose.

        Returns
        -------
        WireGeometry
        """
        m, g, l, b = p.mass_kg, p.g_mps2, p.wire_length_m, p.b_m
        side = np.array([1.0, -1.0])
        clamp = np.stack([np.zeros(2), side * p.R1_m, np.full(2, b + l)], axis=1)
        attach = np.stack([np.zeros(2), side * p.R2_m, np.full(2, b)], axis=1)
        length = float(np.hypot(l, p.R2_m - p.R1_m))
        tension = m * g * length / (2 * l)
        cos2 = (l / length) ** 2
        k_axial = (p.vertical_stiffness_Npm / 2 - tension / length * (1 - cos2)) / cos2

        clamp = clamp + _offsets(clamp_offsets, (2, 3), "clamp_offsets")
        attach = attach + _offsets(attach_offsets, (2, 3), "attach_offsets")
        span = np.linalg.norm(clamp - attach, axis=1)
        com = _offsets(com_offset, (3,), "com_offset")
        inertia = np.diag([p.I_roll_kgm2, p.I_pitch_kgm2, p.I_yaw_kgm2])
        return cls(
            clamp_m=clamp,
            attach_m=attach - com,
            unstretched_m=span - tension / k_axial,
            axial_stiffness_Npm=np.full(2, k_axial),
            mass_kg=m,
            inertia_kgm2=inertia,
            Q={d: p.Q[d] for d in DOFS},
            names=("+y segment", "-y segment"),
            g_mps2=g,
        )


@dataclass(frozen=True)
class Equilibrium:
    """Static equilibrium of a :class:`WireGeometry`.

    Attributes
    ----------
    com_m : ndarray, shape (3,)
        Centre-of-mass position in the frame (m).
    rotation : ndarray, shape (3, 3)
        Orientation of the optic (body to frame).
    tensions_N : ndarray, shape (n,)
        Tension of each wire segment (N).
    lengths_m : ndarray, shape (n,)
        Stretched length of each segment (m).
    iterations : int
        Newton iterations used.
    """

    com_m: NDArray[np.float64]
    rotation: NDArray[np.float64]
    tensions_N: NDArray[np.float64]
    lengths_m: NDArray[np.float64]
    iterations: int

    def pose(self) -> dict[str, float]:
        """Pose in the coordinates of :data:`DOFS` (m, rad; rotation vector from the nominal)."""
        rotvec = Rotation.from_matrix(self.rotation).as_rotvec()
        x = np.concatenate([self.com_m, rotvec])
        return dict(zip(DOFS, (_S @ x).tolist()))


@dataclass(frozen=True)
class GeometricModel:
    """Equilibrium and linear dynamics of a wire-hung optic.

    Attributes
    ----------
    geometry : WireGeometry
    equilibrium : Equilibrium
    mechanics : Mechanics
        Over :data:`DOFS`, about the equilibrium.
    """

    geometry: WireGeometry
    equilibrium: Equilibrium
    mechanics: Mechanics


def geometric_model(geom: WireGeometry) -> GeometricModel:
    """Solve the equilibrium of `geom` and linearise about it.

    Parameters
    ----------
    geom : WireGeometry

    Returns
    -------
    GeometricModel

    Raises
    ------
    SlackWireError
        A wire would be slack at equilibrium.
    NoEquilibriumError
        No stable equilibrium near the nominal pose.
    """
    eq = solve_equilibrium(geom)
    K = wire_stiffness(geom, eq)
    K = 0.5 * (K + K.T)  # the analytic Hessian is symmetric; remove round-off asymmetry
    M = _S @ _mass_matrix(geom, eq.rotation) @ _S.T
    _check_stable(M, K)
    C = np.diag(_damping(geom, M, K))
    return GeometricModel(geom, eq, Mechanics(DOFS, M, C, K))


def geometric_mechanics(geom: WireGeometry) -> Mechanics:
    """Linear dynamics of `geom` about its equilibrium, coordinates :data:`DOFS`.

    Parameters
    ----------
    geom : WireGeometry

    Returns
    -------
    Mechanics
        POS, PIT, YAW, SIDE, VERT, ROLL in the OSEM sign convention (see module docstring).
    """
    return geometric_model(geom).mechanics


def wire_segments(model: GeometricModel) -> list[Segment]:
    """Each wire segment at the equilibrium, as its violin modes see it
    (:mod:`twind.model.violin`): its own tension and length, its axis, and its break-off
    point's motion ``dt + w x a`` over :data:`DOFS`.

    Parameters
    ----------
    model : GeometricModel

    Returns
    -------
    list of Segment
        Named ``+y`` and ``-y`` for the SOS's two (the sign of each break-off's y), or by
        number beyond two.
    """
    geom, eq = model.geometry, model.equilibrium
    segments = []
    for i in range(geom.n_wires):
        lever = eq.rotation @ geom.attach_m[i]  # lab frame, from the centre of mass
        axis = (geom.clamp_m[i] - (eq.com_m + lever)) / eq.lengths_m[i]
        motion = np.hstack([np.eye(3), -_skew(lever[None])[0]]) @ _S.T  # (3, 6) over DOFS
        name = ("+y" if lever[1] > 0 else "-y") if geom.n_wires == 2 else str(i)
        segments.append(Segment(name, float(eq.tensions_N[i]), float(eq.lengths_m[i]),
                                motion, axis))
    return segments


def pendulum_centre_offset(model: GeometricModel) -> float:
    """docs/model.md's ``wire_asymmetry`` delta (m): how far the centre of mass lies along SIDE from
    the wires' pendulum centre, the ``T/L``-weighted mean lateral position of the break-offs.

    With it the POS<->YAW stiffness of near-vertical wires is ``-m g delta / l``
    (``sum_i T_i y_i / L_i``, see the module docstring); unequal wire lengths make it, a
    sideways centre of mass between equal wires does not.

    Parameters
    ----------
    model : GeometricModel

    Returns
    -------
    float
    """
    eq = model.equilibrium
    y = (eq.rotation @ model.geometry.attach_m.T)[1]  # lab-frame, from the centre of mass
    w = eq.tensions_N / eq.lengths_m
    return float(-np.sum(w * y) / np.sum(w))


def solve_equilibrium(geom: WireGeometry) -> Equilibrium:
    """Minimise the potential energy of `geom`, starting from the nominal pose.

    Parameters
    ----------
    geom : WireGeometry

    Returns
    -------
    Equilibrium

    Raises
    ------
    SlackWireError
        A wire would be slack at equilibrium.
    NoEquilibriumError
        The iteration does not settle near the nominal pose.
    """
    t, R = np.zeros(3), np.eye(3)
    # rotations are scaled by the lever-arm size so that the damped Newton step treats metres
    # and radians alike (pitch stiffness ~1e-3 N m/rad vs pendulum ~10 N/m)
    rho = max(float(np.sqrt(np.mean(np.sum(geom.attach_m**2, axis=1)))), 1e-3)
    scale = np.concatenate([np.ones(3), np.full(3, 1.0 / rho)])
    tol = 1e-11 * geom.mass_kg * geom.g_mps2
    lam = 0.0
    for it in range(1, _MAX_ITER + 1):
        energy, grad, hess = _hessian(geom, t, R)
        gs, hs = grad * scale, hess * np.outer(scale, scale)
        if np.linalg.norm(gs) < tol:
            return _finish(geom, t, R, it)
        t, R, lam = _damped_step(geom, t, R, energy, gs, hs, scale, lam)
        _check_not_tumbled(geom, t, R)
    raise NoEquilibriumError(
        f"no equilibrium found in {_MAX_ITER} iterations (residual force "
        f"{np.linalg.norm(_hessian(geom, t, R)[1] * scale):.3g} N): the wires cannot hold the optic "
        "near its nominal pose"
    )


def wire_stiffness(geom: WireGeometry, eq: Equilibrium) -> NDArray[np.float64]:
    """6x6 stiffness in the coordinates of :data:`DOFS` at `eq` (the Hessian of the potential).

    Parameters
    ----------
    geom : WireGeometry
    eq : Equilibrium

    Returns
    -------
    ndarray, shape (6, 6)
    """
    return _S @ _hessian(geom, eq.com_m, eq.rotation)[2] @ _S.T


def potential_energy(geom: WireGeometry, q: ArrayLike, eq: Equilibrium) -> float:
    """Potential energy (J) at coordinates `q` (over :data:`DOFS`) relative to the pose `eq`.

    The rotation part of `q` is a lab-frame rotation vector applied after ``eq.rotation``, the
    same chart in which :func:`wire_stiffness` is the Hessian; meant for checking it.

    Parameters
    ----------
    geom : WireGeometry
    q : array_like, shape (6,)
    eq : Equilibrium

    Returns
    -------
    float
    """
    x = _S.T @ np.asarray(q, dtype=float)
    R = Rotation.from_rotvec(x[3:]).as_matrix() @ eq.rotation
    return _energy(geom, eq.com_m + x[:3], R)


def _offsets(value: ArrayLike | None, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    if value is None:
        return np.zeros(shape)
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise GeometryError(f"{name}: expected shape {shape}, got {arr.shape}")
    return arr


def _validate(geom: WireGeometry) -> None:
    n = geom.clamp_m.shape[0]
    expected = {"clamp_m": (n, 3), "attach_m": (n, 3), "unstretched_m": (n,),
                "axial_stiffness_Npm": (n,), "inertia_kgm2": (3, 3)}
    for key, shape in expected.items():
        if getattr(geom, key).shape != shape:
            raise GeometryError(f"{key}: expected shape {shape}, got {getattr(geom, key).shape}")
    if n == 0:
        raise GeometryError("a wire geometry needs at least one wire")
    if len(geom.names) != n:
        raise GeometryError(f"names: {len(geom.names)} names for {n} wires")
    for name, length, k in zip(geom.names, geom.unstretched_m, geom.axial_stiffness_Npm):
        if not length > 0:
            raise GeometryError(f"{name}: unstretched length must be positive, got {length}")
        if not k > 0:
            raise GeometryError(f"{name}: axial stiffness must be positive, got {k}")
    if not geom.mass_kg > 0:
        raise GeometryError(f"mass_kg must be positive, got {geom.mass_kg}")
    I = geom.inertia_kgm2
    if not np.allclose(I, I.T) or np.linalg.eigvalsh(0.5 * (I + I.T)).min() <= 0:
        raise GeometryError("inertia_kgm2 must be symmetric positive definite")
    for dof in DOFS:
        if not geom.Q.get(dof, 0) > 0:
            raise GeometryError(f"Q.{dof}: must be positive, got {geom.Q.get(dof)}")


def _skew(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cross-product matrices ``[a]x`` (``[a]x v = a x v``) for a stack of vectors (n, 3)."""
    z = np.zeros(a.shape[0])
    return np.stack([
        np.stack([z, -a[:, 2], a[:, 1]], axis=1),
        np.stack([a[:, 2], z, -a[:, 0]], axis=1),
        np.stack([-a[:, 1], a[:, 0], z], axis=1),
    ], axis=1)


def _wires(
    geom: WireGeometry, t: NDArray[np.float64], R: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Lever arms, unit vectors, lengths and (one-sided) tensions of the wires at a pose."""
    a = geom.attach_m @ R.T
    d = t + a - geom.clamp_m
    L = np.linalg.norm(d, axis=1)
    u = d / L[:, None]
    T = geom.axial_stiffness_Npm * np.maximum(L - geom.unstretched_m, 0.0)
    return a, u, L, T


def _energy(geom: WireGeometry, t: NDArray[np.float64], R: NDArray[np.float64]) -> float:
    _, _, L, T = _wires(geom, t, R)
    stretch = T / geom.axial_stiffness_Npm
    return float(geom.mass_kg * geom.g_mps2 * t[2] + 0.5 * np.sum(geom.axial_stiffness_Npm * stretch**2))


def _hessian(
    geom: WireGeometry, t: NDArray[np.float64], R: NDArray[np.float64]
) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """Energy, gradient (6,) and Hessian (6, 6) in ``(t, w)`` with ``R -> exp([w]x) R``."""
    a, u, L, T = _wires(geom, t, R)
    taut = (T > 0)[:, None, None]
    uu = u[:, :, None] * u[:, None, :]
    H = np.where(taut, geom.axial_stiffness_Npm[:, None, None] * uu
                 + (T / L)[:, None, None] * (np.eye(3) - uu), 0.0)
    g = T[:, None] * u  # dE_i/dp_i
    A = _skew(a)
    dp_dw = -A  # dp/dw = w x a = -[a]x w

    grad = np.concatenate([
        g.sum(axis=0) + np.array([0.0, 0.0, geom.mass_kg * geom.g_mps2]),
        np.einsum("nji,nj->i", dp_dw, g),
    ])
    Ktt = H.sum(axis=0)
    Ktw = np.einsum("nij,njk->ik", H, dp_dw)
    lever = np.einsum("nji,njk,nkl->il", dp_dw, H, dp_dw)
    ga = np.einsum("ni,nj->ij", g, a)
    # second-order term of exp([w]x) a = a + w x a + 1/2 w x (w x a) contracted with g
    rotation = 0.5 * (ga + ga.T) - np.trace(ga) * np.eye(3)
    hess = np.block([[Ktt, Ktw], [Ktw.T, lever + rotation]])
    energy = float(geom.mass_kg * geom.g_mps2 * t[2]
                   + 0.5 * np.sum(T**2 / geom.axial_stiffness_Npm))
    return energy, grad, hess


def _damped_step(
    geom: WireGeometry, t: NDArray[np.float64], R: NDArray[np.float64], energy: float,
    gs: NDArray[np.float64], hs: NDArray[np.float64], scale: NDArray[np.float64], lam: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """One Levenberg-Marquardt-damped Newton step that lowers the energy; returns new t, R, lam."""
    diag_scale = max(float(np.max(np.abs(np.diag(hs)))), geom.mass_kg * geom.g_mps2)
    # energy differences below this are round-off of the sum, not a failed descent
    round_off = 1e-13 * (abs(energy) + geom.mass_kg * geom.g_mps2 * float(np.max(geom.unstretched_m)))
    for _ in range(60):
        try:
            chol = np.linalg.cholesky(hs + lam * diag_scale * np.eye(6))
        except np.linalg.LinAlgError:
            lam = max(10 * lam, 1e-8)
            continue
        step = -np.linalg.solve(chol.T, np.linalg.solve(chol, gs)) * scale
        t_new = t + step[:3]
        R_new = Rotation.from_rotvec(step[3:]).as_matrix() @ R
        predicted = float(gs @ (step / scale))
        if _energy(geom, t_new, R_new) <= energy + 1e-4 * predicted + round_off:
            return t_new, R_new, lam / 10 if lam > 1e-12 else 0.0
        lam = max(10 * lam, 1e-8)
    raise NoEquilibriumError(
        "the energy minimisation stalled: no stable equilibrium near the nominal pose "
        "(check that the wires can hold the optic above its centre of mass)"
    )


def _check_not_tumbled(geom: WireGeometry, t: NDArray[np.float64], R: NDArray[np.float64]) -> None:
    angle = float(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()))
    reach = float(np.max(geom.unstretched_m) + np.max(np.linalg.norm(geom.attach_m, axis=1)))
    if angle > _MAX_ROTATION_RAD or np.linalg.norm(t) > 10 * reach:
        raise NoEquilibriumError(
            f"no equilibrium near the nominal pose: the optic tumbles (rotated by {angle:.2f} rad, "
            f"centre of mass moved {np.linalg.norm(t):.3g} m); is the centre of mass below the "
            "attachment points?"
        )


def _finish(
    geom: WireGeometry, t: NDArray[np.float64], R: NDArray[np.float64], iterations: int
) -> Equilibrium:
    _, _, L, T = _wires(geom, t, R)
    span = L - geom.unstretched_m
    for i, name in enumerate(geom.names):
        if span[i] <= 0:
            raise SlackWireError(
                f"{name} is slack at equilibrium: clamp-to-attachment distance {L[i]:.6g} m is "
                f"not longer than its unstretched length {geom.unstretched_m[i]:.6g} m "
                "(wires only pull; shorten it or move its clamp)"
            )
    return Equilibrium(t.copy(), R.copy(), T, L, iterations)


def _mass_matrix(geom: WireGeometry, R: NDArray[np.float64]) -> NDArray[np.float64]:
    M = np.zeros((6, 6))
    M[:3, :3] = geom.mass_kg * np.eye(3)
    M[3:, 3:] = R @ geom.inertia_kgm2 @ R.T  # inertia tensor in the frame at the equilibrium
    return M


def _check_stable(M: NDArray[np.float64], K: NDArray[np.float64]) -> None:
    """Every normal mode needs a positive stiffness, else the equilibrium is a saddle."""
    w2, v = np.linalg.eig(np.linalg.solve(M, K))
    w2 = w2.real
    scale = float(np.max(np.abs(w2)))
    for k in np.flatnonzero(w2 <= 1e-12 * scale):
        dof = DOFS[int(np.argmax(np.abs(v[:, k]) * np.sqrt(np.diag(M))))]
        raise NoEquilibriumError(
            f"no stable equilibrium: the mode dominated by {dof} has stiffness "
            f"{w2[k]:.3g} s^-2 <= 0 (the wires do not hold the optic in {dof}; e.g. centre of mass "
            "above the break-off points, or too few wires)"
        )


def _damping(geom: WireGeometry, M: NDArray[np.float64], K: NDArray[np.float64]) -> NDArray[np.float64]:
    """``M_ii w_i / Q_i`` with ``w_i`` from the stiffness seen once VERT and ROLL have relaxed."""
    slow = [DOFS.index(d) for d in _PENDULUM]
    fast = [DOFS.index(d) for d in _STIFF]
    Kc = K[np.ix_(slow, slow)] - K[np.ix_(slow, fast)] @ np.linalg.solve(
        K[np.ix_(fast, fast)], K[np.ix_(fast, slow)])
    k_eff = np.diag(K).copy()
    k_eff[slow] = np.diag(Kc)
    w = np.sqrt(np.clip(k_eff / np.diag(M), 0.0, None))
    Q = np.array([geom.Q[d] for d in DOFS])
    return np.diag(M) * w / Q
