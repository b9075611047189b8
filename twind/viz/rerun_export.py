"""A recorded twind session (MCAP) as a Rerun recording (.rrd).

What the .rrd holds, and how the Rerun viewer shows it:

- ``sus/<OPTIC>/<DOF>/<POINT>`` (``sus/ETMX/POS/IN1``) and ``sus/<OPTIC>/OSEM/<OSEM>``: every
  channel decimated to about `decimate_to_hz` (Chebyshev anti-aliasing filter, times corrected
  for its group delay; see :mod:`twind.viz.decimate`) as ``Scalars``, named after the LIGO
  channel and its unit. Two timelines index them: ``gps`` (GPS seconds, a duration timeline)
  and ``utc`` (the same instants as wall-clock timestamps). One time-series view per optic and
  DOF overlays EXC, IN1, IN2 and OUT.
- ``events``: injection events of the session (topic ``twin/@events``: start, end, stop,
  refused) as ``TextLog`` rows at their GPS time; clicking a row moves the time cursor there.
- ``bode/<OPTIC>/<DOF>/<EXCITATION>/IN1_EXC/{magnitude_db,phase_deg,coherence}`` (and
  ``IN2_EXC``): for every span in which an EXC channel was driven, the measured transfer
  functions IN1/EXC and IN2/EXC (Welch averages of the full-rate samples over the span,
  Hann window, power-of-two segments, at least 8 of them). They are indexed by the
  ``frequency_hz`` timeline, a *duration* timeline whose "seconds" are hertz: select
  ``frequency_hz`` in the time panel and the Bode views fill, with frequency along the x axis
  (labelled in seconds: read s as Hz; linear, Rerun has no logarithmic time axis), magnitude in
  dB, phase in degrees and coherence 0 to 1; the series views are empty on that timeline, and
  the Bode views on ``gps``. Only bins where the excitation carries power are kept (within
  40 dB of its peak): a sine gives a handful of points around its frequency, a broadband
  noise or a sweep a curve.

The file is read once, block by block, so memory stays bounded by the decimated output and
by the full-rate samples of excited spans (at most ``MAX_SPAN_S`` of each).
"""

from __future__ import annotations

import json
import math
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rerun as rr
from numpy.typing import NDArray

from twind.bus.codec import SampleBlock
from twind.channels import dof_channel, parse_dof_channel
from twind.errors import TwindError
from twind.recording.mcapfile import iter_raw_messages
from twind.timeutil import GPS_EPOCH_UNIX, LEAP_SECONDS
from twind.viz.bode import measure
from twind.viz.decimate import NS, Decimated, Decimator
from twind.viz.entities import blueprint, entity_path, matcher

GPS_TIMELINE = "gps"
UTC_TIMELINE = "utc"
FREQ_TIMELINE = "frequency_hz"
EVENTS_ENTITY = "events"
MAX_SPAN_S = 600.0  # full-rate samples kept per excited span and channel (3 channels a span)
GAP_S = 1.0  # an EXC silent for longer than this ends an excited span
FLUSH_SAMPLES = 16384  # decimated samples per channel held before they are sent
GPS_TO_UNIX_NS = (GPS_EPOCH_UNIX - LEAP_SECONDS) * NS


def gps_columns(gps_ns: NDArray[np.int64]) -> list:
    """The ``gps`` (duration) and ``utc`` (timestamp) index columns of GPS instants in ns."""

    gps_ns = np.asarray(gps_ns, dtype=np.int64)
    return [rr.TimeColumn(GPS_TIMELINE, duration=gps_ns.astype("timedelta64[ns]")),
            rr.TimeColumn(UTC_TIMELINE,
                          timestamp=(gps_ns + GPS_TO_UNIX_NS).astype("datetime64[ns]"))]


def is_events_topic(topic: str) -> bool:
    """``twin/@events`` (what recorders write) or ``twin/@/C1/events`` (the bus key)."""
    return "@" in topic and topic.rstrip("/").endswith("events")


def event_text(event: dict) -> tuple[str, str]:
    """A one-line description of an injection event and its Rerun log level."""
    kind = str(event.get("event", "event"))
    req = event.get("request") if isinstance(event.get("request"), dict) else {}
    what = []
    for key, unit in (("freq", " Hz"), ("f_stop", " Hz"), ("amp", ""), ("duration", " s")):
        if req.get(key) is not None:
            what.append(f"{key} {req[key]}{unit}")
    label = event.get("id", "")
    if kind == "refused":
        return f"refused on {req.get('channel', '?')}: {event.get('reason', '')}", "WARN"
    text = f"{kind} {label}: {req.get('waveform', '')} on {event.get('channel', '?')}"
    if what:
        text += f" ({', '.join(what)})"
    return text, "INFO"


def event_gps(event: dict) -> float | None:
    """When an event happened: an excitation's start at its first sample, others when sent."""
    for key in (("start_gps", "gps") if event.get("event") == "start" else ("gps",)):
        value = event.get(key)
        if isinstance(value, (int, float)) and math.isfinite(value):
            return float(value)
    return None


# ------------------------------------------------------------------------------- excited spans
@dataclass
class _Span:
    """The blocks of one excited DOF while its EXC is driven."""

    blocks: dict[int, dict[str, SampleBlock]] = field(default_factory=dict)
    first_ns: int | None = None  # first non-zero EXC sample
    last_ns: int | None = None  # one sample past the last non-zero EXC sample
    truncated: bool = False


class SpanTracker:
    """Finds the spans where a DOF's EXC is non-zero and keeps EXC, IN1 and IN2 over them.

    Blocks of one instant may come in any order (EXC after IN1), so a few recent blocks of
    every point are kept while nothing is excited.
    """

    POINTS = ("EXC", "IN1", "IN2")

    def __init__(self,
                 on_span: Callable[[str, str, str, dict[str, NDArray], float, float, bool], None],
                 lookback: int = 4) -> None:
        self._on_span = on_span
        self._lookback = lookback
        self._recent: dict[tuple[str, str, str], deque[SampleBlock]] = {}
        self._active: dict[tuple[str, str, str], _Span] = {}
        self._rate: dict[tuple[str, str, str], float] = {}

    def feed(self, block: SampleBlock) -> None:
        parsed = parse_dof_channel(block.channel)
        if parsed is None or parsed[3] not in self.POINTS:
            return
        ifo, optic, dof, point = parsed
        key = (ifo, optic, dof)
        self._rate[key] = block.rate_hz
        start_ns = int(round(block.gps_start * NS))
        span = self._active.get(key)
        if point == "EXC":
            nz = np.flatnonzero(block.samples)
            if nz.size:
                first = start_ns + int(round(nz[0] * NS / block.rate_hz))
                last = start_ns + int(round((nz[-1] + 1) * NS / block.rate_hz))
                if span is None:
                    span = self._active[key] = _Span(first_ns=first)
                    for old in self._recent.pop(key, ()):  # the same instants, seen before
                        self._keep(span, old)
                span.last_ns = last
            elif (span is not None and span.last_ns is not None
                  and start_ns - span.last_ns > GAP_S * NS):
                self._close(key)
                span = None
        if span is None:
            recent = self._recent.setdefault(key, deque(maxlen=self._lookback * len(self.POINTS)))
            recent.append(block)
            return
        self._keep(span, block)

    def _keep(self, span: _Span, block: SampleBlock) -> None:
        point = block.channel.rsplit("_", 1)[1]
        start_ns = int(round(block.gps_start * NS))
        if span.first_ns is not None and start_ns - span.first_ns > MAX_SPAN_S * NS:
            span.truncated = True
            return
        span.blocks.setdefault(start_ns, {})[point] = block

    def close_all(self) -> None:
        for key in list(self._active):
            self._close(key)

    def _close(self, key: tuple[str, str, str]) -> None:
        span = self._active.pop(key)
        ifo, optic, dof = key
        rate = self._rate[key]
        if span.first_ns is None or span.last_ns is None:
            return
        starts = []  # instants with all three points, from the one holding the first sample
        for t in sorted(span.blocks):
            pts = span.blocks[t]
            if not all(p in pts for p in self.POINTS):
                if starts:
                    break  # a point is missing: measure over the contiguous part only
                continue
            if t + pts["EXC"].samples.size * NS / rate > span.first_ns:
                starts.append(t)
        if not starts:
            return
        series = {p: np.concatenate([span.blocks[t][p].samples for t in starts])
                  for p in self.POINTS}
        t0 = starts[0]
        a = max(0, int(round((span.first_ns - t0) * rate / NS)))
        b = min(series["EXC"].size, int(round((span.last_ns - t0) * rate / NS)))
        if b - a < 2:
            return
        cut = {p: x[a:b] for p, x in series.items()}
        self._on_span(ifo, optic, dof, cut, t0 / NS + a / rate, rate, span.truncated)


# ------------------------------------------------------------------------------- the export
BLOCK_SCHEMA = "twind.v1.SampleBlock"


def _messages(path: Path) -> Iterator[tuple[str, str, bytes]]:
    """``(topic, kind, data)`` of every message in file order (the order it was written), up
    to the last complete chunk of a cut recording; kind is ``"block"``, ``"event"`` or ``""``
    (anything else, e.g. the ``twin/@config`` snapshot)."""
    for m in iter_raw_messages(path):
        if is_events_topic(m.topic):
            kind = "event"
        elif (m.message_encoding == "protobuf" and m.topic.startswith("twin/")
              and m.schema_name in ("", BLOCK_SCHEMA)):
            kind = "block"
        else:
            kind = ""
        yield m.topic, kind, m.data


class _Exporter:
    def __init__(self, rec, decimate_to_hz: float, select: Callable[[str], bool],  # noqa: ANN001
                 bode: bool) -> None:
        self.rec, self.rate_out, self.select = rec, decimate_to_hz, select
        self.decimators: dict[str, Decimator] = {}
        self.pending: dict[str, list[Decimated]] = {}
        self.pending_n: dict[str, int] = {}
        self.rows: dict[str, int] = {}
        self.events: list[dict] = []
        self.bode_entities: list[str] = []
        self.spans = SpanTracker(self._bode) if bode else None

    def block(self, block: SampleBlock) -> None:
        if self.spans is not None:
            self.spans.feed(block)
        if not self.select(block.channel):
            return

        name = block.channel
        dec = self.decimators.get(name)
        if dec is None:
            dec = self.decimators[name] = Decimator(block.rate_hz, self.rate_out)
            label = f"{name} [{block.unit}]" if block.unit else name
            self.rec.log(entity_path(name), rr.SeriesLines(names=label), static=True)
            self.pending[name], self.pending_n[name], self.rows[name] = [], 0, 0
        out = dec.feed(block.gps_start, block.samples)
        if out.values.size:
            self.pending[name].append(out)
            self.pending_n[name] += out.values.size
            if self.pending_n[name] >= FLUSH_SAMPLES:
                self._flush(name)

    def _flush(self, name: str) -> None:

        parts = self.pending[name]
        if not parts:
            return
        gps_ns = np.concatenate([p.gps_ns for p in parts])
        values = np.concatenate([p.values for p in parts])
        self.rec.send_columns(entity_path(name), indexes=gps_columns(gps_ns),
                              columns=rr.Scalars.columns(scalars=values))
        self.rows[name] += values.size
        self.pending[name], self.pending_n[name] = [], 0

    def event(self, data: bytes) -> None:
        try:
            event = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            return
        if isinstance(event, dict) and event_gps(event) is not None:
            self.events.append(event)

    def _start_event(self, channel: str, start: float, stop: float) -> dict | None:
        """The start event of the excitation that drove `channel` from `start` to `stop`."""
        for ev in self.events:
            if ev.get("event") == "start" and ev.get("channel") == channel and ev.get("id"):
                t = event_gps(ev)
                if t is not None and start - 1.0 <= t <= stop:
                    return ev
        return None

    def _bode(self, ifo: str, optic: str, dof: str, series: dict[str, NDArray], start: float,
              rate: float, truncated: bool) -> None:

        stop = start + series["EXC"].size / rate
        channel = dof_channel(ifo, optic, dof, "EXC")
        event = self._start_event(channel, start, stop)
        label = str(event["id"]) if event else f"gps{start:.0f}"
        request = event.get("request") if event else None
        tone = None
        if isinstance(request, dict) and request.get("waveform") == "sine":
            freq = request.get("freq")
            tone = float(freq) if isinstance(freq, (int, float)) and freq > 0 else None
        tfs = measure(series["EXC"], {"IN1": series["IN1"], "IN2": series["IN2"]}, rate,
                      tone_hz=tone)
        for point, tf in tfs.items():
            if tf.freq_hz.size == 0:
                continue
            base = f"bode/{optic}/{dof}/{label}/{point}_EXC"
            index = [rr.TimeColumn(FREQ_TIMELINE,
                                   duration=np.round(tf.freq_hz * NS).astype("timedelta64[ns]"))]
            for leaf, values, unit in (("magnitude_db", tf.magnitude_db, "dB"),
                                       ("phase_deg", tf.phase_deg, "deg"),
                                       ("coherence", tf.coherence, "")):
                path = f"{base}/{leaf}"
                name = f"{optic} {dof} {point}/EXC {leaf.split('_')[0]}"
                name += f" [{unit}]" if unit else ""
                self.rec.log(path, rr.SeriesLines(names=name), rr.SeriesPoints(names=name),
                             static=True)
                self.rec.send_columns(path, indexes=index,
                                      columns=rr.Scalars.columns(scalars=values))
            self.bode_entities.append(base)
        note = (f"{label}: {optic} {dof} excited from GPS {start:.3f} to {stop:.3f}; "
                f"IN1/EXC and IN2/EXC under bode/{optic}/{dof}/{label}")
        if truncated:
            note += f" (measured over its first {MAX_SPAN_S:g} s)"
        self.rec.send_columns(EVENTS_ENTITY, indexes=gps_columns(np.array([int(round(stop * NS))])),
                              columns=rr.TextLog.columns(text=[note], level=["INFO"]))

    def finish(self) -> None:

        if self.spans is not None:
            self.spans.close_all()
        for name in self.pending:
            self._flush(name)
        timed = sorted(((event_gps(e), e) for e in self.events), key=lambda p: p[0])
        if timed:
            texts, levels = zip(*(event_text(e) for _, e in timed), strict=True)
            gps_ns = np.array([int(round(t * NS)) for t, _ in timed], dtype=np.int64)
            self.rec.send_columns(EVENTS_ENTITY, indexes=gps_columns(gps_ns),
                                  columns=rr.TextLog.columns(text=list(texts), level=list(levels)))


@dataclass(frozen=True)
class ExportSummary:
    """What :func:`mcap_to_rrd` wrote."""

    rrd_path: Path
    series: dict[str, int]  # entity path -> decimated rows
    rate_hz: float
    events: int
    bode: list[str]  # bode/<optic>/<dof>/<excitation>/<IN1|IN2>_EXC entities


def mcap_to_rrd(mcap_path: str | Path, rrd_path: str | Path,
                channels: Iterable[str] | str | None = None,
                decimate_to_hz: float = 256.0, bode: bool = True,
                recording_id: str | None = None) -> ExportSummary:
    """Convert a twind MCAP session into a Rerun .rrd file.

    Parameters
    ----------
    mcap_path : str or Path
        A session written by ``twind simulate --record`` or ``twind serve --record`` (topics
        ``twin/<channel>``: protobuf ``twind.v1.SampleBlock``; ``twin/@events``: JSON).
    rrd_path : str or Path
        The .rrd to write (an existing file is refused).
    channels : str or iterable of str, optional
        Shell-style patterns of the channels to plot (``"C1:SUS-ETMX_*"``, comma-separated or a
        list); all when None. Bode plots are measured whatever the selection.
    decimate_to_hz : float
        Rate of the plotted series (an integer factor below the model rate).
    bode : bool
        Measure and log IN1/EXC and IN2/EXC over every excited span.
    recording_id : str, optional
        Rerun recording id (a new UUID when None).

    Returns
    -------
    ExportSummary
    """

    mcap_path, rrd_path = Path(mcap_path), Path(rrd_path)
    if not mcap_path.is_file():
        msg = f"{mcap_path}: no such file"
        raise TwindError(msg)
    if rrd_path.exists():
        msg = f"{rrd_path} exists; twind does not overwrite files"
        raise TwindError(msg)
    if not (decimate_to_hz > 0 and math.isfinite(decimate_to_hz)):
        msg = f"the decimated rate must be positive, got {decimate_to_hz}"
        raise TwindError(msg)
    rec = rr.RecordingStream("twind", recording_id=recording_id or str(uuid.uuid4()))
    rec.save(rrd_path)
    rec.send_recording_name(mcap_path.name)
    exporter = _Exporter(rec, decimate_to_hz, matcher(channels), bode)
    try:
        for _topic, kind, data in _messages(mcap_path):
            if kind == "event":
                exporter.event(data)
            elif kind == "block":
                exporter.block(SampleBlock.decode(data))
        exporter.finish()
        if not exporter.rows and not exporter.events:
            msg = f"{mcap_path}: no sample block or event to export (a recording cut early?)"
            raise TwindError(msg)
        optics = sorted({p[1] for n in exporter.decimators if (p := parse_dof_channel(n))})
        rec.send_blueprint(blueprint(optics, exporter.bode_entities))
    except BaseException:
        rec.disconnect()
        rrd_path.unlink(missing_ok=True)  # half an export is no export
        raise
    finally:
        rec.flush()
        rec.disconnect()
    rates = {d.rate_out for d in exporter.decimators.values()}
    return ExportSummary(rrd_path, {entity_path(n): r for n, r in exporter.rows.items()},
                         max(rates) if rates else decimate_to_hz, len(exporter.events),
                         exporter.bode_entities)
