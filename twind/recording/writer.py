"""The MCAP layout of a twind session, and the writers of it.

One layout serves ``twind simulate --record``, ``twind record``, the reader, the exporter
and the replayer:

- header profile ``""``, library ``twind/<version>; mcap-python/<version>``;
- one Metadata record ``twind.session`` (format, ifo, writer, creation time), outside chunks;
- schema ``twind.v1.SampleBlock`` (encoding ``protobuf``, data a serialized
  FileDescriptorSet, exactly as mcap-protobuf-support writes it), registered once;
- schemas ``twind.Event`` and ``twind.Config`` (encoding ``jsonschema``);
- the configuration snapshot (JSON) at the start of every file, twice: in a Metadata record
  ``twind.config`` (key ``json``) and, from ``twind record``, as the first message of topic
  ``twin/@config`` (message encoding ``json``). ``twind simulate --record`` writes the
  metadata only, so that its files hold protobuf messages only and decode with
  mcap-protobuf's DecoderFactory alone (JSON messages need a JSON decoder factory:
  :class:`twind.recording.mcapfile.JsonDecoderFactory`);
- topic ``twin/@events`` (``json``): injection events as published on ``twin/@/<IFO>/events``;
- topics ``twin/<channel>`` (``protobuf``): one message per block, the bytes as published on
  the bus; MCAP ``sequence`` = the block's sequence number, ``log_time`` = ``publish_time`` =
  the block's GPS start in Unix ns;
- chunks compressed with zstd, closed at :data:`CHUNK_BYTES` of messages (and, for the live
  recorder, at most :data:`CHUNK_SECONDS` after their first message) and flushed to the OS
  as they close: a writer killed with SIGKILL loses the open chunk only;
- chunk indexes, statistics, summary offsets and repeated schemas/channels in the summary;
  no message indexes (optional in MCAP, unused by the readers, and their per-chunk maps
  would hold 2.5 kB of the writer's memory per chunk, 1 GB per hour of the 40m). The chunk
  indexes still hold 0.4 kB per chunk until the summary is written: 150 MB per hour of the
  40m's 27.6 MB/s, a reason (with the 100 GB per hour on disk) to rotate long recordings.
"""

from __future__ import annotations

import datetime
import json
import struct
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib.metadata import version as _dist_version
from pathlib import Path
from types import TracebackType
from typing import Any

from mcap.writer import CompressionType, IndexType, Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set

import twind
from twind import strictjson
from twind.bus.codec import SampleBlock
from twind.bus.schema import sample_block_class
from twind.channels import block_channels
from twind.timeutil import gps_to_unix_ns, now_gps

TOPIC_ROOT = "twin"  # the same root as the Zenoh keys: a twin is never mistaken for CDS
FORMAT = "twind-mcap/1"
CONFIG_TOPIC = f"{TOPIC_ROOT}/@config"
EVENTS_TOPIC = f"{TOPIC_ROOT}/@events"
BLOCK_SCHEMA = "twind.v1.SampleBlock"
EVENT_SCHEMA = "twind.Event"
CONFIG_SCHEMA = "twind.Config"
SESSION_METADATA = "twind.session"
CONFIG_METADATA = "twind.config"

CHUNK_BYTES = 256 * 1024
"""Uncompressed bytes of messages per chunk: 9 ms of the 40m's 210 channels, a few blocks of
one optic. A killed writer loses at most this (or :data:`CHUNK_SECONDS` of data)."""
CHUNK_SECONDS = 1.0
"""The live recorder closes a chunk at most this long (wall clock) after its first message,
so that a slow stream reaches the disk too."""

_EVENT_JSON_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "twind injection event (as published on twin/@/<IFO>/events)",
    "type": "object",
    "properties": {
        "event": {"type": "string", "description": "start, stop, refused, ..."},
        "id": {"description": "injection identifier"},
        "gps": {"type": "number", "description": "GPS time of the event (s)"},
        "request": {"type": "object", "description": "the injection request"},
    },
    "required": ["event"],
}
_CONFIG_JSON_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "twind session configuration snapshot",
    "type": "object",
    "properties": {
        "format": {"type": "string"},
        "ifo": {"type": "string"},
        "gps": {"type": "number", "description": "GPS time of the snapshot (s)"},
        "writer": {"type": "string"},
        "status": {"description": "the twin service's reply to twin/@/<IFO>/status, if any"},
    },
    "required": ["format", "ifo", "gps"],
}


def sample_block_schema_data() -> bytes:
    """The serialized FileDescriptorSet of ``twind.v1.SampleBlock``, as mcap-protobuf writes it."""

    return build_file_descriptor_set(sample_block_class()).SerializeToString()


def library_label() -> str:
    """The MCAP header's library field: twind's and mcap-python's versions."""
    try:
        mcap_version = _dist_version("mcap")
    except Exception:  # noqa: BLE001 - only a label
        mcap_version = "?"
    return f"twind/{twind.__version__}; mcap-python/{mcap_version}"


# --- a minimal protobuf scanner for SampleBlock ------------------------------------------
#
# The recorder needs a block's GPS start and sequence number to stamp the MCAP message, and
# the reader needs its samples as a float64 array. Decoding with the generated class costs a
# copy of the samples into a protobuf container and another into numpy; scanning the fields
# by hand finds the packed samples in place, so numpy can view them without a copy.

_DOUBLE = struct.Struct("<d")
_F_CHANNEL, _F_GPS, _F_RATE, _F_SEQ, _F_SAMPLES, _F_UNIT, _F_TWIN = 1, 2, 3, 4, 5, 6, 7


@dataclass(frozen=True)
class BlockHeader:
    """The scalar fields of a ``twind.v1.SampleBlock`` and where its samples lie.

    ``runs`` are ``(offset, n_bytes)`` of the packed (or single) float64 sample fields in the
    message bytes, in order; one run for every message twind writes. ``twin`` is the
    publishing twin's identity, empty when the block names none.
    """

    channel: str
    gps_start: float
    rate_hz: float
    sequence: int
    unit: str
    runs: tuple[tuple[int, int], ...]
    twin: str = ""

    @property
    def n_samples(self) -> int:
        """Number of samples in the block."""
        return sum(n for _, n in self.runs) // 8


def _uvarint(buf: bytes | memoryview, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = buf[i]  # IndexError on a truncated varint, turned into ValueError below
        i += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, i
        shift += 7
        if shift > 63:
            msg = "varint longer than 10 bytes"
            raise ValueError(msg)


def scan_block(data: bytes | memoryview) -> BlockHeader:
    """Scan the protobuf bytes of a ``twind.v1.SampleBlock`` without decoding its samples.

    Parameters
    ----------
    data : bytes
        Any valid encoding: fields in any order, samples packed (possibly in several runs)
        or not; unknown fields are skipped.

    Returns
    -------
    BlockHeader

    Raises
    ------
    ValueError
        If `data` is not a well-formed protobuf message.
    """
    n = len(data)
    i = 0
    channel = unit = twin = ""
    gps = rate = 0.0
    seq = 0
    runs: list[tuple[int, int]] = []
    try:
        while i < n:
            key, i = _uvarint(data, i)
            field, wire = key >> 3, key & 7
            if wire == 0:  # varint
                value, i = _uvarint(data, i)
                if field == _F_SEQ:
                    seq = value
            elif wire == 1:  # 64-bit
                if i + 8 > n:
                    raise IndexError
                if field == _F_GPS:
                    gps = _DOUBLE.unpack_from(data, i)[0]
                elif field == _F_RATE:
                    rate = _DOUBLE.unpack_from(data, i)[0]
                elif field == _F_SAMPLES:
                    runs.append((i, 8))
                i += 8
            elif wire == 2:  # length-delimited
                length, i = _uvarint(data, i)
                if i + length > n:
                    raise IndexError
                if field == _F_CHANNEL:
                    channel = bytes(data[i:i + length]).decode()
                elif field == _F_UNIT:
                    unit = bytes(data[i:i + length]).decode()
                elif field == _F_TWIN:
                    twin = bytes(data[i:i + length]).decode()
                elif field == _F_SAMPLES:
                    if length % 8:
                        msg = f"packed samples of {length} bytes, not a multiple of 8"
                        raise ValueError(msg)
                    if length:
                        runs.append((i, length))
                i += length
            elif wire == 5:  # 32-bit
                i += 4
            else:
                msg = f"protobuf wire type {wire} of field {field} is not supported"
                raise ValueError(msg)
    except IndexError:
        msg = f"truncated protobuf message ({n} bytes)"
        raise ValueError(msg) from None
    if i != n:
        msg = f"protobuf message overruns its {n} bytes"
        raise ValueError(msg)
    return BlockHeader(channel, gps, rate, seq, unit, tuple(runs), twin)


# --- the file ------------------------------------------------------------------------------


class McapSession:
    """One MCAP file in twind's layout, written from raw message bytes.

    The low-level writer under :class:`SessionWriter` and :class:`twind.recording.recorder.
    Recorder`: the bytes of every block are written as given (the bus's bytes), never
    re-serialized.

    Parameters
    ----------
    path : str or Path
        File to create; an existing file is refused, never overwritten.
    ifo : str
        Interferometer prefix, e.g. ``"C1"``.
    config : mapping
        Configuration snapshot, written as the first message (``twin/@config``); the keys
        ``format``, ``ifo`` and ``gps`` are filled in if absent.
    writer : str
        Who writes (``"twind simulate"``, ``"twind record"``), for the session metadata.
    chunk_bytes : int
        Close (compress and flush) the open chunk once its messages reach this many bytes.
    config_message : bool
        Also write the snapshot as a ``twin/@config`` message (it is always in the
        ``twind.config`` metadata record).
    """

    def __init__(self, path: str | Path, ifo: str, config: Mapping[str, Any] | None = None,
                 writer: str = "twind", chunk_bytes: int = CHUNK_BYTES,
                 config_message: bool = True) -> None:
        self.path = Path(path)
        if self.path.exists():
            msg = f"{self.path} exists; twind does not overwrite recordings"
            raise FileExistsError(msg)
        self._fh = open(self.path, "xb")  # noqa: SIM115 - closed in close()
        # chunks are closed by this class (see _add), so that each one is flushed to the OS
        # as soon as it is complete; mcap's own threshold is only a backstop
        self._mcap = McapWriter(self._fh, chunk_size=64 * chunk_bytes,
                                compression=CompressionType.ZSTD,
                                index_types=IndexType.CHUNK | IndexType.ATTACHMENT
                                | IndexType.METADATA,
                                enable_crcs=True)
        self._mcap.start(profile="", library=library_label())
        self.ifo = ifo
        self.chunk_bytes = int(chunk_bytes)
        self._pending = 0  # bytes of messages in the open chunk
        self._pending_since: float | None = None  # monotonic time of its first message
        self.messages = 0
        self.message_bytes = 0
        self.first_gps: float | None = None  # GPS of the first block written
        self._block_schema = self._mcap.register_schema(BLOCK_SCHEMA, "protobuf",
                                                        sample_block_schema_data())
        self._event_schema = self._mcap.register_schema(
            EVENT_SCHEMA, "jsonschema", json.dumps(_EVENT_JSON_SCHEMA).encode())
        self._channels: dict[str, int] = {}
        self._channels[EVENTS_TOPIC] = self._mcap.register_channel(EVENTS_TOPIC, "json",
                                                                   self._event_schema)
        self._mcap.add_metadata(SESSION_METADATA, {
            "format": FORMAT, "ifo": ifo, "writer": writer,
            "created_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        })
        snapshot = {"format": FORMAT, "ifo": ifo, "writer": writer, **(config or {})}
        snapshot.setdefault("gps", now_gps())
        raw = strictjson.dumps(snapshot, default=str).encode()
        self._mcap.add_metadata(CONFIG_METADATA, {"json": raw.decode()})
        if config_message:
            config_schema = self._mcap.register_schema(
                CONFIG_SCHEMA, "jsonschema", json.dumps(_CONFIG_JSON_SCHEMA).encode())
            config_channel = self._mcap.register_channel(CONFIG_TOPIC, "json", config_schema)
            self._add(config_channel, raw, gps_to_unix_ns(float(snapshot["gps"])), 0)
        self.config = json.loads(raw)
        self.events = 0
        self.flush()

    @property
    def size(self) -> int:
        """Bytes in the file so far (closed chunks only)."""
        return self._fh.tell()

    def _add(self, channel_id: int, data: bytes, t_ns: int, sequence: int) -> None:
        self._mcap.add_message(channel_id, t_ns, data, t_ns, sequence)
        self.messages += 1
        self.message_bytes += len(data)
        if self._pending_since is None:
            self._pending_since = time.monotonic()
        self._pending += len(data) + 31  # the Message record's own header
        if self._pending >= self.chunk_bytes:
            self.flush()

    def write_block(self, data: bytes, header: BlockHeader | None = None,
                    topic: str | None = None) -> BlockHeader:
        """Append the protobuf bytes of one SampleBlock.

        Parameters
        ----------
        data : bytes
            The message as published on the bus.
        header : BlockHeader, optional
            ``scan_block(data)`` if the caller already has it.
        topic : str, optional
            Default ``twin/<channel>``.

        Returns
        -------
        BlockHeader
        """
        if header is None:
            header = scan_block(data)
        topic = topic or f"{TOPIC_ROOT}/{header.channel}"
        channel_id = self._channels.get(topic)
        if channel_id is None:
            channel_id = self._mcap.register_channel(topic, "protobuf", self._block_schema)
            self._channels[topic] = channel_id
        if self.first_gps is None:
            self.first_gps = header.gps_start
        self._add(channel_id, data, gps_to_unix_ns(header.gps_start), header.sequence)
        return header

    def write_event(self, data: bytes | Mapping[str, Any], gps: float | None = None) -> None:
        """Append one injection event (JSON bytes as published, or a mapping).

        The log time is the event's ``gps`` field if it has one, else `gps`, else now.
        Non-finite numbers in the event are written as null.

        Parameters
        ----------
        data : bytes or mapping
            The event: the JSON object published on ``twin/@/<ifo>/events``, or its mapping.
        gps : float, optional
            GPS time (s) to log it at when the event has no ``gps`` field.

        Raises
        ------
        ValueError
            If `data` is not JSON.
        """
        # refuse what a JSON decoder would choke on later; NaN, which Python's decoder
        # takes, is written as null (a real JSON reader takes no NaN)
        event = data if isinstance(data, Mapping) else json.loads(bytes(data))
        raw = strictjson.dumps(event).encode()
        stamp = event.get("gps") if isinstance(event, Mapping) else None
        if not isinstance(stamp, int | float) or isinstance(stamp, bool):
            stamp = gps if gps is not None else now_gps()
        self._add(self._channels[EVENTS_TOPIC], raw, gps_to_unix_ns(float(stamp)), self.events)
        self.events += 1

    def maybe_flush(self, max_age_s: float = CHUNK_SECONDS) -> None:
        """Close the open chunk if its first message is older than `max_age_s` (wall clock)."""
        if self._pending_since is not None and \
                time.monotonic() - self._pending_since >= max_age_s:
            self.flush()

    def flush(self) -> None:
        """Close the open chunk and hand everything written so far to the OS."""
        self._mcap.flush()  # finishes the chunk and flushes the stream (no fsync)
        self._pending, self._pending_since = 0, None

    def close(self) -> None:
        """Write the summary and footer, and close the file."""
        if not self._fh.closed:
            try:
                self._mcap.finish()
            finally:
                self._fh.close()

    def __enter__(self) -> McapSession:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


class SessionWriter:
    """An MCAP session file of engine blocks; use as a context manager so the summary is
    written on exit.

    Parameters
    ----------
    path : str or Path
        File to create (an existing file is refused, never overwritten).
    ifo : str
        Interferometer prefix of the channel names.
    gps_start : float
        GPS time of sample 0 of the engine.
    config : mapping, optional
        Extra configuration (e.g. the optics and their parameters) for the ``twin/@config``
        snapshot.
    channels : callable, optional
        ``channels(name)`` is true for the channels to write; default all of a block's.
    """

    def __init__(self, path: str | Path, ifo: str, gps_start: float,
                 config: Mapping[str, Any] | None = None,
                 channels: Callable[[str], bool] | None = None) -> None:
        # no twin/@config message: see the module docstring
        self._file = McapSession(path, ifo, {"gps": gps_start, **(config or {})},
                                 writer="twind simulate", config_message=False)
        self.path = self._file.path
        self.ifo, self.gps_start, self.sequence = ifo, gps_start, 0
        self.channels = channels

    def write_block(self, block) -> None:  # noqa: ANN001 - twind.simulation.engine.Block
        """Append every channel of `block` as one message each."""

        gps = self.gps_start + block.start_sample / block.rate_hz
        for name, unit, samples in block_channels(self.ifo, block):
            if self.channels is not None and not self.channels(name):
                continue
            data = SampleBlock(name, gps, block.rate_hz, self.sequence, samples, unit).encode()
            self._file.write_block(data, BlockHeader(name, gps, block.rate_hz, self.sequence,
                                                     unit, ()))
        self.sequence += 1

    def write_event(self, event: Mapping[str, Any]) -> None:
        """Append an injection event (a JSON object with ``event``, ``gps``, ...)."""
        self._file.write_event(event)

    def close(self) -> None:
        """Write the MCAP summary and close the file."""
        self._file.close()

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
