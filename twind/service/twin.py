"""The twin as a service: the engine paced to the wall clock, publishing every test point on
Zenoh and answering control queries (status, inject, stop, params, filter).

A block is computed when its span has passed and published at once, as data acquisition
does. An excitation asked for "now" starts at the sample of that moment, inside the block
due next: latency at most one block plus the computation. Queries arrive on Zenoh's threads;
they only touch shared state under a lock.
"""

from __future__ import annotations

import collections
import itertools
import json
import math
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable, Hashable
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import zenoh

from twind import DOFS, strictjson
from twind.bus.codec import SampleBlock
from twind.bus.keys import ROOT, control_key, data_key
from twind.channels import DRIVE_POINTS, block_channels, dof_channel, drive_channel
from twind.config import OpticConfig, TwinConfig
from twind.errors import FotonError, TwindError
from twind.excitation import ExcitationError, ExcitationRequest, Limits, check, make_waveform
from twind.excitation.request import MAX_FINITE_SAMPLES
from twind.loop.damping import DampingLoop
from twind.model.effects import with_effect
from twind.protocol import (
    EffectChange,
    Excitation,
    FilterRequest,
    ModuleState,
    ParamsReply,
    ParamsRequest,
    StatusReply,
    StopRequest,
)
from twind.simulation.discretize import closed_loop_matrices
from twind.simulation.engine import Engine
from twind.timeutil import now_gps

VERBS = ("status", "inject", "stop", "params", "filter")


@dataclass
class Active:
    """An accepted excitation and where it runs."""

    id: str
    request: ExcitationRequest
    optic: int
    point: Hashable  # which test point of the optic (Twin._test_point)
    start_sample: int
    waveform: object = field(repr=False)
    received: float = 0.0  # monotonic time the request was taken up
    stopping: bool = False  # asked to stop: ramping down


@dataclass
class Stats:
    """Pacing figures reported by ``status``."""

    blocks: int = 0
    late_blocks: int = 0  # computed after their due time by more than one block
    max_lag_s: float = 0.0
    lag_s: float = 0.0
    busy_s: float = 0.0  # wall time spent computing and publishing
    dropped_blocks: int = 0  # channel blocks Zenoh refused to publish
    latency_s: collections.deque = field(  # request -> its first sample published, the last
        default_factory=lambda: collections.deque(maxlen=LATENCY_KEPT))  # injections'

    def latency(self) -> dict:
        """Injection latency over the last :data:`LATENCY_KEPT` injections (s)."""
        lat = np.array(self.latency_s)
        if lat.size == 0:
            return {"n": 0, "median": None, "p99": None, "max": None}
        return {"n": int(lat.size), "median": float(np.median(lat)),
                "p99": float(np.percentile(lat, 99)), "max": float(lat.max())}


LATENCY_KEPT = 1000


class TwinService:
    """One engine, its Zenoh publishers and its control queryables.

    Parameters
    ----------
    session : zenoh.Session
        An open session (the service declares on it, the caller owns it).
    twin : TwinConfig
        The interferometer's configuration (for names and snapshots).
    optics : list of OpticConfig
        The optics to run.
    block_s : float
        Seconds of twin time per block (1/16 s by default, as CDS test points).
    speed : float
        Twin seconds per wall second (1 = real time).
    seed : int
        Noise seed.
    root : str
        Key root of the data channels.
    recorder_status : callable, optional
        The state of ``serve --record``'s recorder, for status; given here so that no status
        reply goes out before it is known.
    """

    def __init__(self, session: zenoh.Session, twin: TwinConfig, optics: list[OpticConfig],
                 block_s: float = 1 / 16, speed: float = 1.0, seed: int = 0,
                 root: str = ROOT, recorder_status: Callable[[], dict] | None = None) -> None:
        if not (speed > 0 and math.isfinite(speed)):
            msg = f"speed must be positive and finite, got {speed}"
            raise TwindError(msg)
        self.twin, self.optics, self.root = twin, optics, root
        self.accepts = twin.service  # what clients may ask (the file's [service] table)
        self.limits = Limits(peak=twin.service.exc_peak, rms=twin.service.exc_rms)
        self.drive_limits = Limits(peak=twin.service.drive_peak, rms=twin.service.drive_rms)
        self.rate = optics[0].rate_hz
        self.n = int(round(block_s * self.rate))
        if self.n < 1:
            msg = f"a block of {block_s} s holds no sample at {self.rate:g} Hz"
            raise TwindError(msg)
        self.block_s, self.speed = self.n / self.rate, speed
        self._start_engine(seed)
        SampleBlock("warm-up", 0.0, self.rate, 0, np.zeros(self.n)).encode()
        self.gps0 = math.floor(now_gps() / self.block_s) * self.block_s  # blocks on GPS marks
        self.stats = Stats()
        self._lock = threading.Lock()
        self._params_lock = threading.Lock()  # one parameter change at a time
        self._effects: dict[str, EffectChange] = {}  # physics pushed in beyond nominal
        self._changes: collections.deque[float] = collections.deque()  # their times
        self._active: dict[str, Active] = {}
        self._unpublished: dict[str, Active] = {}  # accepted, first sample not yet published
        tag = uuid.uuid4().hex[:6]  # ids stay unique when several twins share a router
        self._ids = (f"exc-{tag}-{i}" for i in itertools.count(1))
        self.twin_id = f"{socket.gethostname()}/{os.getpid()}/{tag}"  # in every reply, event, block
        self._ended: set[str] = set()
        self._started = self._t0 = time.monotonic()
        self._end: int | None = None  # the sample the service stops at, when it is to stop
        self.recorder_status = recorder_status
        self._session = session
        # Zenoh drops samples under congestion by default; a twin whose recordings have gaps is
        # worse than one that waits a moment for a slow subscriber
        self._pubs = {name: session.declare_publisher(
            data_key(name, root), congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE) for name, _, _ in self._channels}
        self._events = session.declare_publisher(control_key(twin.ifo, "events", root))
        self._handlers: dict[str, Callable[[dict], dict]] = {
            "status": lambda _: self.status(), "inject": self.inject, "stop": self.stop,
            "params": self.params, "filter": self.filter}
        self._queryables = [
            session.declare_queryable(key, self._answer(verb, key))
            for verb in VERBS for key in (control_key(twin.ifo, verb, root),)]

    def _start_engine(self, seed: int) -> None:
        """The engine, warmed up, and the channels it publishes (:attr:`_channels`: name,
        unit and the view of the block's samples)."""
        optics = self.optics
        self.engine = Engine([o.loop() for o in optics], {o.name: o.noise for o in optics},
                             seed=seed, rate_hz=self.rate)
        # load the compiled kernels now, so the first block is not late (with several
        # optics the engine runs the kernel that shares them among numba's threads:
        # compiling it takes ~10 s where no cache is)
        first = optics[:2]
        Engine([o.loop() for o in first], {o.name: o.noise for o in first},
               rate_hz=self.rate).step(self.n)
        for optic in optics:  # and what a params or filter change checks, cached
            _check_stable(optic.loop(), self.rate)
        self._buf = self.engine.new_block(self.n)
        # every block is computed into _buf, so its channels' views are taken once; the EXC
        # test points first, so that an excitation goes out before every optic's responses
        self._channels = sorted(block_channels(self.twin.ifo, self._buf),
                                key=lambda c: not c[0].endswith("_EXC"))

    def _advance(self, exc: dict[tuple[int, int], np.ndarray] | None) -> None:
        """Compute the next block into the channels' views, with the excitations `exc` (by
        optic and test point, :meth:`_test_point`; under the lock)."""
        drives: dict[int, np.ndarray] = {}  # 0: the damping EXC, 1: past the filters
        for (o, (kind, d)), samples in (exc or {}).items():
            if kind not in drives:
                drives[kind] = np.zeros((len(self.optics), len(DOFS), self.n))
            drives[kind][o, d] = samples
        self._watch(self.engine.step(self.n, exc=drives.get(0), lsc=drives.get(1),
                                     out=self._buf))

    def _watchdogs(self) -> dict[str, str]:
        """Each optic's watchdog, as ``status`` reports it."""
        return {o.name: "tripped" if self.engine.tripped(o.name) else "armed"
                for o in self.optics}

    # ---------------------------------------------------------------------------- pacing
    def run(self, duration: float | None = None, stop: threading.Event | None = None) -> None:
        """Serve until `duration` twin seconds have passed or `stop` is set.

        Each block is computed and published once its span has passed on the wall clock
        (scaled by the speed); a block done more than one block late counts as late.

        Parameters
        ----------
        duration : float, optional
            Twin seconds to serve; None serves until `stop`.
        stop : threading.Event, optional
            Set (from another thread or a signal handler) to end the service.
        """
        stop = stop or threading.Event()
        if duration is not None:
            self._end = self.engine.samples + int(round(duration * self.rate))
        t0 = self._t0 = time.monotonic()
        for k in itertools.count():
            if duration is not None and k * self.block_s >= duration - 1e-9:
                return
            due = t0 + (k + 1) * self.block_s / self.speed  # a block is published when its span ends
            if stop.wait(max(0.0, due - time.monotonic())):
                return
            started = time.monotonic()
            self.step()
            done = time.monotonic()
            self.stats.busy_s += done - started
            self.stats.lag_s = done - due
            self.stats.max_lag_s = max(self.stats.max_lag_s, self.stats.lag_s)
            if self.stats.lag_s > self.block_s / self.speed:
                self.stats.late_blocks += 1

    def step(self) -> None:
        """Compute the next block, with the excitations that fall in it, and publish it."""
        with self._lock:
            first = self.engine.samples
            self._advance(self._excitation(first))
            starting = collections.defaultdict(list)  # EXC channel -> excitations starting
            for act in self._unpublished.values():
                if act.start_sample < first + self.n:
                    starting[act.request.channel].append(act)
        gps = self.gps0 + first / self.rate
        seq = self.stats.blocks
        for name, unit, samples in self._channels:
            try:
                self._pubs[name].put(SampleBlock(name, gps, self.rate, seq, samples, unit,
                                                 self.twin_id).encode())
            except zenoh.ZError:  # the session is closing or the transport failed: counted
                self.stats.dropped_blocks += 1
            for act in starting.pop(name, ()):
                self.stats.latency_s.append(time.monotonic() - act.received)
                self._unpublished.pop(act.id, None)
        self.stats.blocks += 1

    def _watch(self, block) -> None:  # noqa: ANN001 - simulation.engine.Block
        """Trip the watchdog of every optic whose OSEMs left their range or turned non-finite
        in `block` (under the lock)."""
        limit = self.accepts.watchdog_um
        with np.errstate(invalid="ignore"):
            peak = np.abs(block.sen).max(axis=(1, 2))
        for o, optic in enumerate(self.optics):
            if not peak[o] <= limit and not self.engine.tripped(optic.name):  # NaN too
                self.engine.trip(optic.name)
                reason = (f"an OSEM read {peak[o]:.4g} um, beyond the watchdog's {limit:g} um "
                          "(service.watchdog_um)")
                self._publish_event("tripped", None, optic=optic.name, reason=reason)

    def _excitation(self, first: int) -> dict[tuple[int, int], np.ndarray] | None:
        """The samples of this block's excitations, summed by test point ((optic, DOF) index;
        a state-space optic's: (0, its EXC point)); those that end or fail leave, with their
        event. Under the lock."""
        if not self._active:
            return None
        exc: dict[tuple[int, int], np.ndarray] = {}
        for act in list(self._active.values()):
            a = max(0, act.start_sample - first)
            if a >= self.n:
                continue
            try:
                samples = act.waveform.next(self.n - a)
            except Exception as err:  # noqa: BLE001 - one excitation's fault ends it, not the loop
                del self._active[act.id]
                self._ended.add(act.id)
                self._publish_event("error", act, reason=f"{type(err).__name__}: {err}")
                continue
            key = (act.optic, act.point)
            if key not in exc:
                exc[key] = np.zeros(self.n)
            exc[key][a:] += samples
            if act.waveform.done:
                del self._active[act.id]
                self._ended.add(act.id)
                self._publish_event("end", act)
        return exc

    # ---------------------------------------------------------------------------- control
    def _answer(self, verb: str, key: str) -> Callable[[zenoh.Query], None]:
        def on_query(query: zenoh.Query) -> None:
            if str(query.key_expr) != key:  # a wildcard would run every verb at once
                query.reply_err(f"ask {verb} on its own key {key}, not {query.key_expr}")
                return
            payload = query.payload if query.payload is not None else b""
            reply = self.status() if verb == "status" else self.handle(verb, payload)
            query.reply(query.key_expr, strictjson.dumps({**reply, "twin": self.twin_id}))

        return on_query

    def handle(self, verb: str, payload: bytes | zenoh.ZBytes) -> dict:
        """The reply to one control request: `payload` (JSON) for `verb`, one of
        :data:`VERBS`. Never raises: a request that cannot be served is answered with
        ``"ok": false`` and the reason. A payload beyond ``service.request_bytes`` is
        refused before it is copied out of Zenoh.

        Parameters
        ----------
        verb : str
            ``status``, ``inject``, ``stop``, ``params`` or ``filter``.
        payload : bytes or zenoh.ZBytes
            The request's JSON object; empty for ``{}``.

        Returns
        -------
        dict
            The reply's JSON object.
        """
        received = time.monotonic()
        try:
            # JSON parsing holds the interpreter lock the pacing thread needs
            if len(payload) > self.accepts.request_bytes:
                msg = (f"request of {len(payload)} bytes; at most {self.accepts.request_bytes} "
                       "(service.request_bytes; stream long waveforms in several requests)")
                raise TwindError(msg)
            if isinstance(payload, zenoh.ZBytes):
                payload = payload.to_bytes()
            request = json.loads(payload) if payload else {}
            if not isinstance(request, dict):
                msg = "the request must be a JSON object"
                raise TwindError(msg)
            if verb == "inject":
                return self.inject(request, received)
            return self._handlers[verb](request)
        except Exception as err:  # noqa: BLE001 - every request gets an answer, never silence
            return {"ok": False, "accepted": False, "reason": _cut(
                f"{type(err).__name__}: {err}" if not isinstance(err, TwindError) else str(err))}

    def status(self) -> dict:
        """Real-time factor, lag, late blocks, active excitations, uptime
        (:class:`twind.protocol.StatusReply`)."""
        uptime = time.monotonic() - self._started
        twin_time = self.stats.blocks * self.block_s
        with self._lock:
            active = [Excitation(a.id, a.request.channel, a.request.waveform,
                                 self.gps0 + a.start_sample / self.rate,
                                 a.start_sample >= self.engine.samples)
                      for a in self._active.values()]
        return StatusReply(
            twin=self.twin_id, ifo=self.twin.ifo, optics=[o.name for o in self.optics],
            rate_hz=self.rate, block_s=self.block_s, speed=self.speed,
            gps=self.gps0 + twin_time, uptime_s=uptime, blocks=self.stats.blocks,
            real_time_factor=twin_time / uptime if uptime > 0 else 0.0,
            lag_s=self.stats.lag_s, max_lag_s=self.stats.max_lag_s,
            late_blocks=self.stats.late_blocks, dropped_blocks=self.stats.dropped_blocks,
            injection_latency_s=self.stats.latency(),
            cpu_fraction=self.stats.busy_s / uptime if uptime > 0 else 0.0,
            excitations=active, config=self.twin.source, watchdogs=self._watchdogs(),
            recorder=self.recorder_status() if self.recorder_status else None).to_json()

    def inject(self, request: dict, received: float | None = None) -> dict:
        """Accept an excitation (reply with its id) or refuse it with the reason.

        Parameters
        ----------
        request : dict
            An :class:`~twind.excitation.ExcitationRequest` as JSON: ``channel`` (an EXC
            test point of this twin), ``waveform`` and its settings.
        received : float, optional
            When the request came (:func:`time.monotonic`), for the injection latency
            ``status`` reports; by default the time of the call.

        Returns
        -------
        dict
            ``ok`` and ``accepted``; if accepted the excitation's ``id`` and ``start_gps``,
            else the ``reason``.
        """
        received = time.monotonic() if received is None else received
        try:
            req = ExcitationRequest.from_json(request)
            optic, point, limits = self._test_point(req.channel)
        except (ExcitationError, TwindError) as err:  # maybe another twin's channel: no event
            return {"ok": False, "accepted": False, "reason": _cut(str(err))}
        if req.waveform != "stream" and req.amp == 0:
            return {"ok": False, "accepted": False, "reason": "amp: 0 excites nothing, and "
                    "would hold one of the test point's slots"}
        try:
            check(req, self._room_left(optic, point, limits), self.rate)
        except ExcitationError as err:
            reason = _cut(str(err))
            self._publish_event("refused", None, request=_summary(req.to_json()), reason=reason)
            return {"ok": False, "accepted": False, "reason": reason}
        with self._lock:
            next_sample = self.engine.samples
            if req.start_gps is None:
                # the sample of this moment, inside the block due next: the twin does not
                # excite its past
                now = int((time.monotonic() - self._t0) * self.speed * self.rate)
                start = max(next_sample, min(now, next_sample + self.n - 1))
            else:
                start = int(round((req.start_gps - self.gps0) * self.rate))
                if start < next_sample:
                    reason = (f"start GPS {req.start_gps} has passed; the next sample is at "
                              f"{self.gps0 + next_sample / self.rate}")
                    return {"ok": False, "accepted": False, "reason": reason}
            crowded = self._crowded(optic, point, start - next_sample) or self._past_end(req, start)
            if crowded:
                return {"ok": False, "accepted": False, "reason": f"{req.channel}: {crowded}"}
            waveform = make_waveform(req, self.rate)
            held = waveform.held_bytes + sum(a.waveform.held_bytes
                                             for a in self._active.values())
            if held > self.accepts.waveform_bytes:
                reason = (f"{req.channel}: the excitations' waveforms would hold "
                          f"{held / 1e6:.0f} MB, beyond the {self.accepts.waveform_bytes / 1e6:.0f}"
                          " MB the twin keeps for them (service.waveform_bytes)")
                return {"ok": False, "accepted": False, "reason": reason}
            act = Active(next(self._ids), req, optic, point, start, waveform, received)
            self._active[act.id] = act
            if req.start_gps is None:  # "now": its latency is the service's
                self._unpublished[act.id] = act
            self._publish_event("start", act)  # under the lock: before any "end" of it
        return {"ok": True, "accepted": True, "id": act.id,
                "start_gps": self.gps0 + start / self.rate}

    def _past_end(self, req: ExcitationRequest, start: int) -> str:
        """Why an excitation from sample `start` cannot run whole before the service stops
        ("" if it can, or runs until stopped)."""
        if self._end is None or math.isinf(req.duration):
            return ""
        if start + req.duration * self.rate <= self._end:
            return ""
        return (f"it would run to GPS {self.gps0 + start / self.rate + req.duration:.3f}, past "
                f"the end of this service at GPS {self.gps0 + self._end / self.rate:.3f} "
                "(serve --duration)")

    def _crowded(self, optic: int, point: Hashable, ahead: int) -> str:
        """Why one more excitation, `ahead` samples from now, is too many ("" if not);
        under the lock."""
        limits = self.accepts
        if ahead > limits.schedule_ahead_s * self.rate:
            return (f"starts {ahead / self.rate:.0f} s ahead; at most "
                    f"{limits.schedule_ahead_s:g} s (service.schedule_ahead_s)")
        on = sum((a.optic, a.point) == (optic, point) for a in self._active.values())
        if on >= limits.excitations_per_channel:
            return (f"{on} excitations run or wait on it already, the most one test point "
                    "takes (service.excitations_per_channel)")
        if len(self._active) >= limits.excitations:
            return (f"{len(self._active)} excitations run or wait already, the most the twin "
                    "takes (service.excitations)")
        return ""

    def _room_left(self, optic: int, point: Hashable, limits: Limits) -> Limits:
        """The limits less what the excitations already on that test point use: two
        accepted sines must not add up past the limit."""
        with self._lock:
            on = [a for a in self._active.values() if (a.optic, a.point) == (optic, point)]
        peak = sum(_peak(a.request) for a in on)
        rms = math.sqrt(sum(_rms(a.request) ** 2 for a in on))
        return Limits(peak=max(0.0, limits.peak - peak),
                      rms=math.sqrt(max(0.0, limits.rms**2 - rms**2)))

    def stop(self, request: dict) -> dict:
        """Stop an excitation by id (``{"id": ...}``), or all with ``{"all": true}``; it
        ramps down over its request's ``ramp``, or ``"ramp"`` seconds if given."""
        req = StopRequest.from_json(request)
        ramp = req.ramp
        if ramp is not None and not ramp * self.rate <= MAX_FINITE_SAMPLES:
            msg = f"'ramp' of {ramp:g} s is more samples than the twin counts"
            raise TwindError(msg)
        with self._lock:
            ids = list(self._active) if req.all else [req.id]
            ended = [i for i in ids if i in self._ended]
            missing = [i for i in ids if i not in self._active and i not in self._ended]
            if missing:
                return {"ok": False, "reason": _cut(f"no excitation {missing[0]!r}")}
            stopping = [self._active[i] for i in ids
                        if i in self._active and not self._active[i].stopping]
            for act in stopping:
                act.stopping = True
                if act.start_sample >= self.engine.samples:  # never ran: gone at once
                    del self._active[act.id]
                    self._unpublished.pop(act.id, None)
                    self._ended.add(act.id)
                else:  # ramp down as asked, no kick to the optic
                    act.waveform.stop(act.request.ramp if ramp is None else ramp)
        for act in stopping:
            self._publish_event("stop", act)
        return {"ok": True, "stopped": [a.id for a in stopping], "already_ended": ended}

    def params(self, request: dict) -> dict:
        """Get (``{"optic": "ETMX"}``) or set parameters (:class:`twind.protocol.ParamsRequest`):
        ``"set": {name: value}`` the nominal ones, ``"effect": {"id": ..., "values": {...}}``
        physics the nominal model leaves out (the catalogue of docs/model.md; ``{"id": null}``
        removes it), kept across later changes of the nominal parameters; ``"watchdog":
        "rearm"`` re-arms a tripped watchdog."""
        req = ParamsRequest.from_json(request)
        index = self._optic_index(req.optic)
        name = self.optics[index].name
        if req.rearm:
            with self._lock:
                if self.engine.tripped(name):
                    self.engine.rearm(name)
                    self._publish_event("rearmed", None, optic=name)
        if req.set or req.effect is not None:
            self._rebuild(index, req.set, req.effect)
        modules = {d: ModuleState(m.gain, sorted(m.on), m.limit, m.ramp_s)
                   for d, m in self.engine.loops[index].modules.items()}
        return ParamsReply(self.twin_id, name, asdict(self.optics[index].sus), modules,
                           "tripped" if self.engine.tripped(name) else "armed",
                           self._effects.get(name)).to_json()

    def _count_change(self) -> None:
        """Refuse a change beyond ``service.changes_per_minute`` (under the params lock)."""
        now, most = time.monotonic(), self.accepts.changes_per_minute
        while self._changes and now - self._changes[0] > 60.0:
            self._changes.popleft()
        if len(self._changes) >= most:
            msg = (f"{most} params/filter changes in the last minute already, the most the "
                   f"twin takes (service.changes_per_minute); try again in "
                   f"{60.0 - (now - self._changes[0]):.0f} s")
            raise TwindError(msg)
        self._changes.append(now)

    def _rebuild(self, index: int, changes: dict[str, float],
                 effect: EffectChange | None) -> None:
        """A new plant from the changed parameters and effect, checked, then swapped in."""
        with self._params_lock:
            self._count_change()
            cfg = self.optics[index]
            sus = cfg.sus.updated(**changes)
            problems = sus.check()
            if problems:
                raise TwindError("; ".join(f"{k}: {p}" for k, p in problems))
            applied = self._effects.get(cfg.name)
            if effect is not None:
                applied = effect if effect.id else None
            new = replace(cfg, sus=sus)
            loop = new.loop()
            if applied:
                loop.plant = with_effect(loop.plant, sus, applied.id, applied.values)
            loop.modules = self.engine.loops[index].modules  # the filters as they run now
            _check_stable(loop, self.rate)
            with self._lock:
                try:
                    self.engine.update_plant(cfg.name, loop)
                except ValueError as err:  # e.g. a coil-driver pole adds states
                    msg = f"{err}: start the twin with this plant instead of changing it live"
                    raise TwindError(msg) from None
                self.optics[index] = new
                if applied:
                    self._effects[cfg.name] = applied
                else:
                    self._effects.pop(cfg.name, None)

    def filter(self, request: dict) -> dict:
        """Switch a stage (``fm``, ``on``) or ramp a gain (``gain``, ``ramp``) of a module;
        refused, with the reason, unless the damping loop stays stable with the change."""
        change = FilterRequest.from_json(request)
        index = self._optic_index(change.optic)
        optic = self.optics[index].name
        with self._params_lock:
            self._count_change()
            loop = self.engine.loops[index]
            modules = dict(loop.modules)
            try:
                modules[change.dof] = change.applied(modules[change.dof])
            except FotonError as err:
                raise TwindError(f"{optic} {change.dof}: {err}") from None
            _check_stable(DampingLoop(loop.name, loop.plant, modules), self.rate)
            with self._lock:
                if change.fm is not None:
                    self.engine.switch(optic, change.dof, change.fm, change.on)
                if change.gain is not None:
                    self.engine.set_gain(optic, change.dof, change.gain, change.ramp)
        return self.params({"optic": optic})

    # ---------------------------------------------------------------------------- helpers
    def _optic_index(self, name: str | None) -> int:
        """The index of optic `name`; the first optic's when None."""
        if name is None:
            return 0
        names = [o.name for o in self.optics]
        if name not in names:
            msg = f"unknown optic {name!r}; this twin runs {', '.join(names)}"
            raise TwindError(msg)
        return names.index(name)

    def _test_point(self, channel: str) -> tuple[int, Hashable, Limits]:
        """``(optic, point, limits)`` of an EXC channel: point ``(0, d)`` is DOF ``d``'s
        damping EXC (um or urad), ``(1, d)`` its excitation past the damping filters
        (:func:`drive_channel`, ct)."""
        ifo = self.twin.ifo
        for o, optic in enumerate(self.optics):
            for d, dof in enumerate(DOFS):
                if channel == dof_channel(ifo, optic.name, dof, "EXC"):
                    return o, (0, d), self.limits
                if dof in DRIVE_POINTS and channel == drive_channel(ifo, optic.name, dof):
                    return o, (1, d), self.drive_limits
        first = self.optics[0].name
        msg = (f"unknown excitation channel {channel!r}; e.g. "
               f"{dof_channel(ifo, first, 'POS', 'EXC')} or {drive_channel(ifo, first, 'POS')}")
        raise TwindError(msg)

    def _publish_event(self, event: str, act: Active | None, **extra: object) -> None:
        body: dict = {"event": event, "gps": self.gps0 + self.engine.samples / self.rate,
                      "twin": self.twin_id, **extra}
        if act is not None:
            body.update(id=act.id, channel=act.request.channel,
                        start_gps=self.gps0 + act.start_sample / self.rate,
                        request=_summary(act.request.to_json()))
        self._events.put(strictjson.dumps(body, default=_jsonable))

    def close(self) -> None:
        """Undeclare everything this service declared."""
        for q in self._queryables:
            q.undeclare()
        for p in self._pubs.values():
            p.undeclare()
        self._events.undeclare()


def _peak(req: ExcitationRequest) -> float:
    return 6 * req.amp if req.waveform == "noise" else (
        float(np.max(np.abs(req.samples))) if req.waveform == "stream" else req.amp)


def _rms(req: ExcitationRequest) -> float:
    if req.waveform == "stream":
        return float(np.sqrt(np.mean(np.square(req.samples))))
    return req.amp if req.waveform == "noise" else req.amp / math.sqrt(2)


def _check_stable(loop, rate: float) -> None:  # noqa: ANN001 - DampingLoop

    with np.errstate(all="ignore"):
        A = closed_loop_matrices(loop, rate)[0]
        worst = (np.abs(np.linalg.eigvals(A)).max() if np.all(np.isfinite(A)) else math.inf)
    if not worst < 1.0:  # NaN too
        msg = f"refused: with these parameters the damping loop would be unstable (|z| = {worst:.6f})"
        raise TwindError(msg)


def _jsonable(obj: object) -> str:
    return str(obj)


def _summary(request: dict) -> dict:
    """A request for the event log: a stream's samples only by count and RMS, any other
    long string cut to :data:`ECHO_CHARS`."""
    samples = request.get("samples")
    if isinstance(samples, list):
        x = np.asarray(samples, dtype=float)
        with np.errstate(over="ignore"):  # a refused stream of 1e300s: its RMS is inf
            rms = float(np.sqrt(np.mean(x**2))) if x.size else 0.0
        request = {**request, "samples": {"n": int(x.size), "rms": rms}}
    return {k: _cut(v) if isinstance(v, str) else v for k, v in request.items()}


ECHO_CHARS = 300
"""The longest piece of a request a reply or an event repeats: a refused 5 MB shape is not
sent back whole, nor written into every recording."""


def _cut(text: str) -> str:
    return text if len(text) <= ECHO_CHARS else f"{text[:ECHO_CHARS]}... ({len(text)} characters)"
