"""The proof corpus of ``twind diagnose`` and the benchmark that scores it
(``twind bench --suite diagnose``).

Each case is an optic whose nominal parameters drifted at random (:data:`SPREAD`) and,
except for the nulls, that carries one effect of the catalogue of docs/model.md, put into the plant
the twin runs *by hand here*: the coil or OSEM columns of the actuation and sensing
matrices, the loop delay, the coil-driver pole, the SIDE column of the face OSEMs; a wire
asymmetry is one loop's clamp raised in the geometric rigid-body model (:func:`raised_clamp`);
bounce and roll are the geometric body's VERT and ROLL seen by face heads whose axes tilt
against the optic, in 3-D kinematics (:func:`tilted_heads`).
Beyond the catalogue (:data:`BEYOND`): a small body on a spring at a face point, a new
coordinate of the mechanics in 3-D kinematics (:func:`attached_body`); one coil driver's or
OSEM readback's own pole/zero stage, integrated by the engine as a state
(:func:`one_stage`); and pairs of catalogue effects in one plant.
None of it goes through :mod:`twind.model.effects`, whose models the diagnosis fits to
explain it.
The twin's time-domain engine measures the optic, noise through the loop, and the
measurement reaches ``diagnose`` as users have it: a diaggui XML set (like example_null) or
an MCAP session with its injection events.

Each effect is concealed: scaled so that its largest change of any bin of ``IN1/EXC`` the
fit uses is :data:`CONCEAL_SIGMA` times that bin's standard error, while its change summed
over all bins (``present``, in chi^2 units) shows it is there.

Scored as the issue asks: the right effect named (or declared equivalent) with its key
parameter within 35 %; nothing claimed on the nulls; chi^2/nu after augmentation against
the nulls'; seconds per case. To tell a miss's scatter from a bias, each key parameter's
error is also given in its own fit's sigma (:func:`key_z`).

Not in the default corpus: ``side_coupling`` (see :data:`EFFECTS`).
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from twind import DOFS, OSEMS
from twind.analysis.diagnose import (
    MIN_COHERENCE,
    diagnose,
    evidence,
    explained,
    f_profile,
)
from twind.analysis.estimation.diaggui import write_measurement_set
from twind.analysis.estimation.tf import from_diaggui, from_session
from twind.analysis.identification.data import FitData
from twind.analysis.identification.inmatrix import recorded_input_matrix
from twind.analysis.identification.model import ClosedLoopModel
from twind.analysis.identification.params import FitError, param_value, with_params
from twind.config import OpticConfig
from twind.lab.measurement import SETTLE_S, measure_tfs, record_measurement
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
from twind.viz.report import write_report

CONCEAL_SIGMA = 3.0
"""Largest change of one bin of IN1/EXC an effect makes, in that bin's standard errors."""
SPREAD = {"wire_length_m": 0.015, "b_m": 0.02, "R1_m": 0.02, "coil_N_per_ct": 0.03,
          "osem_lever_m": 0.015, "Q_POS": 0.15, "Q_PIT": 0.15, "Q_YAW": 0.15, "Q_SIDE": 0.15}
"""Relative standard deviation of each nominal parameter's drift from case to case."""
EFFECTS = ("coil_imbalance", "osem_imbalance", "loop_delay", "actuator_pole", "wire_asymmetry",
           "bounce_roll")
"""The catalogue effects the corpus hides by default. ``side_coupling`` on request, with SIDE
among the excited DOFs: a POS/PIT/YAW measurement barely moves SIDE, so no physical
coupling reaches 3 sigma in it."""
BEYOND = ("resonance", "channel_filter", "coil_imbalance+loop_delay",
          "osem_imbalance+actuator_pole", "wire_asymmetry+coil_imbalance")
"""What the catalogue alone cannot say, hidden by default beside it: a body on the face
(:func:`attached_body`), one channel's own stage (:func:`one_stage`) and pairs of
catalogue effects, each concealed alone and then put in together."""
KEY_TOLERANCE = 0.35
RESOLVED_F = 0.15
"""A body the data resolve fixes its frequency within this fraction of it (95 %)."""
RESOLVED_MARGIN = 3.84
"""How much more (chi^2, nulls' units) the truth's structure must explain than what was
called a full explanation for that call to be wrong: one parameter's 95 %."""
AS_GOOD = 1.0
"""A hidden body's miss is the measurement's, not the search's, when the fit started at the
truth beats the search's by no more than this in chi^2 (one parameter's 1 sigma)."""
AVERAGES, RMS = 10, 3.0
EXCITED = ("POS", "PIT", "YAW")
"""The corpus measurement: white EXC of RMS 3 below 30 Hz on each of POS, PIT, YAW in turn,
Hann, 10 averages overlapping by half."""
ROUTE_BW = {"xml": 0.01, "mcap": 0.05}
"""Its resolution (Hz) per route: diaggui sets in example_null's format, the blind sets';
sessions of 5.5 min (at 0.01 Hz one is 27 min long, 2.2 GB of MCAP and 3 min to record).
At 0.05 Hz an effect concealed to the same largest bin has a fifth of the bins, and it is
1.7 to 4.9 times less present (the default effects, in chi^2 units)."""
STOP_HZ = 30.0  # example_null's StopFrequency: the bins a diaggui set holds
FACES = ("UL", "UR", "LL", "LR")
# directions of four face gains a damping-loop measurement determines: pitch-like and
# yaw-like; their mean is a change of coil (or lever) strength, their butterfly is unseen
_SEEN = np.array([[1.0, 1.0, -1.0, -1.0], [1.0, -1.0, 1.0, -1.0]]) / 2


@dataclass
class Case:
    """One optic of the corpus.

    Attributes
    ----------
    name : str
    effect : str or None
        The catalogue effect hidden in `plant`; None for a null.
    real : OpticConfig
        The drifted optic.
    plant : Plant
        The plant the twin runs.
    truth : dict
        The effect's parameters in the names of docs/model.md.
    largest_sigma : float
        Largest change of one bin of IN1/EXC the effect makes, in standard errors.
    present : float
        The effect's change summed over the bins, in chi^2 units.
    """

    name: str
    effect: str | None
    real: OpticConfig
    plant: Plant
    truth: dict = field(default_factory=dict)
    largest_sigma: float = 0.0
    present: float = 0.0


def drifted(cfg: OpticConfig, rng: np.random.Generator) -> OpticConfig:
    """`cfg` with each nominal parameter drifted by :data:`SPREAD` (Gaussian).

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    rng : numpy.random.Generator
        Draws the drifts.

    Returns
    -------
    OpticConfig
    """
    values = {k: param_value(cfg.sus, k) * (1 + s * rng.standard_normal())
              for k, s in SPREAD.items()}
    return replace(cfg, sus=with_params(cfg.sus, values))


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


_FIRST_SIZE = {"coil_imbalance": 1e-3, "osem_imbalance": 1e-3, "loop_delay": 1e-4,
               "actuator_pole": 1 / 300, "side_coupling": 1e-2, "wire_asymmetry": 1e-3,
               "bounce_roll": 1e-3, "resonance": 1e-4, "channel_filter": 0.1}
MADE = tuple(_FIRST_SIZE)
"""Every effect the corpus can hide."""


def conceal(real: OpticConfig, effect: str, reference: FitData, direction: NDArray,
            target: float = CONCEAL_SIGMA, shape: dict | None = None
            ) -> tuple[Plant, dict, float, float]:
    """The effect scaled so that its largest change of a bin ``diagnose`` fits is `target`
    standard errors of `reference` (a measurement of the same kind, its bins as
    ``diagnose`` chooses them).

    Parameters
    ----------
    real : OpticConfig
        The drifted optic.
    effect : str
        One of :data:`MADE`.
    reference : FitData
        The bins and errors the effect is concealed against (:func:`reference_data`).
    direction : ndarray
        Four face gains of an imbalance (see :func:`hidden`).
    target : float
        The largest change of one bin, in its standard errors.
    shape : dict, optional
        As :func:`hidden`.

    Returns
    -------
    plant : Plant
    truth : dict
        The effect's parameters, and ``_size``: the size to hide it again.
    largest : float
        Its largest change of one bin (standard errors).
    present : float
        Its change summed over the bins (chi^2 units).
    """
    base = real.plant()
    model = ClosedLoopModel.of(real, reference)
    rows, cols = _indices(reference)

    def in1(plant: Plant) -> NDArray[np.complex128]:
        return model.response(plant)[:, rows][:, :, cols]

    T0 = in1(base)

    def change(size: float) -> NDArray[np.float64]:
        z = np.abs(in1(hidden(base, effect, size, direction, real.sus, shape)[0]) - T0
                   ) / reference.sigma
        return z[reference.mask]

    size = _FIRST_SIZE[effect]
    if effect == "wire_asymmetry":  # either loop's clamp raised
        size = math.copysign(size, direction[0])
    # nearly linear in size (a tilt's modes: in its square): a few secant steps
    power = 0.5 if effect == "bounce_roll" else 1.0
    for _ in range(3):
        size *= (target / max(change(size).max(), 1e-12)) ** power
    if effect == "loop_delay":  # the engine delays by whole samples
        rate = real.sus.sample_rate_hz
        size = max(round(size * rate), 1) / rate
    z = change(size)
    plant, truth = hidden(base, effect, size, direction, real.sus, shape)
    truth["_size"] = size  # how to hide it again beside another effect (pairs)
    return plant, truth, float(z.max()), float(np.sum(z**2))


def _indices(data: FitData) -> tuple[list[int], list[int]]:

    return [DOFS.index(d) for d in data.responses], [DOFS.index(d) for d in data.excited]


def reference_data(cfg: OpticConfig, seed: int, excited: Sequence[str] = EXCITED,
                   route: str = "xml", bw: float | None = None, averages: int = AVERAGES,
                   rms: float = RMS) -> FitData:
    """A corpus measurement of the nominal optic on `route`, its bins as ``diagnose``
    chooses them: the errors the effects are concealed against.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    seed : int
        Seed of the twin's noise and the excitation.
    excited : sequence of str
        DOFs excited in turn.
    route : str
        ``"xml"`` (bins up to :data:`STOP_HZ`) or ``"mcap"``.
    bw : float, optional
        Resolution (Hz); default the route's (:data:`ROUTE_BW`).
    averages : int
    rms : float
        RMS of the white EXC.

    Returns
    -------
    FitData
    """

    tfs = measure_tfs(cfg, excited, bw=bw or ROUTE_BW[route], averages=averages, rms=rms,
                      seed=seed)
    band = (0.0, STOP_HZ) if route == "xml" else None
    return FitData.from_tfset(tfs, MIN_COHERENCE, band).span()


def make_cases(cfg: OpticConfig, reference: FitData | None, per_effect: int = 3, nulls: int = 3,
               seed: int = 11, effects: Sequence[str] = EFFECTS) -> list[Case]:
    """The corpus: `nulls` drifted optics and `per_effect` of each kind of `effects`
    (a catalogue effect, ``resonance``, ``channel_filter`` or a pair ``"a+b"``), each
    effect concealed.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    reference : FitData or None
        The bins and errors effects are concealed against (:func:`reference_data`); None
        when there are no effects.
    per_effect : int
        Cases of each kind of `effects`.
    nulls : int
        Cases with no effect.
    seed : int
        Seed of the drifts, directions and shapes.
    effects : sequence of str
        Kinds of effect hidden.

    Returns
    -------
    list of Case
        The nulls first.
    """
    rng = np.random.default_rng(seed)
    cases = []
    for k in range(nulls):
        real = drifted(cfg, rng)
        cases.append(Case(f"null #{k + 1}", None, real,
                          real.plant()))
    for effect in effects:
        for k in range(per_effect):
            real = drifted(cfg, rng)
            parts = effect.split("+")
            draws = [_draw(e, rng) for e in parts]
            hid = [conceal(real, e, reference, direction, shape=shape)
                   for e, (direction, shape) in zip(parts, draws, strict=True)]
            sizes = [h[1].pop("_size") for h in hid]
            if len(parts) == 1:
                plant, truth, largest, present = hid[0]
            else:  # each concealed alone, then both put into one plant
                plant = real.plant()
                for e, size, (direction, shape) in zip(parts, sizes, draws, strict=True):
                    plant = hidden(plant, e, size, direction, real.sus, shape)[0]
                truth = {e: h[1] for e, h in zip(parts, hid, strict=True)}
                largest = max(h[2] for h in hid)
                present = sum(h[3] for h in hid)
            cases.append(Case(f"{effect} #{k + 1}", effect, real, plant, truth, largest,
                              present))
    return cases


def _draw(effect: str, rng: np.random.Generator) -> tuple[NDArray, dict | None]:
    """A random direction (face gains) and the shape of a case."""
    direction = rng.standard_normal(4)
    direction /= np.abs(direction).max()
    shape = None
    if effect == "resonance":  # a body anywhere on the face, 0.3-20 Hz, Q 5-100
        shape = {"f_hz": float(np.exp(rng.uniform(math.log(0.3), math.log(20.0)))),
                 "q": float(np.exp(rng.uniform(math.log(5.0), math.log(100.0)))),
                 "point_m": (float(rng.uniform(-0.025, 0.025)),
                             float(rng.uniform(-0.025, 0.025)))}
    elif effect == "channel_filter":  # one face channel (SIDE is barely excited)
        shape = {"kind": str(rng.choice(["coil", "osem"])), "channel": int(rng.integers(4)),
                 "pole_hz": float(np.exp(rng.uniform(math.log(3.0), math.log(50.0))))}
    return direction, shape


# ------------------------------------------------------------------------------ scoring
@dataclass
class Score:
    """How ``diagnose`` did on one case."""

    case: Case
    named: bool  # the case's effect is the winner or declared equivalent (nulls: nothing)
    claimed: list[str]
    key_error: float  # relative error of the key parameter (nan: not named, or a null)
    key_z: float  # the same error in units of the fit's own sigma (RMS over its components)
    chi2_nu_nominal: float
    chi2_nu_final: float
    seconds: float  # measurement and diagnosis
    p_value: float = math.nan  # the hidden effect's; a null's smallest (its nearest claim)
    diagnosis_seconds: float = math.nan  # the diagnosis alone (what a blind set costs)
    located: bool = False  # a resonance: a band holding f +- 15 % located, or modelled
    forced: bool = False  # a resonance passed off as catalogue effects, nothing unexplained
    truth_p: float = math.nan  # a resonance: its p-value from a fit started at the truth
    truth_margin: float = math.nan
    """A resonance: how much better (in chi^2) the fit started at the truth explains the data
    than the search's own first fit; at or below :data:`AS_GOOD` the data do not prefer the
    truth to what the search found."""
    coupled: list[str] = field(default_factory=list)  # a resonance: the claimed one's DOFs
    f_in_range: bool | None = None  # a claimed resonance: f inside the ranges it allows
    f_range_width: float = math.nan  # their total width, relative to f
    f_allowed: tuple[float, float] = (math.nan, math.nan)
    """A resonance: the f range the data allow a fit of the truth's structure (95 %)."""
    final_lr: float = math.nan
    """A resonance: the final model's likelihood ratio over the nominal (nulls' units)."""
    truth_lr: float = math.nan
    """A resonance: the truth's structure's, fitted from the truth."""

    @property
    def resolved(self) -> bool:
        """A resonance the data resolve: the truth's structure, fitted from the truth, beats
        the nominal at the detection level and fixes f within :data:`RESOLVED_F` of it."""
        f = self.case.truth.get("f_hz", math.nan) if self.case.truth else math.nan
        lo, hi = self.f_allowed
        return (self.truth_p < 0.01 and lo >= (1 - RESOLVED_F) * f
                and hi <= (1 + RESOLVED_F) * f)

    @property
    def coupled_right(self) -> bool:
        """A resonance modelled with the DOFs the body couples (POS among them)."""
        return bool(self.coupled) and set(self.coupled) <= set(self.case.truth["coupled"])

    @property
    def wrongly_full(self) -> bool:
        """Catalogue effects called a full explanation of a body whose structure fits
        better than them by more than the noise (one parameter's 95 %)."""
        return self.forced and self.truth_lr - self.final_lr > RESOLVED_MARGIN

    @property
    def kind(self) -> str:
        """null, single (a catalogue effect), resonance, channel_filter or pair."""
        effect = self.case.effect
        if effect is None:
            return "null"
        if "+" in effect:
            return "pair"
        return effect if effect in ("resonance", "channel_filter") else "single"


def key_error(effect: str, truth: dict, fitted: dict) -> float:
    """Relative error of an effect's key parameter: the face gains' pitch- and yaw-like
    part (what the measurement determines), ``extra_s``, ``f_hz``, ``sensing``, ``delta_m``
    or ``vertical`` (the bounce's coupling: its compliance is what IN1/EXC shows).

    Parameters
    ----------
    effect : str
        A catalogue effect (not ``resonance`` or ``channel_filter``).
    truth : dict
        The hidden effect's parameters (:func:`hidden`).
    fitted : dict
        The claimed effect's parameters in the same names (``EffectFit.to_json``'s).

    Returns
    -------
    float
    """
    if effect in ("coil_imbalance", "osem_imbalance"):
        t = _SEEN @ np.array([truth["gains"][f] for f in FACES])
        g = _SEEN @ np.array([fitted["gains"][f] for f in FACES])
        return float(np.linalg.norm(g - t) / np.linalg.norm(t))
    key = {"loop_delay": "extra_s", "actuator_pole": "f_hz", "side_coupling": "sensing",
           "wire_asymmetry": "delta_m", "bounce_roll": "vertical"}[effect]
    return abs(fitted[key] - truth[key]) / abs(truth[key])


def key_z(effect: str, truth: dict, result) -> float:  # noqa: ANN001 - FitResult
    """The key parameter's error in units of the fit's own sigma: RMS over the determined
    components (pitch- and yaw-like gains), 1 on average when the sigmas are honest.

    Parameters
    ----------
    effect : str
        A catalogue effect (not ``resonance`` or ``channel_filter``).
    truth : dict
        The hidden effect's parameters (:func:`hidden`).
    result : FitResult
        The fit holding the claimed effect (alone or in a combination).

    Returns
    -------
    float
        NaN when the key combination is not determined.
    """
    pre = f"{effect}." if result.effect and result.effect != effect else ""  # joint fits
    got = result.as_dict()
    if effect in ("coil_imbalance", "osem_imbalance"):
        combos = [{f"{pre}gain_{f}": w for f, w in zip(FACES, row, strict=True)}
                  for row in _SEEN]
        d = _SEEN @ np.array([got[f"{pre}gain_{f}"] - truth["gains"][f] for f in FACES])
    else:  # a driver pole is fitted as 1/f
        name = {"loop_delay": "extra_s", "actuator_pole": "inv_f_hz",
                "side_coupling": "sensing", "wire_asymmetry": "delta_m",
                "bounce_roll": "vertical"}[effect]
        value = 1 / truth["f_hz"] if effect == "actuator_pole" else truth[name]
        combos = [{pre + name: 1.0}]
        d = np.array([got[pre + name] - value])
    cov = result.combination_covariance(combos)
    if not np.all(np.isfinite(cov)):
        return math.nan
    return float(np.sqrt(d @ np.linalg.lstsq(cov, d, rcond=None)[0] / d.size))


def score(case: Case, diagnosis, seconds: float,  # noqa: ANN001 - Diagnosis
          diagnosis_seconds: float = math.nan) -> Score:
    """Score one diagnosis (None: it failed) against its case; `seconds` with the
    measurement, `diagnosis_seconds` without.

    A catalogue effect is named when it is claimed (chosen, or a rival of the chosen);
    a pair when both are, its key error the worse of the two; a channel filter when its
    channel is, its key error its stage's low-frequency delay's; a resonance when a
    ``resonance`` is claimed within 15 % of its frequency, coupling no DOF the body leaves
    alone and POS among them, its key error the frequency's ("passed off" when no
    resonance is claimed, catalogue effects are and nothing is left unexplained).

    Parameters
    ----------
    case : Case
    diagnosis : Diagnosis or None
        What ``diagnose`` found; None when it failed.
    seconds : float
        Measurement and diagnosis (s).
    diagnosis_seconds : float
        The diagnosis alone (s).

    Returns
    -------
    Score
    """
    if diagnosis is None:
        return Score(case, False, ["(failed)"], math.nan, math.nan, math.nan, math.nan,
                     seconds, diagnosis_seconds=diagnosis_seconds)
    out = diagnosis.to_json()
    claimed = [e["effect"] for e in out["effects"]]
    entries = {e.effect: e for e in diagnosis.effects}
    tried = diagnosis.p_values
    effect, err, z, located, forced = case.effect, math.nan, math.nan, False, False
    body: dict = {}
    p = min(tried.values(), default=math.nan) if effect is None else tried.get(
        effect, tried.get(case.truth.get("channel", ""), math.nan))
    if effect is None:
        named = not claimed
    elif effect == "resonance":
        body = _resonance(case.truth, diagnosis)
        named, err, z, located = (body.pop(k) for k in ("named", "err", "z", "located"))
        forced = (not any(e.effect.startswith("resonance") for e in diagnosis.effects)
                  and bool(diagnosis.chosen) and not diagnosis.unexplained)
    elif effect == "channel_filter":
        named = case.truth["channel"] in claimed
        if named:
            err = stage_error(case.truth, entries[case.truth["channel"]].to_json()["params"])
    elif "+" in effect:
        parts = effect.split("+")
        named = all(e in claimed for e in parts)
        if named:
            err = max(key_error(e, case.truth[e], entries[e].to_json()["params"])
                      for e in parts)
    else:
        named = effect in claimed
        if named:
            err = key_error(effect, case.truth, entries[effect].to_json()["params"])
            z = key_z(effect, case.truth, entries[effect].result)
    return Score(case, named, claimed, err, z, out["chi2_nu_nominal"],
                 out["chi2_nu_final"], seconds, p, diagnosis_seconds, located, forced, **body)


def body_start(truth: dict) -> dict[str, float]:
    """A hidden body (:func:`attached_body`, pulling along the beam) in the catalogue
    ``resonance``'s parameters: ``g = sqrt(m2) (1, z0, y0, 0)``."""
    y, z = truth["point_m"]
    g = math.sqrt(truth["mass_kg"]) * np.array([1.0, z, y, 0.0])
    return {"f_hz": truth["f_hz"], "q": truth["q"],
            **{f"g_{d}": float(x) for d, x in zip(("POS", "PIT", "YAW", "SIDE"), g,
                                                 strict=True)}}


def stage_error(truth: dict, fitted: dict) -> float:
    """A channel stage's key error: its low-frequency delay ``(1/p - 1/z) / 2 pi`` (the
    stage's change is ``-j f (1/p - 1/z)`` to first order below its corners) against the
    truth's, relative to it. A concealed stage's corners lie close together and its change
    is seen below them: the data fix this slope, not each corner (a stage fitted hundreds of
    Hz above the band has the same slope).

    Parameters
    ----------
    truth, fitted : dict
        The hidden and the fitted stage: ``pole_hz`` and ``zero_hz``.

    Returns
    -------
    float
    """
    def delay(p: dict) -> float:
        return (1 / p["pole_hz"] - 1 / p["zero_hz"]) / (2 * math.pi)

    return abs(delay(fitted) - delay(truth)) / abs(delay(truth))


def _resonance(truth: dict, diagnosis) -> dict:  # noqa: ANN001 - Diagnosis
    """A hidden body's scores: ``named`` (modelled), ``err`` (relative frequency error) and
    ``z`` (the same in the fit's own sigma), ``located``, and for the nearest claimed
    resonance the DOFs it couples, whether f lies in the ranges it allows and their width
    relative to f."""
    f = truth["f_hz"]
    bands = [x.band_hz for x in (*diagnosis.located, *diagnosis.unexplained)]
    located = any(lo <= 1.15 * f and hi >= 0.85 * f for lo, hi in bands)
    # chosen, or a rival the data do not tell from the chosen effect (as for the catalogue)
    fits = [e.to_json() for e in diagnosis.effects if e.effect.startswith("resonance")]
    if not fits:
        return {"named": False, "err": math.nan, "z": math.nan, "located": located}
    best = min(fits, key=lambda e: abs(e["params"]["f_hz"] - f))
    err = abs(best["params"]["f_hz"] - f) / f
    sigma = best["sigma"]["f_hz"]
    coupled = best["reading"]["coupled"]
    modelled = err <= 0.15 and "POS" in coupled and set(coupled) <= set(truth["coupled"])
    ranges = best["reading"]["f_hz_ranges"]
    return {"named": modelled, "err": err,
            "z": math.nan if not sigma else abs(best["params"]["f_hz"] - f) / sigma,
            "located": located or modelled, "coupled": coupled,
            "f_in_range": any(lo <= f <= hi for lo, hi in ranges),
            "f_range_width": sum(hi - lo for lo, hi in ranges) / f}


# ------------------------------------------------------------------------------ routes
def measure(case: Case, route: str, workdir: Path, seed: int,  # noqa: ANN201 - TFSet
            excited: Sequence[str] = EXCITED, bw: float | None = None,
            averages: int = AVERAGES, rms: float = RMS):
    """The case's measurement as users have it: ``"xml"`` (a diaggui set written from the
    twin's TFs, up to :data:`STOP_HZ`) or ``"mcap"`` (a session recorded from the twin's
    engine), each DOF of `excited` in turn, at resolution `bw` (default the route's), with
    `averages` and an excitation of `rms`.

    Parameters
    ----------
    case : Case
        The optic measured (its drifted parameters and its plant).
    route : str
        ``"xml"`` or ``"mcap"``.
    workdir : Path
        Where the files go (a new directory in it).
    seed : int
        Seed of the twin's noise and the excitation.
    excited : sequence of str
        DOFs excited in turn.
    bw : float, optional
        Resolution (Hz); default the route's (:data:`ROUTE_BW`).
    averages : int
    rms : float
        RMS of the white EXC.

    Returns
    -------
    TFSet

    Raises
    ------
    ValueError
        If `route` is neither.
    """

    if route not in ROUTE_BW:
        msg = f"unknown route {route!r}: xml or mcap"
        raise ValueError(msg)
    bw = bw or ROUTE_BW[route]
    here = Path(tempfile.mkdtemp(dir=workdir))
    if route == "xml":
        tfs = measure_tfs(case.real, excited, bw=bw, averages=averages, rms=rms, seed=seed,
                          plant=case.plant)
        return from_diaggui(write_measurement_set(tfs, here, stop_hz=STOP_HZ))
    path = record_measurement(case.real, here / "session.mcap", excited, bw=bw,
                              averages=averages, rms=rms, seed=seed, plant=case.plant)
    try:
        return from_session([path], bw=bw, settle_s=SETTLE_S)
    finally:
        path.unlink()


def run_corpus(cfg: OpticConfig, route: str = "xml", per_effect: int = 3, nulls: int = 3,
               seed: int = 11, effects: Sequence[str] = EFFECTS,
               say: Callable[[str], None] = print, excited: Sequence[str] = EXCITED,
               bw: float | None = None, averages: int = AVERAGES, rms: float = RMS
               ) -> list[Score]:
    """Build the corpus, measure (at resolution `bw`, default :data:`ROUTE_BW`'s, with
    `averages` and excitation `rms`) and diagnose every case (each DOF of `excited` in
    turn), print a line each and the rates, each kind apart.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic (every diagnosis's model).
    route : str
        ``"xml"`` (diaggui sets) or ``"mcap"`` (twin sessions).
    per_effect : int
        Cases of each kind of `effects`.
    nulls : int
        Cases with no effect.
    seed : int
        Seed of the corpus and, offset by case, of each measurement.
    effects : sequence of str
        Kinds of effect hidden (:func:`make_cases`).
    say : callable
        Takes each line of the report.
    excited : sequence of str
        DOFs excited in turn.
    bw : float, optional
        Resolution (Hz); default the route's.
    averages : int
    rms : float
        RMS of the white EXC.

    Returns
    -------
    list of Score
    """

    bw = bw or ROUTE_BW[route]
    say(f"resolution {bw:g} Hz, {averages} averages, excitation RMS {rms:g}")
    cases = make_cases(cfg, reference_data(cfg, seed, excited, route, bw, averages, rms),
                       per_effect, nulls, seed, effects)
    scores = []
    with tempfile.TemporaryDirectory(prefix="twind-corpus-") as tmp:
        for k, case in enumerate(cases):
            t0 = time.perf_counter()
            tfs = measure(case, route, Path(tmp), seed + 100 + k, excited, bw, averages, rms)
            t1 = time.perf_counter()
            try:
                d = diagnose(tfs, cfg)
            except FitError as err:  # a failure of the tool, scored as a miss
                say(f"{case.name:18s} diagnose failed: {err}")
                d = None
            t2 = time.perf_counter()
            s = score(case, d, t2 - t0, t2 - t1)
            if d is not None and case.effect == "resonance":
                start = body_start(case.truth)
                s.truth_p, s.truth_lr = evidence(tfs, cfg, d, "resonance", start)
                found = next(c for c in d.first_step if c.effect == "resonance")
                s.truth_margin = s.truth_lr - found.lr
                s.f_allowed = f_profile(tfs, cfg, d, start)
                s.final_lr = explained(tfs, d)
            scores.append(s)
            say(_line(s))
    for line in summary(scores):
        say(line)
    return scores


def _line(s: Score) -> str:
    c = s.case
    hidden_ = (f"largest bin {c.largest_sigma:.1f} sigma, present {c.present:6.0f}"
               if c.effect else "drift only" + " " * 27)
    if c.effect == "resonance":
        lo, hi = s.f_allowed
        hidden_ += (f" (body {c.truth['f_hz']:.3g} Hz, Q {c.truth['q']:.2g}; from the truth "
                    f"p {s.truth_p:.1g}, chi2 {s.truth_margin:+.1f} on the search's, f "
                    f"allowed {lo:.3g}-{hi:.3g} Hz: "
                    f"{'resolved' if s.resolved else 'not resolved'})")
    elif c.effect == "channel_filter":
        hidden_ += (f" ({c.truth['channel']} {c.truth['pole_hz']:.3g}/"
                    f"{c.truth['zero_hz']:.3g} Hz)")
    key = "" if math.isnan(s.key_error) else (f"  key param {100 * s.key_error:5.1f} % "
                                               f"({s.key_z:.1f} sigma)")
    verdict = ", ".join(s.claimed) or "consistent"
    if s.coupled:
        verdict += (f" (resonance coupling {'/'.join(s.coupled)}, f "
                    f"{'in' if s.f_in_range else 'outside'} the ranges it allows, "
                    f"{100 * s.f_range_width:.0f} % wide)")
    return (f"{c.name:18s} {hidden_}  chi2/nu {s.chi2_nu_nominal:6.2f} -> "
            f"{s.chi2_nu_final:5.2f}  {'ok ' if s.named else 'MISS'} {verdict}{key}"
            f"  p {s.p_value:.1g}  [{s.seconds:.0f} s, diagnosis {s.diagnosis_seconds:.0f} s]")


def _median_pct(x: Sequence[float]) -> str:
    return f"{100 * np.median(x):.0f} %" if len(x) else "-"


def summary(scores: Sequence[Score]) -> list[str]:
    """The issue's targets, as measured on `scores` (a corpus without effect cases or without
    nulls leaves their lines out)."""
    out = []
    for kind, label, target in (("resonance", "modes in no list (resonance)", 80),
                                ("channel_filter", "one channel's own stage (channel_filter)",
                                 90),
                                ("pair", "two effects at once, both named", 80)):
        some = [s for s in scores if s.kind == kind]
        if some:
            named = [s for s in some if s.named]
            keyed = [s for s in named if s.key_error <= KEY_TOLERANCE]
            out.append(f"{label}: {len(named)}/{len(some)} = {100 * len(named) / len(some):.0f}"
                       f" % (target >= {target} %), key parameters within "
                       f"{100 * KEY_TOLERANCE:.0f} %: {len(keyed)}/{len(some)}")
            if kind == "resonance":
                held = [s for s in some if s.truth_p < 0.01]
                limited = [s for s in held if not s.named and s.truth_margin <= AS_GOOD]
                out.append(f"  with evidence enough from a fit started at the truth (p < 0.01, "
                           f"the search's cost paid): {len(held)}/{len(some)}, of which "
                           f"modelled {sum(s.named for s in held)}; missed where the search's "
                           f"fit explains the data as well as the truth's (chi2 within "
                           f"{AS_GOOD:g}): {len(limited)}")
                resolved = [s for s in some if s.resolved]
                others = [s for s in some if not s.resolved]
                right = [s for s in resolved if s.key_error <= RESOLVED_F and s.coupled_right]
                told = [s for s in others if math.isfinite(s.key_error)]
                out.append(f"  resolved by the data (the truth's structure, fitted from the "
                           f"truth, beats the nominal at p < 0.01 and fixes f within "
                           f"{100 * RESOLVED_F:.0f} %): {len(resolved)}/{len(some)}; of them "
                           f"modelled with f within {100 * RESOLVED_F:.0f} % and the coupled "
                           f"DOFs right: {len(right)}/{len(resolved)} (target >= 90 %)")
                out.append(f"  not resolved: {len(others)}; catalogue effects called the full "
                           f"explanation where the truth's structure fits better by more "
                           f"than the noise: {sum(s.wrongly_full for s in others)} (target 0); "
                           f"a resonance claimed with f in the range the data allow: "
                           f"{sum(bool(s.f_in_range) for s in told)}/{len(told)}")
                claims = [s for s in some if math.isfinite(s.key_error)]
                out.append(f"  claimed within 15 % of its frequency, whatever DOFs it couples: "
                           f"{sum(s.key_error <= 0.15 for s in some)}/{len(some)}; of the "
                           f"{len(claims)} claimed, f within 2 of its own sigmas: "
                           f"{sum(s.key_z <= 2 for s in claims)}, f in the ranges the data "
                           f"allow: {sum(bool(s.f_in_range) for s in claims)} (their width "
                           f"median {_median_pct([s.f_range_width for s in claims])} of f)")
                out.append(f"  located (a band holding f +- 15 %, or modelled): "
                           f"{sum(s.located for s in some)}/{len(some)}; passed off as "
                           f"catalogue effects with nothing unexplained: "
                           f"{sum(s.forced for s in some)}/{len(some)} (target 0)")
    effects = [s for s in scores if s.kind == "single"]
    nulls = [s for s in scores if not s.case.effect]
    named = [s for s in effects if s.named]
    keyed = [s for s in named if s.key_error <= KEY_TOLERANCE]
    secs = np.array([s.seconds for s in scores])
    if effects:
        z = np.array([s.key_z for s in named if math.isfinite(s.key_z)] or [np.nan])
        out += [f"catalogue effects named (or equivalent): {len(named)}/{len(effects)} "
                f"= {100 * len(named) / len(effects):.0f} % (target >= 90 %)",
                f"  with the key parameter within {100 * KEY_TOLERANCE:.0f} %: {len(keyed)}/"
                f"{len(effects)} = {100 * len(keyed) / len(effects):.0f} %",
                f"  key parameter errors in the fit's own sigmas: RMS "
                f"{np.sqrt(np.mean(z**2)):.2f} over {int(np.isfinite(z).sum())} cases (1 when "
                f"the sigmas are honest), beyond 2 sigma in {int(np.sum(z > 2))}"]
    if nulls:
        out.append(f"nulls with an effect claimed: {sum(not s.named for s in nulls)}/"
                   f"{len(nulls)} (target 0)")
    final = [s.chi2_nu_final for s in named]
    null_chi = [s.chi2_nu_nominal for s in nulls]
    chi = [f"mean {np.mean(final):.2f}, max {np.max(final):.2f}" if final else "",
           f"nulls' mean {np.mean(null_chi):.2f}, max {np.max(null_chi):.2f}" if null_chi else ""]
    if any(chi):
        label = "chi2/nu after augmentation" if final else "chi2/nu"
        out.append(f"{label}: " + "; ".join(c for c in chi if c))
    if len(secs):
        diag = np.array([s.diagnosis_seconds for s in scores])
        out.append(f"seconds per case: diagnosis median {np.median(diag):.0f} (target <= 15), "
                   f"max {np.max(diag):.0f} (target <= 30); with the measurement median "
                   f"{np.median(secs):.0f}, max {np.max(secs):.0f}")
        measuring = secs - diag
        out.append(f"measurement (the twin's engine and the estimates): {np.sum(measuring):.0f} s "
                   f"over {len(secs)} cases, median {np.median(measuring):.1f} s a case")
    return out


# ------------------------------------------------------------------------------ the demo
def run_demo(cfg: OpticConfig, out: str | Path, effect: str = "actuator_pole", seed: int = 3,
             say: Callable[[str], None] = print) -> tuple:
    """A "real" optic (drifted, `effect` concealed in its plant) and the nominal one, both
    excited alike on the twin's engine and recorded as twin sessions (MCAP), then each
    diagnosed from its recording alone; reports (Bode matrices before and after, HTML,
    Rerun) under `out`/real and `out`/nominal.

    Parameters
    ----------
    cfg : OpticConfig
        The nominal optic.
    out : str or Path
        Directory of the recordings and reports (made if missing).
    effect : str
        One of :data:`MADE` with no shape (not ``resonance`` or ``channel_filter``).
    seed : int
        Seed of the drift, the effect's direction and the measurements.
    say : callable
        Takes each line of the report.

    Returns
    -------
    (Diagnosis, Diagnosis)
        The real optic's and the nominal one's.
    """

    out = Path(out)
    rng = np.random.default_rng(seed)
    real = drifted(cfg, rng)
    direction = rng.standard_normal(4)
    plant, truth, largest, present = conceal(real, effect, reference_data(cfg, seed,
                                                                         route="mcap"),
                                             direction / 2)
    say(f"real {cfg.name}: drifted, with {effect} {truth} hidden in its plant "
        f"(largest bin {largest:.1f} sigma, {present:.0f} in chi^2 units over all bins)")
    results = []
    for name, optic, run in (("real", real, plant), ("nominal", cfg, None)):
        out.mkdir(parents=True, exist_ok=True)
        path = out / f"{name}.mcap"
        say(f"{name}: exciting POS, PIT, YAW in turn and recording {path} ...")
        record_measurement(optic, path, bw=ROUTE_BW["mcap"], averages=AVERAGES, rms=RMS,
                           seed=seed + 1, plant=run)
        tfs = from_session([path], bw=ROUTE_BW["mcap"], settle_s=SETTLE_S)
        d = diagnose(tfs, cfg, input_matrix=recorded_input_matrix([path], cfg))
        write_report(d, tfs, cfg, out / name, [path])
        say(f"{name}: " + "\n  ".join(d.lines()))
        say(f"{name}: report in {out / name}/index.html")
        results.append(d)
    return tuple(results)
