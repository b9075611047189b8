"""Read twind sessions: MCAP files (one, or a rotated set) or the live bus.

:func:`read_session` returns every channel's samples joined across blocks and files, with
the sequence numbers and any gaps; :func:`getdata` gives a GPS span of some channels, from a
recording or from the bus, as gwpy ``TimeSeriesDict`` when gwpy is installed.

Files are read with mcap's sequential :class:`~mcap.stream_reader.StreamReader`, never
through the summary at the end, so that a file whose writer was killed (no summary, no
footer, perhaps half a chunk at the end) gives everything up to its last complete chunk,
with a :class:`TruncatedRecordingWarning`. A damaged chunk inside a complete file is
skipped by the file's chunk index, and the rest read, with a
:class:`DamagedRecordingWarning` giving the time span lost.
"""

from __future__ import annotations

import json
import math
import queue
import struct
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.reader import SeekingReader
from mcap.records import Channel as McapChannel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import MCAP0_MAGIC
from numpy.typing import NDArray

from twind.bus.keys import data_key
from twind.bus.session import DEFAULT_ENDPOINT, ENDPOINT, zenoh_config, zenoh_message
from twind.errors import TwindError, TwindWarning
from twind.recording.writer import (
    BLOCK_SCHEMA,
    CONFIG_METADATA,
    CONFIG_TOPIC,
    EVENTS_TOPIC,
    TOPIC_ROOT,
    BlockHeader,
    scan_block,
)
from twind.timeutil import now_gps, unix_ns_to_gps


class RecordingError(TwindError):
    """A recording cannot be read, or does not hold what was asked of it."""


class TruncatedRecordingWarning(TwindWarning):
    """A recording ends without its summary: its writer was killed or the disk filled."""


class DamagedRecordingWarning(TwindWarning):
    """A chunk inside a complete recording cannot be read; the rest is read by its index."""


class GapWarning(TwindWarning):
    """Blocks of a channel are missing (sequence numbers or GPS times jump)."""


# --- files ---------------------------------------------------------------------------------


def rotated_name(out: str | Path, index: int) -> Path:
    """``run-0001.mcap`` for ``("run.mcap", 1)``: the name of a rotated recording's file."""
    out = Path(out)
    return out.with_name(f"{out.stem}-{index:04d}{out.suffix or '.mcap'}")


def session_files(path_or_paths: str | Path | Iterable[str | Path]) -> list[Path]:
    """The files of a session, in order.

    Parameters
    ----------
    path_or_paths : path or iterable of paths
        A file; or the name a rotated recording was given (``run.mcap`` when the files are
        ``run-0001.mcap``, ``run-0002.mcap``, ...); or a list of files, read in that order.

    Returns
    -------
    list of Path

    Raises
    ------
    RecordingError
        If a file does not exist.
    """
    if isinstance(path_or_paths, str | Path):
        path = Path(path_or_paths)
        if path.is_file():
            return [path]
        pattern = f"{path.stem}-[0-9][0-9][0-9][0-9]{path.suffix or '.mcap'}"
        found = sorted(path.parent.glob(pattern))
        if found:
            return found
        msg = f"{path}: no such recording (nor rotated files {rotated_name(path, 1).name}, ...)"
        raise RecordingError(msg)
    paths = [Path(p) for p in path_or_paths]
    if not paths:
        msg = "no recording given"
        raise RecordingError(msg)
    files: list[Path] = []
    for p in paths:
        files.extend(session_files(p))
    return files


@dataclass(frozen=True)
class RawMessage:
    """One message of a recording, as stored."""

    topic: str
    schema_name: str
    message_encoding: str
    log_time: int
    sequence: int
    data: bytes
    file: Path
    schema_encoding: str = ""
    schema_data: bytes = b""


def require_header(path: Path, size: int) -> None:
    """Refuse an empty file, or one too short for the MCAP magic that does not begin it: not
    a recording (a file cut inside the magic is a recording killed at once, read as cut)."""
    if size == 0:
        msg = (f"{path}: not an MCAP file (empty); give a recording twind record or twind "
               "serve --record wrote")
        raise RecordingError(msg)
    if size < len(MCAP0_MAGIC):
        with open(path, "rb") as fh:
            if not MCAP0_MAGIC.startswith(fh.read()):
                msg = f"{path}: not an MCAP file ({size} bytes, no MCAP magic)"
                raise RecordingError(msg)


def iter_raw_messages(path: str | Path, problems: list[str] | None = None,
                      topics: Callable[[str], bool] | None = None,
                      metadata: dict[str, dict[str, str]] | None = None,
                      ) -> Iterator[RawMessage]:
    """Every message of one MCAP file in file order, up to its last complete chunk.

    Parameters
    ----------
    path : str or Path
    problems : list of str, optional
        Receives a description of a truncation (a warning is issued too).
    topics : callable, optional
        ``topics(topic)`` is true for the topics wanted; default all.
    metadata : dict, optional
        Receives the file's Metadata records by name.

    Yields
    ------
    RawMessage

    Raises
    ------
    RecordingError
        If the file is not an MCAP file at all, or refers to a channel it never defined.
    """
    path = Path(path)
    size = path.stat().st_size
    require_header(path, size)
    schemas: dict[int, Schema] = {}
    channels: dict[int, McapChannel] = {}
    chunks = 0
    data_end = footer = False
    with open(path, "rb") as fh:
        reader = StreamReader(fh, emit_chunks=True, validate_crcs=True,
                              record_size_limit=size)

        def handle(record: Any) -> Iterator[RawMessage]:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, McapChannel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None:
                    msg = f"{path}: message on channel {record.channel_id}, never defined"
                    raise RecordingError(msg)
                if topics is None or topics(channel.topic):
                    schema = schemas.get(channel.schema_id)
                    yield RawMessage(channel.topic, schema.name if schema else "",
                                     channel.message_encoding, record.log_time,
                                     record.sequence, record.data, path,
                                     schema.encoding if schema else "",
                                     schema.data if schema else b"")
            elif isinstance(record, Metadata) and metadata is not None:
                metadata[record.name] = dict(record.metadata)

        read_to = 0  # the end of the last chunk read whole
        try:
            for record in reader.records:
                if isinstance(record, Chunk):
                    # a chunk is decoded whole (and its CRC checked) before any of its
                    # messages is used: a chunk cut by a SIGKILL contributes nothing
                    inner = breakup_chunk(record, validate_crc=True)
                    chunks += 1
                    read_to = fh.tell()
                    for rec in inner:
                        yield from handle(rec)
                elif isinstance(record, DataEnd):
                    data_end = True
                elif isinstance(record, Footer):
                    footer = True
                elif not data_end:  # the summary repeats schemas and channels: skip it
                    yield from handle(record)
        except InvalidMagic as err:
            if fh.tell() <= 8 and size >= 8:
                msg = f"{path}: not an MCAP file ({err})"
                raise RecordingError(msg) from None
            footer = False
            reason = str(err)
        except (EndOfFile, McapError, ValueError, struct.error, zstandard.ZstdError) as err:
            # ValueError covers mcap's CRCValidationError and a short chunk's decompression;
            # an error after the footer means the closing magic is cut: not complete either
            footer = False
            reason = truncation_reason(err, size)
            summary = None if data_end else indexed_summary(fh)
            if summary is not None:  # damage inside a complete file: on by its index
                schemas.update(summary.schemas)
                channels.update(summary.channels)
                for chunk in indexed_chunks(fh, summary, read_to, path, problems):
                    for rec in chunk:
                        yield from handle(rec)
                return
        else:
            reason = ""
    if not footer:
        report_truncation(path, data_end, chunks, size, reason, problems, stacklevel=4)


# --- sessions ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Gap:
    """Missing data in one channel: the blocks between two recorded ones.

    Attributes
    ----------
    channel : str
    after_sequence, before_sequence : int
        Sequence numbers of the recorded blocks either side.
    gps_start, gps_end : float
        The span missing (GPS s): end of the block before, start of the block after.
    n_samples : int
        Samples missing; filled with NaN in :attr:`Channel.samples`.
    """

    channel: str
    after_sequence: int
    before_sequence: int
    gps_start: float
    gps_end: float
    n_samples: int

    @property
    def restarted(self) -> bool:
        """Whether the twin restarted in the gap: its numbering began again."""
        return self.before_sequence <= self.after_sequence

    @property
    def missing_blocks(self) -> int:
        """Blocks missing by the sequence numbers (0 across a restart, whose numbers say
        nothing of it: :attr:`n_samples` does)."""
        return 0 if self.restarted else self.before_sequence - self.after_sequence - 1

    def __str__(self) -> str:
        what = (f"the twin restarted between sequence {self.after_sequence} and "
                f"{self.before_sequence}" if self.restarted else
                f"{self.missing_blocks} block(s) missing between sequence "
                f"{self.after_sequence} and {self.before_sequence}")
        return (f"{self.channel}: {what}, GPS {self.gps_start:.6f} to {self.gps_end:.6f} "
                f"({self.n_samples} samples, NaN-filled)")


@dataclass
class Channel:
    """One channel of a session.

    Attributes
    ----------
    name : str
        ``C1:SUS-ETMX_SUSPOS_IN1``.
    unit : str
    rate : float
        Sample rate (Hz).
    t0 : float
        GPS time of the first sample (s).
    samples : ndarray of float64
        All blocks joined; the samples of missing blocks (:attr:`gaps`) are NaN, so that
        sample ``i`` is always at ``t0 + i / rate``.
    sequences : ndarray of int64
        Sequence number of every block recorded, in order (consecutive when nothing is lost).
    gps_starts : ndarray of float64
        GPS start of every block recorded.
    gaps : list of Gap
    """

    name: str
    unit: str
    rate: float
    t0: float
    samples: NDArray[np.float64]
    sequences: NDArray[np.int64]
    gps_starts: NDArray[np.float64]
    gaps: list[Gap] = field(default_factory=list)

    @property
    def dt(self) -> float:
        """Sample period (s)."""
        return 1.0 / self.rate

    @property
    def duration(self) -> float:
        """Seconds covered, gaps included."""
        return len(self.samples) / self.rate

    @property
    def t_end(self) -> float:
        """GPS time just after the last sample."""
        return self.t0 + self.duration

    def times(self) -> NDArray[np.float64]:
        """GPS time of every sample."""
        return self.t0 + np.arange(len(self.samples)) / self.rate


@dataclass
class Session:
    """A recording read back.

    Attributes
    ----------
    files : list of Path
    channels : dict of str to Channel
        By channel name, in the order first recorded.
    events : list of dict
        Injection events (``twin/@events``), in recorded order.
    configs : list of dict
        Configuration snapshot of every file (``twin/@config`` or metadata ``twind.config``).
    complete : bool
        Whether every file was read whole (each ends with its summary and footer, and no
        chunk was damaged).
    problems : list of str
        Truncations, damaged chunks and gaps, as also issued as warnings.
    """

    files: list[Path]
    channels: dict[str, Channel]
    events: list[dict[str, Any]]
    configs: list[dict[str, Any]]
    complete: bool
    problems: list[str]

    @property
    def config(self) -> dict[str, Any] | None:
        """The configuration snapshot at the start of the session."""
        return self.configs[0] if self.configs else None

    @property
    def gaps(self) -> list[Gap]:
        """Gaps of every channel."""
        return [g for ch in self.channels.values() for g in ch.gaps]

    def __getitem__(self, name: str) -> Channel:
        try:
            return self.channels[name]
        except KeyError:
            msg = f"{name} is not in the recording; it holds {_some(self.channels)}"
            raise RecordingError(msg) from None

    def __contains__(self, name: object) -> bool:
        return name in self.channels

    def __iter__(self) -> Iterator[str]:
        return iter(self.channels)

    def __len__(self) -> int:
        return len(self.channels)


def _some(names: Iterable[str], n: int = 4) -> str:
    names = list(names)
    if not names:
        return "no channels"
    more = f" and {len(names) - n} more" if len(names) > n else ""
    return ", ".join(names[:n]) + more


@dataclass
class _Block:
    sequence: int
    gps_start: float
    rate: float
    unit: str
    samples: NDArray[np.float64]


def _block_samples(data: bytes, header: BlockHeader) -> NDArray[np.float64]:
    # a view on the message bytes: no copy until the channel is joined
    if len(header.runs) == 1:
        offset, n = header.runs[0]
        return np.frombuffer(data, dtype="<f8", count=n // 8, offset=offset)
    if not header.runs:
        return np.empty(0)
    return np.concatenate([np.frombuffer(data, dtype="<f8", count=n // 8, offset=o)
                           for o, n in header.runs])


def _join(name: str, blocks: list[_Block]) -> Channel:
    """One channel from its blocks in recorded order: NaN in gaps, errors on overlaps."""
    rate = blocks[0].rate
    if not rate > 0:
        msg = f"{name}: block {blocks[0].sequence} has sample rate {rate}"
        raise RecordingError(msg)
    pieces: list[NDArray[np.float64]] = []
    gaps: list[Gap] = []
    kept: list[_Block] = []
    prev: _Block | None = None
    for b in blocks:
        if b.rate != rate:
            msg = (f"{name}: the sample rate changes from {rate:g} to {b.rate:g} Hz at "
                   f"block {b.sequence}; read the parts separately")
            raise RecordingError(msg)
        if prev is not None:
            end = prev.gps_start + len(prev.samples) / rate
            offset = (b.gps_start - end) * rate  # in samples
            k = round(offset)
            if b.sequence == prev.sequence and b.gps_start == prev.gps_start and \
                    np.array_equal(b.samples, prev.samples, equal_nan=True):
                continue  # the same block recorded twice (e.g. two overlapping keyexprs)
            if abs(offset - k) > 0.05 or k < 0:
                msg = (f"{name}: block {b.sequence} starts at GPS {b.gps_start:.6f}, "
                       f"{offset:+.3f} samples from the end of block {prev.sequence} "
                       f"(GPS {end:.6f}): overlapping or misaligned data, e.g. two runs of "
                       f"a twin in one recording; read the files separately")
                raise RecordingError(msg)
            if k > 0 or b.sequence != prev.sequence + 1:
                gaps.append(Gap(name, prev.sequence, b.sequence, end, b.gps_start, k))
                if k:
                    pieces.append(np.full(k, np.nan))
        pieces.append(b.samples)
        kept.append(b)
        prev = b
    samples = np.concatenate(pieces) if pieces else np.empty(0)
    return Channel(name, kept[0].unit, rate, kept[0].gps_start,
                   np.asarray(samples, dtype=np.float64),
                   np.array([b.sequence for b in kept], dtype=np.int64),
                   np.array([b.gps_start for b in kept]), gaps)


def scan_sample_block(data: bytes, topic: str) -> tuple[BlockHeader, str]:
    """A block's header and channel name (its topic's, when the block names none)."""
    try:
        header = scan_block(data)
    except ValueError as err:
        msg = f"{topic}: not a twind.v1.SampleBlock ({err})"
        raise RecordingError(msg) from None
    return header, header.channel or topic.removeprefix(f"{TOPIC_ROOT}/")


class _Assembler:
    """Blocks of many channels, by name, in arrival order; joined on demand."""

    def __init__(self, wanted: set[str] | None = None) -> None:
        self.blocks: dict[str, list[_Block]] = {}
        self.wanted = wanted

    def add(self, data: bytes, topic: str = "") -> BlockHeader | None:
        header, name = scan_sample_block(data, topic)
        if self.wanted is not None and name not in self.wanted:
            return None
        self.blocks.setdefault(name, []).append(
            _Block(header.sequence, header.gps_start, header.rate_hz, header.unit,
                   _block_samples(data, header)))
        return header

    def channels(self) -> dict[str, Channel]:
        return {name: _join(name, blocks) for name, blocks in self.blocks.items() if blocks}


def _warn_gaps(channels: dict[str, Channel], problems: list[str]) -> None:
    gaps = [g for ch in channels.values() for g in ch.gaps]
    if not gaps:
        return
    lines = [str(g) for g in gaps[:5]]
    more = f"; and {len(gaps) - 5} more" if len(gaps) > 5 else ""
    text = (f"{len(gaps)} gap(s) in {len({g.channel for g in gaps})} channel(s): "
            + "; ".join(lines) + more)
    problems.append(text)
    warnings.warn(text, GapWarning, stacklevel=3)


def read_session(path_or_paths: str | Path | Iterable[str | Path],
                 channels: Iterable[str] | None = None) -> Session:
    """Read a recording: one MCAP file, a rotated set, or a list of files.

    Parameters
    ----------
    path_or_paths : path or iterable of paths
        See :func:`session_files`.
    channels : iterable of str, optional
        Read only these channels (faster), in this order; default all, in the order first
        recorded.

    Returns
    -------
    Session

    Raises
    ------
    RecordingError
        If a file is missing or not MCAP, a block is not a SampleBlock, a channel's sample
        rate changes, or two blocks of a channel overlap.

    Warns
    -----
    TruncatedRecordingWarning
        For a file that ends without its summary; everything up to its last complete chunk
        is returned.
    GapWarning
        For missing blocks, which are NaN in the samples and listed in ``Channel.gaps``.
    """
    files = session_files(path_or_paths)
    order = list(dict.fromkeys(channels)) if channels is not None else None
    wanted = set(order) if order is not None else None
    wanted_topics = None if wanted is None else {f"{TOPIC_ROOT}/{c}" for c in wanted}

    def keep(topic: str) -> bool:
        return wanted_topics is None or topic in wanted_topics or topic.startswith(
            f"{TOPIC_ROOT}/@")

    problems: list[str] = []
    assembler = _Assembler(wanted)
    events: list[dict[str, Any]] = []
    configs: list[dict[str, Any]] = []
    for path in files:
        metadata: dict[str, dict[str, str]] = {}
        config_seen = False
        for m in iter_raw_messages(path, problems, keep, metadata):
            if m.topic == EVENTS_TOPIC:
                events.append(_json(m))
            elif m.topic == CONFIG_TOPIC:
                configs.append(_json(m))
                config_seen = True
            elif m.schema_name == BLOCK_SCHEMA and m.message_encoding == "protobuf":
                assembler.add(m.data, m.topic)
        if not config_seen and CONFIG_METADATA in metadata:
            configs.append(json.loads(metadata[CONFIG_METADATA].get("json", "{}")))
    joined = assembler.channels()
    if wanted is not None:
        missing = sorted(wanted - set(joined))
        if missing:
            msg = (f"{_some(missing)} not in {files[0]}"
                   f"{f' (and {len(files) - 1} more files)' if len(files) > 1 else ''}")
            raise RecordingError(msg)
        joined = {name: joined[name] for name in order}  # in the order asked for
    complete = not problems
    _warn_gaps(joined, problems)
    return Session(files, joined, events, configs, complete, problems)


def _json(m: RawMessage) -> dict[str, Any]:
    try:
        return json.loads(m.data)
    except ValueError as err:
        msg = f"{m.file}: {m.topic}: a message is not JSON ({err})"
        raise RecordingError(msg) from None


class JsonDecoderFactory(McapDecoderFactory):
    """An mcap ``DecoderFactory`` for the JSON topics (``twin/@events``, ``twin/@config``).

    ``make_reader(fh, decoder_factories=[mcap_protobuf.decoder.DecoderFactory(),
    JsonDecoderFactory()]).iter_decoded_messages()`` then decodes every topic of a session.
    """

    def decoder_for(self, message_encoding: str, schema: Any) -> Callable[[bytes], Any] | None:
        """``json.loads`` for message encoding ``json``, else None."""
        return json.loads if message_encoding == "json" else None


# --- getdata -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Series:
    """A time series, when gwpy is not installed (gwpy's ``TimeSeries`` otherwise).

    Attributes
    ----------
    value : ndarray of float64
    t0 : float
        GPS time of the first sample (s).
    sample_rate : float
        Hz.
    name : str
    unit : str
    """

    value: NDArray[np.float64]
    t0: float
    sample_rate: float
    name: str = ""
    unit: str = ""

    @property
    def dt(self) -> float:
        """Sample period (s)."""
        return 1.0 / self.sample_rate

    @property
    def duration(self) -> float:
        """Seconds covered."""
        return len(self.value) / self.sample_rate

    @property
    def times(self) -> NDArray[np.float64]:
        """GPS time of every sample."""
        return self.t0 + np.arange(len(self.value)) / self.sample_rate

    def __len__(self) -> int:
        return len(self.value)

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> NDArray:
        """The samples, so that numpy takes a series as an array (as gwpy's)."""
        return np.array(self.value, dtype=dtype, copy=copy)

    def __getitem__(self, index: Any) -> Any:  # noqa: ANN401 - a sample or an array
        return self.value[index]


def _slice(ch: Channel, start: float, duration: float) -> tuple[NDArray[np.float64], float]:
    i0 = round((start - ch.t0) * ch.rate)
    n = round(duration * ch.rate)
    if i0 < 0 or i0 + n > len(ch.samples) or n < 1:
        msg = (f"{ch.name}: asked for GPS {start:.6f} to {start + duration:.6f}, the data "
               f"cover GPS {ch.t0:.6f} to {ch.t_end:.6f}")
        raise RecordingError(msg)
    return ch.samples[i0:i0 + n], ch.t0 + i0 / ch.rate


def _as_series(parts: dict[str, tuple[NDArray[np.float64], float, Channel]]) -> Any:
    """gwpy series when gwpy is installed, else :class:`Series`."""
    try:  # gwpy is optional and slow to import: only when a series is returned
        from gwpy.timeseries import TimeSeries, TimeSeriesDict
    except ImportError:
        return {name: Series(np.array(x), t0, ch.rate, name, ch.unit)
                for name, (x, t0, ch) in parts.items()}
    out = TimeSeriesDict()
    for name, (x, t0, ch) in parts.items():
        try:
            out[name] = TimeSeries(np.array(x), t0=t0, sample_rate=ch.rate, name=name,
                                   channel=name, unit=ch.unit or None)
        except ValueError:  # a unit astropy does not know
            out[name] = TimeSeries(np.array(x), t0=t0, sample_rate=ch.rate, name=name,
                                   channel=name)
    return out


def getdata(channels: str | Sequence[str], duration: float | None, start: float | None = None,
            source: Any = None, timeout: float | None = None) -> Any:
    """A GPS span of some channels, from a recording or from the bus.

    Parameters
    ----------
    channels : str or sequence of str
        Channel names, e.g. ``"C1:SUS-ETMX_SUSPOS_IN1"``.
    duration : float or None
        Seconds; None (a recording only): up to the end of the span every channel covers.
    start : float, optional
        GPS start. Default: the first time every channel has data (a recording's start, or
        the first block received from the bus).
    source : path, list of paths, endpoint or zenoh.Config
        A recording (see :func:`session_files`), or the bus to subscribe to for `duration`
        seconds: a Zenoh endpoint such as ``"tcp/127.0.0.1:7447"`` (the default) or a
        configuration.
    timeout : float, optional
        Bus only: wall-clock seconds to wait for the data; default ``2 * duration + 10`` plus
        the wait until `start`.

    Returns
    -------
    gwpy.timeseries.TimeSeriesDict, or dict of str to Series
        By channel name, each ``round(duration * rate)`` samples from the sample nearest to
        `start`; ``t0`` is that sample's GPS time. Samples in gaps are NaN.

    Raises
    ------
    RecordingError
        If a channel is not there, or the span is not covered.
    """
    names = [channels] if isinstance(channels, str) else list(channels)
    if not names:
        msg = "getdata: no channels given"
        raise RecordingError(msg)
    if duration is not None and not (duration > 0 and math.isfinite(duration)):
        msg = f"getdata: duration must be positive and finite, got {duration}"
        raise RecordingError(msg)


    if source is None:
        source = DEFAULT_ENDPOINT
    if isinstance(source, str) and ENDPOINT.match(source) and not Path(source).exists():
        source = zenoh_config(connect=[source], mode="client")
    if isinstance(source, zenoh.Config):
        if duration is None:
            msg = "getdata: reading from the bus needs a duration"
            raise RecordingError(msg)
        joined = _collect_from_bus(source, names, duration, start, timeout)
    else:
        joined = read_session(source, names).channels
    if start is None:
        start = max(joined[n].t0 for n in names)
    if duration is None:
        duration = min(joined[n].t_end for n in names) - start
    parts = {}
    for n in names:
        x, t0 = _slice(joined[n], start, duration)
        parts[n] = (x, t0, joined[n])
    return _as_series(parts)


def as_array(data: Any) -> tuple[NDArray[np.float64], float]:
    """The channels of a :func:`getdata` result as the rows of one array (in its order), and
    their common sample rate (Hz).

    Raises
    ------
    RecordingError
        If the channels' rates or lengths differ.
    """
    series = list(data.values())
    rates = {float(getattr(s.sample_rate, "value", s.sample_rate)) for s in series}
    if len(rates) != 1 or len({len(s) for s in series}) != 1:
        msg = (f"{', '.join(data)}: rates {sorted(rates)} Hz and lengths differ; resample "
               "them to one rate first")
        raise RecordingError(msg)
    return np.array([np.asarray(s.value, dtype=float) for s in series]), rates.pop()


def _collect_from_bus(conf: Any, names: list[str], duration: float, start: float | None,
                      timeout: float | None) -> dict[str, Channel]:
    """Subscribe to `names` until each covers the span asked for, then join the blocks."""

    if timeout is None:
        timeout = 2 * duration + 10 + (max(0.0, start - now_gps()) if start else 0.0)
    inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
    assembler = _Assembler(set(names))
    # first and last GPS covered per channel, updated as blocks arrive
    first: dict[str, float] = {}
    last: dict[str, float] = {}
    deadline = time.monotonic() + timeout
    try:
        opened = zenoh.open(conf)
    except zenoh.ZError as err:
        msg = (f"getdata: cannot reach the bus at {conf.get_json('connect/endpoints')} "
               f"({zenoh_message(err)}): is a twin (twind serve) running there?")
        raise RecordingError(msg) from None
    with opened as session:
        subs = [session.declare_subscriber(
            data_key(n), lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes())))
            for n in names]
        try:
            while True:
                try:
                    key, data = inbox.get(timeout=0.1)
                except queue.Empty:
                    key = ""
                if key:
                    header = assembler.add(data, key)
                    if header is not None:
                        name = header.channel or key.removeprefix(f"{TOPIC_ROOT}/")
                        first.setdefault(name, header.gps_start)
                        last[name] = header.gps_start + header.n_samples / header.rate_hz
                if len(last) == len(names):
                    begin = start if start is not None else max(first.values())
                    early = [n for n in names if first[n] > begin + 1e-9]
                    if early:
                        msg = (f"the bus has no history: {early[0]} starts at GPS "
                               f"{first[early[0]]:.6f}, after the start asked for "
                               f"({begin:.6f}); record with 'twind record' and read the file")
                        raise RecordingError(msg)
                    if min(last.values()) >= begin + duration - 1e-9:
                        break
                if time.monotonic() > deadline:
                    silent = [n for n in names if n not in last]
                    what = (f"no data on {data_key(silent[0])}" if silent else
                            "not enough data")
                    msg = (f"getdata: {what} within {timeout:g} s "
                           f"(is a twin publishing {_some(silent or names)}?)")
                    raise RecordingError(msg)
        finally:
            for s in subs:
                s.undeclare()
    return assembler.channels()


def indexed_summary(fh: Any) -> Any:  # noqa: ANN401 - mcap.records.Summary or None
    """The summary of a file whose footer and summary section are intact, else None."""
    try:
        fh.seek(0)
        summary = SeekingReader(fh, validate_crcs=True).get_summary()
    except Exception:  # noqa: BLE001 - any failure: no usable index
        return None
    return summary if summary is not None and summary.chunk_indexes else None


def indexed_chunks(fh: Any, summary: Any, offset: int, path: Path,  # noqa: ANN401
                  problems: list[str] | None) -> Iterator[list[Any]]:
    """The records of each indexed chunk from `offset` on; a damaged one is skipped, and
    the time span it held reported (a warning, and in `problems`)."""
    for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        if index.chunk_start_offset < offset:
            continue
        try:
            fh.seek(index.chunk_start_offset + 1 + 8)  # past the opcode and the length
            records = list(breakup_chunk(Chunk.read(ReadDataStream(fh)), validate_crc=True))
        except (ValueError, struct.error, zstandard.ZstdError, EOFError) as err:
            span = (f"GPS {unix_ns_to_gps(index.message_start_time):.3f} to "
                    f"{unix_ns_to_gps(index.message_end_time):.3f}")
            text = (f"{path}: the chunk at byte {index.chunk_start_offset} is damaged "
                    f"({type(err).__name__}: {err}); its messages, {span}, are lost, the "
                    "rest is read by the file's index")
            if problems is not None:
                problems.append(text)
            warnings.warn(text, DamagedRecordingWarning, stacklevel=5)
            continue
        yield records


def truncation_reason(err: Exception, size: int) -> str:
    """Why reading stopped early, for the truncation report."""
    if size < 8:
        return "shorter than the MCAP magic"
    return f"{type(err).__name__}: {err}" if str(err) else type(err).__name__


def report_truncation(path: Path, data_end: bool, chunks: int, size: int, reason: str,
                      problems: list[str] | None, stacklevel: int) -> None:
    """Warn (and note in `problems`) that `path` stops without its summary and footer."""
    where = "after its data" if data_end else f"after {chunks} complete chunk(s)"
    text = (f"{path}: the recording ends {where} without its summary and footer "
            f"({size} bytes; the writer was killed or the disk filled?); read up to there"
            + (f" [{reason}]" if reason else ""))
    if problems is not None:
        problems.append(text)
    warnings.warn(text, TruncatedRecordingWarning, stacklevel=stacklevel)
