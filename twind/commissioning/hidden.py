"""Effects put into an optic's plant by hand, for the demo and the proof corpus, written
independently of :mod:`twind.model.effects` (whose models the diagnosis fits): the coil or
OSEM columns, a raised clamp in the geometric model (:func:`raised_clamp`), face heads
tilted against the optic (:func:`tilted_heads`), a body on a spring at a face point
(:func:`attached_body`), one channel's own stage (:func:`one_stage`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from twind import OSEMS
from twind.model.geometric import (
    WireGeometry,
    geometric_mechanics,
    geometric_model,
    pendulum_centre_offset,
)
from twind.model.mechanics import Mechanics
from twind.model.osem import FACE_POSITION
from twind.model.params import SOSParams
from twind.model.plant import Plant

FACES = ("UL", "UR", "LL", "LR")
# directions of four face gains a damping-loop measurement determines: pitch-like and
# yaw-like; their mean is a change of coil (or lever) strength, their butterfly is unseen
SEEN = np.array([[1.0, 1.0, -1.0, -1.0], [1.0, -1.0, 1.0, -1.0]]) / 2


def hidden(plant: Plant, effect: str, size: float, direction: NDArray[np.float64],
           sus: SOSParams | None = None, shape: dict | None = None) -> tuple[Plant, dict]:
    """`plant` with `effect` of `size` put in by hand, and its parameters in the names of
    docs/model.md.

    `direction` (4 values) spreads an imbalance over the face coils or OSEMs.
    ``wire_asymmetry`` is one wire loop's clamp raised by `size` (m) in the geometric
    rigid-body model of `sus` (the suspension's parameters), not docs/model.md's formula.
    ``resonance`` is a body of mass `size` (kg) attached as `shape` says (``f_hz``, ``q``,
    ``point_m``, ``axis``: :func:`attached_body`); ``channel_filter`` one channel's stage
    with its zero `size` (a fraction) above its pole (``kind``, ``channel``, ``pole_hz``:
    :func:`one_stage`).

    Parameters
    ----------
    plant : Plant
        The drifted optic's plant.
    effect : str
        One of :data:`MADE`.
    size : float
        The effect's size: face gains' scale, extra delay (s), the driver pole's ``1/f``
        (s), SIDE's share in the face OSEMs, clamp rise (m), the heads' tilt towards VERT
        (rad), body mass (kg) or the stage's zero-pole separation (fraction).
    direction : ndarray
        Four face gains (UL, UR, LL, LR) of an imbalance; the sign of its first picks a
        ``wire_asymmetry``'s loop.
    sus : SOSParams, optional
        The suspension's parameters; needed for ``wire_asymmetry`` and ``bounce_roll``.
    shape : dict, optional
        Keyword arguments of :func:`attached_body` or :func:`one_stage`.

    Returns
    -------
    plant : Plant
    truth : dict
        The effect's parameters in docs/model.md's names.

    Raises
    ------
    ValueError
        If `effect` is not one the corpus makes, or `sus` is missing where needed.
    """
    if effect == "resonance":
        return attached_body(plant, sus, size, **(shape or {}))
    if effect == "channel_filter":
        return one_stage(plant, size, **(shape or {}))
    if effect == "coil_imbalance":
        gains = size * direction  # docs/model.md's g_i: F_i (1 + g_i)
        act = plant.actuation.copy()
        act[:, :4] *= 1 + gains
        return replace(plant, actuation=act), {"gains": dict(zip(FACES, gains.tolist(),
                                                                  strict=True))}
    if effect == "osem_imbalance":
        gains = size * direction
        sens = plant.sensing.copy()
        sens[:4] *= (1 + gains)[:, None]
        return replace(plant, sensing=sens), {"gains": dict(zip(FACES, gains.tolist(),
                                                                strict=True))}
    size = float(size)
    if effect == "loop_delay":
        return replace(plant, delay_s=plant.delay_s + size), {"extra_s": size}
    if effect == "actuator_pole":
        return replace(plant, drive_pole_hz=1 / size), {"f_hz": 1 / size}
    if effect == "side_coupling":
        sens = plant.sensing.copy()
        sens[:4, 3] += size
        return replace(plant, sensing=sens), {"sensing": size}
    if effect in ("wire_asymmetry", "bounce_roll"):
        if sus is None:
            msg = f"a hand-made {effect} needs the suspension's parameters (sus)"
            raise ValueError(msg)
        if effect == "wire_asymmetry":
            return raised_clamp(plant, sus, size)
        # the optic pitched against its heads: a yaw would put SIDE into the face OSEMs at
        # first order, and that side coupling, not the modes, is what a measurement sees
        return tilted_heads(plant, sus, 0.0, size)
    msg = f"the corpus has no hand-made {effect!r}; it makes {', '.join(MADE)}"
    raise ValueError(msg)


def raised_clamp(plant: Plant, sus: SOSParams, rise_m: float) -> tuple[Plant, dict]:
    """`plant` with the +y wire loop's clamp raised by `rise_m` (the -y one's when negative).

    The change it makes to the POS/PIT/YAW stiffness comes from the geometric rigid body
    (equilibrium and Hessian of the wires), so the longer wire's softer pull, and with it
    the POS<->YAW coupling, is not docs/model.md's formula put back; docs/model.md's
    ``delta_m`` is the geometry's pendulum-centre offset.

    Parameters
    ----------
    plant : Plant
    sus : SOSParams
        The suspension's parameters (the geometric model's wires).
    rise_m : float
        How far the clamp is raised (m); negative raises the -y loop's.

    Returns
    -------
    plant : Plant
    truth : dict
        ``delta_m``: the pendulum-centre offset (m).
    """

    offsets = np.zeros((2, 3))
    offsets[0 if rise_m >= 0 else 1, 2] = abs(rise_m)
    level = geometric_model(WireGeometry.from_params(sus))
    raised = geometric_model(WireGeometry.from_params(sus, clamp_offsets=offsets))
    geo, mech = level.mechanics, plant.mechanics
    dofs = ("POS", "PIT", "YAW")
    dK = (raised.mechanics.K - geo.K)[np.ix_(*[[geo.index(d) for d in dofs]] * 2)]
    # the analytical model's PIT is T000134's, opposite to the geometry's OSEM convention:
    # take the plant's by the sign of its POS-PIT stiffness
    i, j = mech.index("POS"), mech.index("PIT")
    flip = mech.K[i, j] * geo.K[geo.index("POS"), geo.index("PIT")] < 0
    S = np.diag([1.0, -1.0 if flip else 1.0, 1.0])
    at = [mech.index(d) for d in dofs]
    K = mech.K.copy()
    K[np.ix_(at, at)] += S @ dK @ S
    return (replace(plant, mechanics=Mechanics(mech.dofs, mech.M, mech.C, K)),
            {"delta_m": pendulum_centre_offset(raised)})


def tilted_heads(plant: Plant, sus: SOSParams, towards_side: float, towards_vert: float
                 ) -> tuple[Plant, dict]:
    """`plant` with the geometric rigid body's VERT and ROLL modes, and every face OSEM's
    axis (and its coaxial coil's) tilted by the same small angles (rad) towards SIDE and
    towards VERT: how a statically pitched or yawed optic sits against its heads.

    What each head reads and pushes is 3-D kinematics of the tilted axis ``n`` at the face
    point ``r``: ``n . (t + theta x r)``, with ``t = (POS, SIDE, VERT)`` and ``theta`` =
    (ROLL, PIT, -YAW) in the plant's sign convention; the modes' mass, stiffness and damping
    are the geometric model's (its roll a little above ``sqrt(k_v R2^2 / I_roll)``).
    Nothing goes through the catalogue's ``bounce_roll``; docs/model.md's parameters come
    out of the geometry: ``vertical`` = (sensing x actuation of VERT per face head),
    ``roll`` the same of ROLL per unit lever, and the modes' frequencies.

    Parameters
    ----------
    plant : Plant
        A plant without VERT and ROLL coordinates.
    sus : SOSParams
        The suspension's parameters (the geometric model and the heads' lever).
    towards_side, towards_vert : float
        The heads' tilt (rad).

    Returns
    -------
    plant : Plant
        With VERT and ROLL, and the face heads' sensing and actuation rebuilt.
    truth : dict
        ``vertical``, ``roll``, ``f_vertical_hz``, ``f_roll_hz`` and ``roll_angle``.
    """

    geo = geometric_mechanics(WireGeometry.from_params(sus))
    mech, extra = plant.mechanics, ("VERT", "ROLL")
    at = [geo.index(d) for d in extra]
    n0 = mech.n
    M, C, K = (np.pad(a, (0, 2)) for a in (mech.M, mech.C, mech.K))
    for a, g in ((M, geo.M), (C, geo.C), (K, geo.K)):
        a[n0:, n0:] = g[np.ix_(at, at)]
    dofs = (*mech.dofs, *extra)
    # not normalised: the cos(tilt) it would take off each head's POS reading and push is a
    # common OSEM and coil gain, the drift's business; the case hides what tilt adds
    axis = np.array([1.0, towards_side, towards_vert])
    sensing = np.pad(plant.sensing, ((0, 0), (0, 2)))
    for i, (y, z) in enumerate(FACE_POSITION.values()):
        r = np.array([0.0, y, z]) * sus.osem_lever_m
        motion = np.zeros((3, len(dofs)))  # face-point displacement per coordinate
        for d, e in (("POS", 0), ("SIDE", 1), ("VERT", 2)):
            motion[e, dofs.index(d)] = 1.0
        for d, w in (("ROLL", (1, 0, 0)), ("PIT", (0, 1, 0)), ("YAW", (0, 0, -1))):
            motion[:, dofs.index(d)] = np.cross(w, r)
        sensing[i] = axis @ motion
    gains = np.array([sus.coil_N_per_ct] * 4 + [sus.side_coil_N_per_ct])
    tilted = replace(plant, mechanics=Mechanics(dofs, M, C, K), sensing=sensing,
                     actuation=-sensing.T * gains)
    f = {d: float(np.sqrt(K[i, i] / M[i, i]) / (2 * np.pi)) for i, d in enumerate(dofs)
         if d in extra}
    lever = sus.osem_lever_m
    vertical = sensing[0, dofs.index("VERT")] ** 2
    roll = float(np.mean(sensing[:4, dofs.index("ROLL")] ** 2)) / lever**2
    return tilted, {"vertical": float(vertical), "roll": roll,
                    "f_vertical_hz": f["VERT"], "f_roll_hz": f["ROLL"],
                    "roll_angle": math.atan2(towards_vert, -towards_side) % math.pi}


def attached_body(plant: Plant, sus: SOSParams, mass_kg: float, f_hz: float, q: float,
                  point_m: tuple[float, float], axis: Sequence[float] = (1.0, 0.0, 0.0)
                  ) -> tuple[Plant, dict]:
    """`plant` with a small body (`mass_kg`) held by a spring (resonance `f_hz`, quality
    factor `q`) to the face point ``point_m`` = (y, z), pulling along `axis` (POS, SIDE,
    VERT components): a loose cable or a ringing standoff.

    The spring stretches by ``u - n . (t + theta x r)``, the body's displacement less the
    face point's along the axis, in 3-D kinematics with ``t = (POS, SIDE, VERT)`` and
    ``theta = (ROLL, PIT, -YAW)`` as :func:`tilted_heads` has them; the body is a new
    coordinate of the mechanics in metres. Nothing goes through the catalogue's
    ``resonance``; the truth is given as the issue's reading: ``f_hz``, ``q``, ``mass_kg``,
    the point and the DOFs it couples (``coupled``).

    Parameters
    ----------
    plant : Plant
    sus : SOSParams
        Unused (the signature :func:`hidden` calls).
    mass_kg : float
        The body's mass (kg).
    f_hz : float
        Its resonance (Hz) on the spring, the optic held still.
    q : float
        Its quality factor.
    point_m : (float, float)
        The face point (y, z) (m) from the centre.
    axis : sequence of float
        The pull's direction (POS, SIDE, VERT); normalised here.

    Returns
    -------
    plant : Plant
        With a new coordinate ``ATTACHED`` (m).
    truth : dict
    """
    mech = plant.mechanics
    n = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    r = np.array([0.0, *point_m])
    motion = np.zeros((3, mech.n))
    for d, e in (("POS", 0), ("SIDE", 1), ("VERT", 2)):
        if d in mech.dofs:
            motion[e, mech.index(d)] = 1.0
    for d, w in (("ROLL", (1, 0, 0)), ("PIT", (0, 1, 0)), ("YAW", (0, 0, -1))):
        if d in mech.dofs:
            motion[:, mech.index(d)] = np.cross(w, r)
    link = np.append(-(n @ motion), 1.0)  # spring stretch per coordinate
    w = 2 * math.pi * f_hz
    M = np.pad(mech.M, (0, 1))
    M[-1, -1] = mass_kg
    K = np.pad(mech.K, (0, 1)) + mass_kg * w**2 * np.outer(link, link)
    C = np.pad(mech.C, (0, 1)) + mass_kg * w / q * np.outer(link, link)
    body = replace(plant, mechanics=Mechanics((*mech.dofs, "ATTACHED"), M, C, K),
                   sensing=np.pad(plant.sensing, ((0, 0), (0, 1))),
                   actuation=np.pad(plant.actuation, ((0, 1), (0, 0))))
    coupled = [d for d, x in zip(mech.dofs, n @ motion, strict=True) if abs(x) > 1e-12]
    return body, {"f_hz": f_hz, "q": q, "mass_kg": mass_kg, "point_m": list(point_m),
                  "coupled": coupled}


def one_stage(plant: Plant, separation: float, kind: str, channel: int, pole_hz: float
              ) -> tuple[Plant, dict]:
    """`plant` with one coil driver's (``kind`` "coil") or OSEM readback's ("osem") own
    stage: a pole at `pole_hz` and a zero `separation` (a fraction, may be negative) above
    it, put into the plant's channel filters, which the engine integrates as states.

    Parameters
    ----------
    plant : Plant
    separation : float
        The zero's distance above the pole, as a fraction of it.
    kind : str
        ``"coil"`` or ``"osem"``.
    channel : int
        Index into :data:`~twind.OSEMS` (0 is UL).
    pole_hz : float
        The stage's pole (Hz).

    Returns
    -------
    plant : Plant
    truth : dict
        ``channel`` (the catalogue's name, ``coil_filter_UL``), ``pole_hz``, ``zero_hz``.
    """
    zero = pole_hz * (1 + separation)
    stage = (kind, channel, pole_hz, zero)
    return (replace(plant, channel_filters=(*plant.channel_filters, stage)),
            {"channel": f"{kind}_filter_{OSEMS[channel]}", "pole_hz": pole_hz,
             "zero_hz": zero})


FIRST_SIZE = {"coil_imbalance": 1e-3, "osem_imbalance": 1e-3, "loop_delay": 1e-4,
               "actuator_pole": 1 / 300, "side_coupling": 1e-2, "wire_asymmetry": 1e-3,
               "bounce_roll": 1e-3, "resonance": 1e-4, "channel_filter": 0.1}
MADE = tuple(FIRST_SIZE)
"""Every effect the corpus can hide."""
