"""Stream a running twin's channels from Zenoh into Rerun, decimated, until stopped.

Blocks arrive on Zenoh's threads and are queued; the calling thread decodes, decimates
(:mod:`twind.viz.decimate`, one filter per channel) and sends the series to Rerun every
`flush_s` seconds with ``send_columns``, under the same entity paths and timelines as
:mod:`twind.viz.rerun_export` (``sus/ETMX/POS/IN1`` on ``gps`` and ``utc``); injection events
go to ``events`` as text rows. The layout (a tab per optic) is sent again whenever a new optic
shows up.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rerun as rr
import zenoh

from twind.bus.codec import SampleBlock
from twind.bus.keys import ROOT, all_data, control_key
from twind.bus.session import zenoh_config
from twind.channels import parse_dof_channel
from twind.viz.decimate import NS, Decimated, Decimator
from twind.viz.entities import blueprint, entity_path, matcher
from twind.viz.rerun_export import EVENTS_ENTITY, event_gps, event_text, gps_columns

MAX_BACKLOG = 20_000  # queued blocks: about 6 s of all 210 channels of the 40m


@dataclass
class LiveStats:
    """What :func:`stream` sent."""

    blocks: int = 0
    rows: dict[str, int] = field(default_factory=dict)  # entity path -> decimated rows
    events: int = 0
    dropped: int = 0  # undecodable payloads, and blocks dropped while too far behind


def stream(rec, connect: Sequence[str], *, config_file: str | None = None, ifo: str = "C1",  # noqa: ANN001, PLR0913
           channels: Iterable[str] | str | None = None, rate_hz: float = 64.0,
           flush_s: float = 0.25, stop: threading.Event | None = None,
           duration: float | None = None, root: str = ROOT,
           subscribed: threading.Event | None = None) -> LiveStats:
    """Subscribe to every twin channel and stream it to the Rerun recording `rec`.

    Parameters
    ----------
    rec : rerun.RecordingStream
        Where to send (a viewer, a gRPC server or a file: the caller sets the sink).
    connect : sequence of str
        Zenoh endpoints of the twin or its router (a client session is opened).
    config_file : str, optional
        A Zenoh JSON5 configuration (credentials, TLS) to start from.
    ifo : str
        Interferometer prefix, for the events key ``twin/@/<ifo>/events``.
    channels : str or iterable of str, optional
        Shell-style patterns of channels to show (all when None).
    rate_hz : float
        Rate of the plotted series.
    flush_s : float
        Seconds between sends to Rerun.
    stop : threading.Event, optional
        Set it to end the stream (Ctrl-C ends it too).
    duration : float, optional
        Wall seconds after which to stop.
    root : str
        Root of the twin's keys.
    subscribed : threading.Event, optional
        Set once the subscriptions are in place at the twin: declared, and a query of its
        status answered over the same link after them (up to 5 s for the answer), so that
        what is published from then on, an injection's events too, is seen.

    Returns
    -------
    LiveStats
        What was streamed.
    """

    stop = stop or threading.Event()
    select = matcher(channels)
    inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
    sink = _Sink(rec, rate_hz)
    session = zenoh.open(zenoh_config(connect=connect, mode="client", config_file=config_file))

    def on_data(sample: zenoh.Sample) -> None:
        if inbox.qsize() > MAX_BACKLOG:  # falling behind: drop rather than grow without end
            sink.stats.dropped += 1
            return
        inbox.put(("data", sample.payload.to_bytes()))

    subs = [session.declare_subscriber(all_data(root), on_data),
            session.declare_subscriber(control_key(ifo, "events", root),
                                       lambda s: inbox.put(("event", s.payload.to_bytes())))]
    if subscribed is not None:
        list(session.get(control_key(ifo, "status", root), timeout=5.0))  # a round trip
        subscribed.set()
    started = time.monotonic()
    next_flush = started + flush_s
    try:
        while not stop.is_set():
            now = time.monotonic()
            if duration is not None and now - started >= duration:
                break
            try:
                kind, data = inbox.get(timeout=max(0.0, min(next_flush - now, 0.1)))
            except queue.Empty:
                kind = ""
            if kind == "data":
                sink.data(data, select)
            elif kind == "event":
                sink.event(data)
            if time.monotonic() >= next_flush:
                sink.flush()
                next_flush = time.monotonic() + flush_s
    except KeyboardInterrupt:
        pass
    finally:
        for sub in subs:
            sub.undeclare()
        session.close()
        sink.flush()
        rec.flush()
    return sink.stats


class _Sink:
    """What :func:`stream` sends to Rerun: each channel decimated to `rate_hz` and sent in
    batches, a blueprint tab per optic as its channels appear, the injection events."""

    def __init__(self, rec: Any, rate_hz: float) -> None:  # noqa: ANN401 - rr.RecordingStream
        self.rec, self.rate_hz = rec, rate_hz
        self.stats = LiveStats()
        self.decimators: dict[str, Decimator] = {}
        self.pending: dict[str, list[Decimated]] = {}
        self.optics: list[str] = []

    def data(self, data: bytes, select: Callable[[str], bool]) -> None:
        """A published block: decoded, and kept if its channel is selected."""
        try:
            block = SampleBlock.decode(data)
        except Exception:  # noqa: BLE001 - a foreign payload under twin/**
            self.stats.dropped += 1
            return
        self.stats.blocks += 1
        if select(block.channel):
            self.block(block)

    def block(self, block: SampleBlock) -> None:
        """Decimate a block of a selected channel; a new channel gets its series and tab."""
        name = block.channel
        if name not in self.decimators:
            self.decimators[name] = Decimator(block.rate_hz, self.rate_hz)
            self.pending[name] = []
            label = f"{name} [{block.unit}]" if block.unit else name
            self.rec.log(entity_path(name), rr.SeriesLines(names=label), static=True)
            parsed = parse_dof_channel(name)
            if parsed and parsed[1] not in self.optics:
                self.optics.append(parsed[1])
                self.rec.send_blueprint(blueprint(self.optics), make_active=True,
                                        make_default=True)
        out = self.decimators[name].feed(block.gps_start, block.samples)
        if out.values.size:
            self.pending[name].append(out)

    def event(self, data: bytes) -> None:
        """An injection event, as a line of the events log at its GPS time."""
        try:
            event = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            self.stats.dropped += 1
            return
        gps = event_gps(event) if isinstance(event, dict) else None
        if gps is None:
            return
        text, level = event_text(event)
        self.rec.send_columns(EVENTS_ENTITY,
                              indexes=gps_columns(np.array([int(round(gps * NS))])),
                              columns=rr.TextLog.columns(text=[text], level=[level]))
        self.stats.events += 1

    def flush(self) -> None:
        """Send what each channel holds."""
        for name, parts in self.pending.items():
            if not parts:
                continue
            gps_ns = np.concatenate([p.gps_ns for p in parts])
            values = np.concatenate([p.values for p in parts])
            path = entity_path(name)
            self.rec.send_columns(path, indexes=gps_columns(gps_ns),
                                  columns=rr.Scalars.columns(scalars=values))
            self.stats.rows[path] = self.stats.rows.get(path, 0) + values.size
            self.pending[name] = []
