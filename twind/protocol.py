"""The twin's control verbs as typed objects: each request read from its JSON object with
every field checked, and each reply the twin sends, read back by a client.

The client builds a request and checks it before sending it; the twin reads the same JSON
with the same code, so a field is spelled and checked in one place. An excitation's request
is :class:`twind.excitation.ExcitationRequest`.

- ``status``: no request; :class:`StatusReply`.
- ``stop``: :class:`StopRequest`; the ids stopped and those already ended.
- ``params``: :class:`ParamsRequest`; :class:`ParamsReply`.
- ``filter``: :class:`FilterRequest`; :class:`ParamsReply`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

from twind import DOFS
from twind.errors import TwindError
from twind.excitation.request import is_int, is_real
from twind.loop.foton_file import N_STAGES
from twind.model.params import SOSParams

if TYPE_CHECKING:  # named, not loaded: its foton designs take a second to import
    from twind.loop.filtermodule import FilterModule

LIVE_PARAMS = (frozenset(f.name for f in fields(SOSParams))
               - {"name", "sample_rate_hz", "loop_delay_s", "Q", "wire"}) | {f"Q_{d}" for d in DOFS}
"""Parameters a running twin may change (the rate, the delay and the name need a restart); a
DOF's Q by the name ``twind fit`` reports (``Q_POS``), one number each."""

MAX_GAIN_RAMP_S = 3600.0
"""The longest ramp of a filter module's gain."""


class RequestError(TwindError):
    """A control request that cannot be served as written: the field at fault is named."""


def _known(request: Mapping[str, Any], fields_: tuple[str, ...], verb: str) -> None:
    """Refuse a request with a field `verb` does not take: a misspelt one does nothing."""
    if not isinstance(request, Mapping):
        msg = "the request must be a JSON object"
        raise RequestError(msg)
    unknown = sorted(str(k)[:40] for k in request if k not in fields_)
    if unknown:
        msg = (f"{verb} takes {', '.join(fields_)}; unknown field(s): "
               f"{', '.join(map(repr, unknown))[:200]}")
        raise RequestError(msg)


def _number(value: object) -> bool:
    """A finite JSON number (not a boolean; not an integer beyond a float's range)."""
    try:
        return is_real(value) and math.isfinite(value)  # type: ignore[arg-type]
    except OverflowError:
        return False


def _optic(request: Mapping[str, Any]) -> str | None:
    optic = request.get("optic")
    if optic is not None and not isinstance(optic, str):
        msg = f"'optic' takes a name such as \"ETMX\", got {str(optic)[:40]!r}"
        raise RequestError(msg)
    return optic


# ------------------------------------------------------------------------------ requests
@dataclass(frozen=True)
class StopRequest:
    """Stop one excitation (``id``) or all of them (``all``), ramped down over ``ramp``
    seconds, or over its own request's ramp when None."""

    id: str | None = None
    all: bool = False
    ramp: float | None = None

    @classmethod
    def from_json(cls, request: Mapping[str, Any]) -> StopRequest:
        """The request in `request`, or a RequestError naming the field at fault."""
        _known(request, ("id", "all", "ramp"), "stop")
        everything, exc_id, ramp = request.get("all"), request.get("id"), request.get("ramp")
        if everything is not True and not isinstance(exc_id, str):
            msg = 'stop takes {"id": "<the id inject returned>"} or {"all": true}'
            raise RequestError(msg)
        if ramp is not None and not (_number(ramp) and 0 <= ramp < math.inf):
            msg = f"'ramp' takes a number of seconds >= 0, got {str(ramp)[:40]}"
            raise RequestError(msg)
        return cls(None if everything is True else exc_id, everything is True,
                   None if ramp is None else float(ramp))

    def to_json(self) -> dict[str, Any]:
        """The JSON object the twin reads."""
        body: dict[str, Any] = {"all": True} if self.all else {"id": self.id}
        return body if self.ramp is None else {**body, "ramp": self.ramp}


@dataclass(frozen=True)
class EffectChange:
    """Physics the nominal model leaves out, run from now on: a catalogue entry's id and
    values (docs/model.md), or ``id`` None to remove it."""

    id: str | None
    values: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, effect: object) -> EffectChange:
        """The change in `effect`, or a RequestError naming what is wrong."""
        if not (isinstance(effect, Mapping) and "id" in effect
                and (effect["id"] is None or isinstance(effect["id"], str))
                and isinstance(effect.get("values") or {}, Mapping)):
            msg = "'effect' must be an object {\"id\": <catalogue id or null>, \"values\": {...}}"
            raise RequestError(msg)
        return cls(effect["id"], dict(effect.get("values") or {}))

    def to_json(self) -> dict[str, Any]:
        """``{"id", "values"}``."""
        return {"id": self.id, "values": self.values}


@dataclass(frozen=True)
class ParamsRequest:
    """Read an optic's parameters, or change them live first.

    Attributes
    ----------
    optic : str or None
        The optic; None for the twin's first.
    set : dict of str to float
        Nominal parameters to change, by the names of :data:`LIVE_PARAMS`.
    effect : EffectChange or None
        Physics left out to run from now on (kept across later changes of `set`).
    rearm : bool
        Re-arm a tripped watchdog (``"watchdog": "rearm"``).
    """

    optic: str | None = None
    set: dict[str, float] = field(default_factory=dict)
    effect: EffectChange | None = None
    rearm: bool = False

    @classmethod
    def from_json(cls, request: Mapping[str, Any]) -> ParamsRequest:
        """The request in `request`, or a RequestError naming the field at fault."""
        _known(request, ("optic", "set", "effect", "watchdog"), "params")
        watchdog, changes = request.get("watchdog"), request.get("set") or {}
        if watchdog is not None and watchdog != "rearm":
            msg = f"'watchdog' takes \"rearm\", got {str(watchdog)[:40]!r}"
            raise RequestError(msg)
        if not isinstance(changes, Mapping):
            msg = "'set' must be an object of parameter names and values"
            raise RequestError(msg)
        unknown = [str(k) for k in changes if k not in LIVE_PARAMS]
        if unknown:
            msg = (f"cannot change {', '.join(unknown)[:200]} live; parameters: "
                   f"{', '.join(sorted(LIVE_PARAMS))}")
            raise RequestError(msg)
        bad = [k for k, v in changes.items() if not _number(v)]
        if bad:
            msg = f"'set' takes numbers; {bad[0]} is {str(changes[bad[0]])[:40]}"
            raise RequestError(msg)
        effect = request.get("effect")
        return cls(_optic(request), {k: float(v) for k, v in changes.items()},
                   None if effect is None else EffectChange.from_json(effect),
                   watchdog == "rearm")

    def to_json(self) -> dict[str, Any]:
        """The JSON object the twin reads (only the fields given)."""
        body: dict[str, Any] = {} if self.optic is None else {"optic": self.optic}
        if self.set:
            body["set"] = dict(self.set)
        if self.effect is not None:
            body["effect"] = self.effect.to_json()
        return {**body, "watchdog": "rearm"} if self.rearm else body


@dataclass(frozen=True)
class FilterRequest:
    """Switch a stage (``fm``, ``on``) or ramp the gain (``gain``, ``ramp``) of an optic's
    damping filter module; the twin refuses it unless the loop stays stable."""

    dof: str
    optic: str | None = None
    fm: int | None = None
    on: bool = True
    gain: float | None = None
    ramp: float | None = None

    @classmethod
    def from_json(cls, request: Mapping[str, Any]) -> FilterRequest:
        """The request in `request`, or a RequestError naming the field at fault."""
        _known(request, ("optic", "dof", "fm", "on", "gain", "ramp"), "filter")
        dof = request.get("dof")
        if dof not in DOFS:
            msg = f"dof must be one of {', '.join(DOFS)}, got {str(dof)[:40]!r}"
            raise RequestError(msg)
        fm, on, gain, ramp = (request.get(k) for k in ("fm", "on", "gain", "ramp"))
        if fm is not None and (not is_int(fm) or not 1 <= fm <= N_STAGES):
            msg = f"fm must be an integer 1..{N_STAGES}, got {str(fm)[:40]!r}"
            raise RequestError(msg)
        if on is not None and not isinstance(on, bool):
            msg = f"on must be true or false, got {str(on)[:40]!r}"
            raise RequestError(msg)
        if gain is not None and not _number(gain):
            msg = f"gain must be a finite number, got {str(gain)[:40]!r}"
            raise RequestError(msg)
        if ramp is not None and not (is_real(ramp) and 0 <= ramp <= MAX_GAIN_RAMP_S):
            msg = (f"ramp must be a number of seconds in 0..{MAX_GAIN_RAMP_S:g}, "
                   f"got {str(ramp)[:40]!r}")
            raise RequestError(msg)
        if fm is None and gain is None:
            msg = "a filter request changes a stage (fm, on) or the gain (gain, ramp)"
            raise RequestError(msg)
        return cls(dof, _optic(request), None if fm is None else int(fm),
                   True if on is None else on, None if gain is None else float(gain),
                   None if ramp is None else float(ramp))

    def to_json(self) -> dict[str, Any]:
        """The JSON object the twin reads (only the fields given)."""
        body = {"optic": self.optic, "dof": self.dof, "gain": self.gain, "ramp": self.ramp,
                **({"fm": self.fm, "on": self.on} if self.fm is not None else {})}
        return {k: v for k, v in body.items() if v is not None}

    def applied(self, module: FilterModule) -> FilterModule:
        """`module` as it would be after the change (it is not touched)."""
        on = set(module.on)
        if self.fm is not None:
            on = on | {self.fm} if self.on else on - {self.fm}
        return replace(module, on=on, gain=module.gain if self.gain is None else self.gain)


# ------------------------------------------------------------------------------ replies
@dataclass(frozen=True)
class Excitation:
    """An excitation a twin runs or has scheduled, as ``status`` lists it."""

    id: str
    channel: str
    waveform: str
    start_gps: float
    scheduled: bool


@dataclass(frozen=True)
class StatusReply:
    """A twin's ``status``: who it is, how well it keeps time, what it runs.

    Attributes
    ----------
    twin, ifo : str
        The twin's id (host/pid/tag) and its interferometer's prefix (``C1``).
    optics : list of str
    rate_hz, block_s, speed : float
        Samples per second, seconds per published block, twin seconds per wall second.
    gps, uptime_s : float
        The twin's time now and the seconds it has served.
    blocks, late_blocks, dropped_blocks : int
    real_time_factor, cpu_fraction : float
    lag_s, max_lag_s : float
        Behind the wall clock now and at worst.
    injection_latency_s : dict
        Request-to-EXC latency (``median``, ``p99``, ``max``, ``n``).
    excitations : list of Excitation
    config : str
        The configuration file it was started from.
    watchdogs : dict of str to str
        Per optic: ``armed`` or ``tripped``.
    recorder : dict or None
        The recorder it runs, if any (``folder``, ``recording``, ``restarts``...).
    """

    twin: str
    ifo: str
    optics: list[str]
    rate_hz: float
    block_s: float
    speed: float
    gps: float
    uptime_s: float
    blocks: int
    real_time_factor: float
    lag_s: float
    max_lag_s: float
    late_blocks: int
    dropped_blocks: int
    injection_latency_s: dict[str, Any]
    cpu_fraction: float
    excitations: list[Excitation]
    config: str
    watchdogs: dict[str, str]
    recorder: dict[str, Any] | None = None

    @classmethod
    def from_json(cls, reply: Mapping[str, Any]) -> StatusReply:
        """The status in a twin's reply (fields a newer twin adds are left out)."""
        names = {f.name for f in fields(cls)}
        body = {k: v for k, v in reply.items() if k in names}
        return cls(**{**body, "excitations": [Excitation(**e) for e in reply["excitations"]]})

    def to_json(self) -> dict[str, Any]:
        """The reply's JSON object, ``"ok": true`` first."""
        return {"ok": True, **asdict(self)}


@dataclass(frozen=True)
class ModuleState:
    """A damping filter module as it runs: gain, the stages on, output limit, ramp time."""

    gain: float
    on: list[int]
    limit: float | None
    ramp_s: float


@dataclass(frozen=True)
class ParamsReply:
    """An optic's parameters as it runs, the reply of ``params`` and ``filter``.

    Attributes
    ----------
    twin : str
    optic : str
    params : dict
        Every field of its :class:`twind.model.params.SOSParams`.
    filters : dict of str to ModuleState
        Its damping filter modules by DOF.
    watchdog : str
        ``armed`` or ``tripped``.
    effect : EffectChange or None
        The physics left out it runs.
    """

    twin: str
    optic: str
    params: dict[str, Any]
    filters: dict[str, ModuleState]
    watchdog: str
    effect: EffectChange | None = None

    @classmethod
    def from_json(cls, reply: Mapping[str, Any]) -> ParamsReply:
        """The parameters in a twin's reply."""
        effect = reply.get("effect")
        return cls(reply.get("twin", ""), reply["optic"], dict(reply["params"]),
                   {d: ModuleState(**m) for d, m in reply["filters"].items()},
                   reply["watchdog"], None if effect is None else EffectChange(**effect))

    def to_json(self) -> dict[str, Any]:
        """The reply's JSON object, ``"ok": true`` first."""
        return {"ok": True, **asdict(self)}
