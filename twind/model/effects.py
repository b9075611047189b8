"""Physics the nominal model leaves out: the catalogue of docs/model.md, each entry a change to the plant.

Every effect is zero at zero parameters, so "nominal + effect" nests the nominal model (what
a likelihood-ratio test needs).  Parameters carry the names of docs/model.md, flattened for fitting:
``gains`` {UL, UR, LL, LR} become ``gain_UL`` ... ``gain_LR``.

| id               | physics (docs/model.md)                                        | parameters              |
| ---------------- | ----------------------------------------------------------- | ----------------------- |
| coil_imbalance   | face coil i pushes F_i (1 + g_i)                             | gain_UL .. gain_LR      |
| osem_imbalance   | face OSEM i reads s_i (1 + g_i)                              | gain_UL .. gain_LR      |
| loop_delay       | delay beyond the one-cycle nominal                           | extra_s (s)             |
| actuator_pole    | every coil driver x 1 / (1 + s / 2 pi f)                     | f_hz (Hz)               |
| side_coupling    | face OSEMs also read ks y; face coils also push ka F_i along y | sensing, actuation    |
| wire_asymmetry   | centre of mass off the wire plane by d: K_xphi = K_phix = -m g d / l | delta_m (m)     |
| bounce_roll      | VERT and ROLL modes read by the face OSEMs, driven by the face coils | vertical, roll, f_vertical_hz, f_roll_hz, roll_angle |
| resonance        | a body on a spring at a point of the optic (a cable, a standoff): a mode at f, Q, coupled along g | f_hz, q, g_POS .. g_SIDE |
| channel_filter   | one coil driver or OSEM readback x (1 + s/2 pi z) / (1 + s/2 pi p) | inv_pole_hz, inv_zero_hz |

``resonance`` is the family for a mode in no list: a body of mass m2 held by a spring (rate
m2 w^2, quality factor q) to a point of the optic, pulling along a direction ``d`` over
POS/PIT/YAW/SIDE (a face point (y0, z0) pulled along the beam has ``d = (1, z0, y0, 0)``).
Its coordinate, scaled to unit mass, adds ``w^2 g g^T`` (and ``w / q`` times it) to the
optic's stiffness (damping) with ``g = sqrt(m2) d``; at ``g = 0`` it moves nothing, so
the model nests the nominal one. Its frequency is searched over the whole measured band
(``twind.analysis.identification.narrow``).

Effects combine: ``"coil_imbalance+loop_delay"`` applies both, its parameters prefixed
with their effect (``coil_imbalance.gain_UL``, :func:`effect_params`).

``bounce_roll`` is what OSEM axes tilted against the optic (a static pitch or yaw of the
optic, a head mounted askew) do: a head tilted by (a towards SIDE, b towards VERT) at face
point (y, z) reads ``b VERT + (b y - a z) ROLL`` besides POS/PIT/YAW, and its coil, coaxial,
pushes along the same tilted axis. A common tilt puts VERT into the POS pattern (every face
OSEM alike) and ROLL into a mix of the PIT and YAW patterns, ``cos(angle) z + sin(angle) y``.
Each mode reaches the loop as sensing x actuation, so its parameter is that product
(``vertical`` = b^2 and ``roll`` = a^2 + b^2 for a common tilt): linear in it, the model
nests the nominal one. The modes are narrower than a spectral bin (Q 1000: 0.016 Hz at
16 Hz), so their frequencies are fitted too, within :data:`MODE_SEARCH` of the nominal
``sqrt(k_v / m)`` and ``sqrt(k_v R2^2 / I_roll)``; at zero coupling they and the angle move
nothing, so a fit starts them where a search put them (``twind.analysis.identification.narrow``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from twind import OSEMS
from twind.errors import TwindError
from twind.model.mechanics import Mechanics
from twind.model.osem import FACE_POSITION
from twind.model.params import SOSParams
from twind.model.plant import Plant

FACES = tuple(FACE_POSITION)  # UL, UR, LL, LR: the first four OSEM columns/rows


class EffectError(TwindError):
    """An unknown effect, or parameters it does not take."""


@dataclass(frozen=True)
class Effect:
    """One entry of the catalogue.

    Attributes
    ----------
    id : str
        the identifier in docs/model.md.
    params : tuple of str
        Its parameters (all zero: the nominal model).
    physics : str
        One line for a report.
    apply : callable
        ``(plant, sus, values) -> plant`` with the effect in.
    scale : dict of str to float
        A typical size of each parameter, for finite differences and starting steps.
    narrow : tuple of str
        Frequency parameters of modes that can be narrower than a spectral bin: a fit starts
        them where a search put them.
    search : str
        Where that search looks: ``"model_modes"`` near the model's own modes (on bands
        around them, :func:`mode_bands`), ``"band"`` over the whole band; empty for none.
    searched : tuple of str
        Parameters a search over the whole band sets beside the couplings: paid for in the
        p-value, not counted as parameters.
    repeatable : bool
        Whether a combination may hold it more than once (``resonance#2``).
    family : str
        The family it is one member of (the data choosing among the members, paid for as a
        search), or empty.
    body : bool
        Whether it is a body on a spring pulling on the optic's coordinates through its
        ``g_<DOF>`` couplings: read as a body's mass and place.
    """

    id: str
    params: tuple[str, ...]
    physics: str
    apply: Callable[[Plant, SOSParams, Mapping[str, float]], Plant]
    scale: dict[str, float]
    narrow: tuple[str, ...] = ()
    search: str = ""
    searched: tuple[str, ...] = ()
    repeatable: bool = False
    family: str = ""
    body: bool = False


MODE_SEARCH = {"f_vertical_hz": ("VERT", 0.92, 1.08), "f_roll_hz": ("ROLL", 0.92, 1.08)}
"""Where a narrow mode is looked for: (coordinate, lowest, highest) as fractions of its
nominal frequency. An SOS's bounce and roll lie within a few percent of the wire-stiffness
values (the 40m's BounceRoll notches span 15.85-16.34 Hz and sit at 23.14 Hz)."""


def mode_bands(sus: SOSParams, reach_hz: float = 0.0) -> list[tuple[float, float]]:
    """The bands (Hz) :data:`MODE_SEARCH` looks for `sus`'s narrow modes in, each widened by
    `reach_hz` (how far a spectral estimate's kernel carries a mode).

    Parameters
    ----------
    sus : SOSParams
        The suspension (its VERT and ROLL frequencies from the wire stiffness).
    reach_hz : float
        Added on both sides of each band (Hz).

    Returns
    -------
    list of (float, float)
        (lowest, highest) of each band (Hz), in :data:`MODE_SEARCH`'s order.
    """
    nominal = sus.uncoupled_frequencies_hz()
    return [(lo * nominal[d] - reach_hz, hi * nominal[d] + reach_hz)
            for d, lo, hi in MODE_SEARCH.values()]


def _gains(values: Mapping[str, float]) -> np.ndarray:
    return np.array([1.0 + values.get(f"gain_{f}", 0.0) for f in FACES] + [1.0])


def _coil_imbalance(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    return replace(plant, actuation=plant.actuation * _gains(v)[None, :])


def _osem_imbalance(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    return replace(plant, sensing=plant.sensing * _gains(v)[:, None])


def _loop_delay(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    return replace(plant, delay_s=plant.delay_s + v.get("extra_s", 0.0))


def _actuator_pole(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    # parametrised by 1/f so that zero is "no pole" and the model nests the nominal one
    inv = v.get("inv_f_hz", 0.0)
    return replace(plant, drive_pole_hz=math.inf if inv <= 0 else 1.0 / inv)


def _side_coupling(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    dofs = plant.mechanics.dofs
    sensing, actuation = plant.sensing.copy(), plant.actuation.copy()
    side, pos = dofs.index("SIDE"), dofs.index("POS")
    sensing[:4, side] += v.get("sensing", 0.0)
    actuation[side, :4] += v.get("actuation", 0.0) * actuation[pos, :4]
    return replace(plant, sensing=sensing, actuation=actuation)


def _wire_asymmetry(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    mech = plant.mechanics
    i, j = mech.index("POS"), mech.index("YAW")
    K = mech.K.copy()
    k = -sus.mass_kg * sus.g_mps2 * v.get("delta_m", 0.0) / sus.wire_length_m
    K[i, j] += k
    K[j, i] += k
    return replace(plant, mechanics=Mechanics(mech.dofs, mech.M, mech.C, K))


def _bounce_roll(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    nominal = sus.uncoupled_frequencies_hz()
    mech = _with_modes(plant.mechanics, sus, {
        "VERT": v.get("f_vertical_hz") or nominal["VERT"],
        "ROLL": v.get("f_roll_hz") or nominal["ROLL"]})
    grow = mech.n - plant.mechanics.n
    sensing = np.hstack([plant.sensing, np.zeros((5, grow))])
    actuation = np.vstack([plant.actuation, np.zeros((grow, 5))])
    h = sus.osem_lever_m
    y, z = (np.array([p[k] for p in FACE_POSITION.values()]) * h for k in (0, 1))
    angle = v.get("roll_angle", 0.0)
    roll = math.cos(angle) * z + math.sin(angle) * y  # m of a face point per rad of ROLL
    push = actuation[mech.index("POS"), :4]  # each face coil's force along its axis
    vert, rol = mech.index("VERT"), mech.index("ROLL")
    # the product sits in the sensing; the coils push with the unit tilt's pattern
    sensing[:4, vert] = v.get("vertical", 0.0)
    actuation[vert, :4] = push
    sensing[:4, rol] = v.get("roll", 0.0) * roll
    actuation[rol, :4] = push * roll
    return replace(plant, mechanics=mech, sensing=sensing, actuation=actuation)


BODY_DOFS = ("POS", "PIT", "YAW", "SIDE")
"""The optic's coordinates a ``resonance`` body pulls on."""
MIN_Q = 1.0
"""A ``resonance``'s quality factor is at least this: below it there is no mode to name."""


def _resonance(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
    mech = plant.mechanics
    g = np.zeros(mech.n)
    for d in BODY_DOFS:
        g[mech.index(d)] = v.get(f"g_{d}", 0.0)
    f, q = v.get("f_hz", 0.0), max(abs(v.get("q", 0.0)), MIN_Q)
    if not g.any() or f <= 0:
        return plant
    w = 2 * math.pi * f
    # the body's coordinate scaled to unit mass: spring w^2 between it and g . q_optic
    link = np.append(g, -1.0)
    M = np.pad(mech.M, (0, 1))
    M[-1, -1] = 1.0
    K = np.pad(mech.K, (0, 1)) + w**2 * np.outer(link, link)
    C = np.pad(mech.C, (0, 1)) + w / q * np.outer(link, link)
    name = "BODY" + (f"#{sum(d.startswith('BODY') for d in mech.dofs) + 1}"
                     if "BODY" in mech.dofs else "")
    return replace(plant, mechanics=Mechanics((*mech.dofs, name), M, C, K),
                   sensing=np.pad(plant.sensing, ((0, 0), (0, 1))),
                   actuation=np.pad(plant.actuation, ((0, 1), (0, 0))))


def _with_modes(mech: Mechanics, sus: SOSParams, f_hz: Mapping[str, float]) -> Mechanics:
    """`mech` with uncoupled VERT (mass m) and ROLL (I_roll) coordinates at `f_hz`, Q from
    `sus`; coordinates it already has are retuned."""
    inertia = {"VERT": sus.mass_kg, "ROLL": sus.I_roll_kgm2}
    new = [d for d in f_hz if d not in mech.dofs]
    M, C, K = (np.pad(a, (0, len(new))) for a in (mech.M, mech.C, mech.K))
    dofs = mech.dofs + tuple(new)
    for d, f in f_hz.items():
        i, w = dofs.index(d), 2 * np.pi * f
        M[i, i] = M[i, i] if d in mech.dofs else inertia[d]
        K[i, i], C[i, i] = M[i, i] * w**2, M[i, i] * w / sus.Q[d]
    return Mechanics(dofs, M, C, K)


_GAINS = tuple(f"gain_{f}" for f in FACES)
CATALOGUE: dict[str, Effect] = {e.id: e for e in (
    Effect("coil_imbalance", _GAINS, "face coils of unequal strength: F_i x (1 + g_i)",
           _coil_imbalance, dict.fromkeys(_GAINS, 0.01)),
    Effect("osem_imbalance", _GAINS, "face OSEMs of unequal gain: s_i x (1 + g_i)",
           _osem_imbalance, dict.fromkeys(_GAINS, 0.01)),
    Effect("loop_delay", ("extra_s",), "delay beyond the one-cycle nominal (ADC/DAC, AA/AI)",
           _loop_delay, {"extra_s": 1e-4}),
    Effect("actuator_pole", ("inv_f_hz",), "a pole in every coil-driver chain",
           _actuator_pole, {"inv_f_hz": 1e-2}),
    Effect("side_coupling", ("sensing", "actuation"),
           "SIDE mixes into the face OSEMs (sensing) and the face coils push sideways",
           _side_coupling, {"sensing": 0.01, "actuation": 0.01}),
    Effect("wire_asymmetry", ("delta_m",), "centre of mass off the wire plane: K_x,yaw",
           _wire_asymmetry, {"delta_m": 1e-4}),
    Effect("bounce_roll", ("vertical", "roll", "f_vertical_hz", "f_roll_hz", "roll_angle"),
           "VERT and ROLL modes read by tilted face OSEMs and driven by their coils",
           # scales as wide as the parameters can physically be: a fit holds a parameter
           # whose sigma exceeds its scale (a mode's frequency, seen only through its
           # compliance below resonance) where it started
           _bounce_roll, {"vertical": 1.0, "roll": 1.0, "f_vertical_hz": 1.0,
                          "f_roll_hz": 1.0, "roll_angle": 1.0},
           narrow=("f_vertical_hz", "f_roll_hz"), search="model_modes"),
    Effect("resonance", ("f_hz", "q", *(f"g_{d}" for d in BODY_DOFS)),
           "a body on a spring at a point of the optic: a mode at f_hz, q, pulling along g",
           _resonance, {"f_hz": 1.0, "q": 10.0, "g_POS": 0.01, "g_PIT": 1e-4, "g_YAW": 1e-4,
                        "g_SIDE": 0.01},
           narrow=("f_hz",), search="band", searched=("f_hz", "q"), repeatable=True,
           body=True),
)}


def _channel_filter(kind: str, k: int) -> Callable[[Plant, SOSParams, Mapping[str, float]],
                                                    Plant]:
    def apply(plant: Plant, sus: SOSParams, v: Mapping[str, float]) -> Plant:
        # parametrised by 1/f, so that zero is "no pole, no zero": the model nests the
        # nominal one (a fit may take either through zero: its size is what counts)
        inv_p, inv_z = abs(v.get("inv_pole_hz", 0.0)), abs(v.get("inv_zero_hz", 0.0))
        if inv_p == inv_z:
            return plant
        stage = (kind, k, 1 / inv_p if inv_p else math.inf, 1 / inv_z if inv_z else math.inf)
        return replace(plant, channel_filters=(*plant.channel_filters, stage))
    return apply


CHANNEL_FILTERS: dict[str, Effect] = {e.id: e for e in (
    Effect(f"{kind}_filter_{name}", ("inv_pole_hz", "inv_zero_hz"),
           f"the {name} {kind} {'driver' if kind == 'coil' else 'readback'} has its own "
           "pole/zero pair: (1 + s/2 pi zero) / (1 + s/2 pi pole)",
           _channel_filter(kind, k), {"inv_pole_hz": 1e-2, "inv_zero_hz": 1e-2},
           family="channel_filter")
    for kind in ("coil", "osem") for k, name in enumerate(OSEMS))}
"""One coil driver or one OSEM readback with a stage the others lack: the
``channel_filter`` family, one entry per channel (``coil_filter_UL`` ...
``osem_filter_SIDE``), whose channel a diagnosis searches."""
FAMILIES = {f: tuple(e.id for e in CHANNEL_FILTERS.values() if e.family == f)
            for f in dict.fromkeys(e.family for e in CHANNEL_FILTERS.values())}
"""Hypotheses made of several entries (:attr:`Effect.family`), the data choosing among them
(paid for as a search)."""


def entry(name: str) -> Effect:
    """The catalogue entry `name` stands for (``resonance#2``: a second ``resonance``)."""
    base, _, k = name.partition("#")
    if name in CHANNEL_FILTERS:
        return CHANNEL_FILTERS[name]
    if base not in CATALOGUE or (k and (not CATALOGUE[base].repeatable or not k.isdigit())):
        msg = (f"unknown effect {name!r}; the catalogue has {', '.join(CATALOGUE)} and "
               f"{', '.join(CHANNEL_FILTERS)}")
        raise EffectError(msg)
    return CATALOGUE[base]


def parts(effect: str) -> list[str]:
    """The catalogue entries of `effect` (``"a+b"``: both), checked."""
    names = effect.split("+")
    for name in names:
        entry(name)
    if len(set(names)) < len(names):
        msg = f"{effect!r} names an effect twice"
        raise EffectError(msg)
    return names


def effect_params(effect: str) -> tuple[str, ...]:
    """Parameter names of `effect`: the catalogue's, or ``entry.param`` for a combination."""
    names = parts(effect)
    if len(names) == 1:
        return entry(effect).params
    return tuple(f"{e}.{p}" for e in names for p in entry(e).params)


def effect_scale(effect: str) -> dict[str, float]:
    """Typical size of each of :func:`effect_params`."""
    names = parts(effect)
    if len(names) == 1:
        return entry(effect).scale
    return {f"{e}.{p}": x for e in names for p, x in entry(e).scale.items()}


def param_name(effect: str, name: str, param: str) -> str:
    """The name `effect` (catalogue entry `name` itself or a combination holding it) gives
    the entry's parameter `param`.

    Parameters
    ----------
    effect : str
        The effect fitted: a catalogue entry, or a combination ``"a+b"``.
    name : str
        The entry in it.
    param : str
        One of the entry's parameters.

    Returns
    -------
    str
        `param` alone, or ``name.param`` in a combination.

    Examples
    --------
    >>> param_name("loop_delay", "loop_delay", "extra_s")
    'extra_s'
    >>> param_name("coil_imbalance+loop_delay", "loop_delay", "extra_s")
    'loop_delay.extra_s'
    """
    return param if effect == name else f"{name}.{param}"


def own_values(effect: str, name: str, values: Mapping[str, float]) -> dict[str, float]:
    """The values of catalogue entry `name`'s parameters, by its own names, among those of
    `effect` (a combination holding it, or the entry itself).

    Parameters
    ----------
    effect : str
        The effect fitted: a catalogue entry, or a combination ``"a+b"``.
    name : str
        The entry in it.
    values : mapping of str to float
        Parameter values in `effect`'s names (others are ignored).

    Returns
    -------
    dict of str to float
        Those of `values` that are `name`'s, by the entry's own names.
    """
    return {p: values[param_name(effect, name, p)] for p in entry(name).params
            if param_name(effect, name, p) in values}


def with_effect(plant: Plant, sus: SOSParams, effect: str, values: Mapping[str, float]
                ) -> Plant:
    """`plant` with catalogue `effect` (or a combination ``"a+b"``) at parameter `values`
    (missing ones are zero).

    Parameters
    ----------
    plant : Plant
        The nominal plant of `sus`.
    sus : SOSParams
        The suspension's parameters (mass, wire length for ``wire_asymmetry``).
    effect : str
        A key of :data:`CATALOGUE`.
    values : mapping of str to float
        The effect's parameters.

    Returns
    -------
    Plant
    """
    names = effect_params(effect)
    unknown = sorted(set(values) - set(names))
    if unknown:
        msg = f"{effect} takes {', '.join(names)}, not {', '.join(unknown)}"
        raise EffectError(msg)
    for name in parts(effect):
        plant = entry(name).apply(plant, sus, own_values(effect, name, values))
    return plant


def model_names(effect: str, values: Mapping[str, float], sigma: Mapping[str, float | None]
                ) -> tuple[dict, dict]:
    """An effect's fitted parameters and their sigmas in the names of docs/model.md: the face
    gains as ``{"gains": {"UL": ...}}``, a driver pole as ``f_hz`` (fitted as 1/f, which is
    linear near the nominal model; its sigma propagated to first order).

    Parameters
    ----------
    effect : str
        A catalogue entry (one, not a combination nor a repeat like ``resonance#2``).
    values : mapping of str to float
        Its fitted parameters, by its own names.
    sigma : mapping of str to float or None
        Their sigmas, None where undetermined.

    Returns
    -------
    params : dict
    sigma : dict
        Both in docs/model.md's names; a sigma None where undetermined (and for a pole
        at infinity).
    """
    if effect in ("coil_imbalance", "osem_imbalance"):
        return ({"gains": {f: values[f"gain_{f}"] for f in FACES}},
                {"gains": {f: sigma[f"gain_{f}"] for f in FACES}})
    if effect == "resonance":  # a quality factor as the plant takes it
        return ({**values, "q": max(abs(values["q"]), MIN_Q)}, dict(sigma))
    if effect in CHANNEL_FILTERS:
        out, err = {}, {}
        for key, name in (("pole_hz", "inv_pole_hz"), ("zero_hz", "inv_zero_hz")):
            inv, s = abs(values[name]), sigma[name]
            out[key] = 1 / inv if inv > 0 else math.inf
            err[key] = None if s is None or inv <= 0 else s / inv**2
        return out, err
    if effect == "actuator_pole":
        inv, s = values["inv_f_hz"], sigma["inv_f_hz"]
        f = 1 / inv if inv > 0 else math.inf
        return {"f_hz": f}, {"f_hz": None if s is None or inv <= 0 else s / inv**2}
    return dict(values), dict(sigma)
