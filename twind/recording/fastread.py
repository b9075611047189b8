"""The engine of :func:`twind.recording.reader.read_session`: the sample channels of MCAP
sessions read fast, for long recordings.

:func:`read_channels` returns a :class:`~twind.recording.session.Session` for the channels
a predicate selects, with the truncation and gap handling of
:mod:`twind.recording.mcapfile`. It is built for an hour of 16 kHz channels (700 000
blocks): mcap's :func:`~mcap.stream_reader.breakup_chunk` and the protobuf scanner cost some
20 us of Python per block, so here a chunk's records are indexed, its SampleBlocks scanned
and their samples copied out by numba kernels, a chunk at a time; the decompression and CRC
check (which release the GIL) run one chunk ahead in a worker thread.

Anything unusual (a block whose channel name differs from its topic, samples in several
runs, a schema other than SampleBlock) sends its chunk through a plain Python path, message
by message; a channel with gaps, duplicates or overlaps is joined by
:func:`~twind.recording.session.join_blocks`.
"""

from __future__ import annotations

import json
import mmap
import struct
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any, Protocol

import lz4.frame
import numpy as np
import zstandard
from mcap import records as mcap_records
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, InvalidMagic, McapError, RecordLengthLimitExceeded
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel as McapChannel
from mcap.records import DataEnd, Footer, Message, Metadata, Schema
from mcap.writer import MCAP0_MAGIC as _MAGIC
from numpy.typing import NDArray

from twind.recording.kernels import _index_records, _scan_blocks
from twind.recording.mcapfile import (
    indexed_chunks,
    indexed_summary,
    report_truncation,
    require_header,
    truncation_reason,
)
from twind.recording.session import (
    Block,
    Channel,
    RecordingError,
    Session,
    block_samples,
    join_blocks,
    scan_sample_block,
    session_files,
    some_names,
    warn_gaps,
)
from twind.recording.sources import warn_unserved
from twind.recording.writer import (
    BLOCK_SCHEMA,
    CONFIG_METADATA,
    CONFIG_TOPIC,
    EVENTS_TOPIC,
    TOPIC_ROOT,
    scan_block,
)

try:  # the same CRC-32 as zlib's, from zlib-ng's vectorised code
    from zlib_ng.zlib_ng import crc32 as _crc32
except ImportError:  # pragma: no cover - a platform without its wheels
    from zlib import crc32 as _crc32

_OP_MESSAGE, _OP_SCHEMA, _OP_CHANNEL = 0x05, 0x03, 0x04
# what a channel id of a file is to the kernels
_UNDEFINED, _IGNORED, _PYTHON = -3, -2, -1  # >= 0: a slot (a wanted block channel)
_PREFETCH = 4  # batches of chunks decompressed ahead of the kernels
_BATCH_BYTES = 4 << 20  # uncompressed bytes of chunks a worker decodes at once
_DECODERS = 2  # threads decompressing: zstd is most of the reading


# ------------------------------------------------------------------------------ the reader
class _Slot:
    """The samples of one wanted channel, in recorded order, in one growing buffer."""

    def __init__(self, name: str, blocks: int = 0) -> None:
        self.name = name
        self.unit: str | None = None
        self.buf = np.empty(0, dtype=np.float64)
        self.n = 0
        self.blocks = blocks  # expected, from the files' summaries (0: unknown)

    def add(self, x: NDArray[np.float64], blocks: int = 1) -> None:
        """The samples of `blocks` consecutive blocks."""
        need = self.n + x.size
        if self.buf.size == 0 and self.blocks and x.size:
            # sized once from the summary's message count: growing is a copy (resize
            # zero-fills the new part), and fresh memory is slow to fault in
            self.buf = np.empty(max(need, self.blocks * -(-x.size // blocks)),
                                dtype=np.float64)
        if need > self.buf.size:
            # realloc: a large buffer is moved by remapping its pages, not copied
            self.buf.resize(max(need, 2 * self.buf.size, 1 << 16), refcheck=False)
        self.buf[self.n:need] = x
        self.n = need

    def join(self, meta_i: NDArray[np.int64], meta_f: NDArray[np.float64]) -> Channel:
        """One channel from its blocks' (sequence, samples) and (GPS, rate); the common case
        (consecutive blocks, one rate) without a Python loop over blocks, anything else by
        the session's :func:`~twind.recording.session.join_blocks`."""
        seq, nsamp = meta_i
        gps, rate = meta_f
        self.buf.resize(self.n, refcheck=False)
        samples, self.buf = self.buf, np.empty(0)
        r0 = float(rate[0])
        simple = r0 > 0 and bool(np.all(rate == r0))
        if simple and len(seq) > 1:
            end = gps[:-1] + nsamp[:-1] / r0
            offset = (gps[1:] - end) * r0
            k = np.round(offset)
            simple = bool(np.all((np.abs(offset - k) <= 0.05) & (k == 0))
                          and np.all(np.diff(seq) == 1))
        if not simple:
            blocks = [Block(int(s), float(g), float(r), self.unit or "", x)
                      for s, g, r, x in zip(seq, gps, rate,
                                            np.split(samples, np.cumsum(nsamp)[:-1]),
                                            strict=True)]
            return join_blocks(self.name, blocks)
        return Channel(self.name, self.unit or "", r0, float(gps[0]), samples,
                       seq.astype(np.int64), gps.astype(np.float64), [])


Decoded = tuple[NDArray[np.uint8], tuple, tuple | None]
"""Chunks as :func:`_decode_batch` leaves them: their records, the records' index, their
SampleBlocks scanned."""


def _decode_batch(chunks: list[_ChunkView], channel_map: tuple
                  ) -> tuple[Decoded | None, int, BaseException | None]:
    """Consecutive chunks decompressed into one buffer, its records indexed and, if they are
    all messages, its SampleBlocks scanned with the channels defined so far: the work of a
    worker thread (all of it releases the GIL). The chunks before the first that fails, how
    many, and the error.

    One buffer for a few MB of chunks, scanned once: an hour of test points is 20 000
    chunks, and the per-chunk hand-overs between threads cost more than their kernels.
    """
    buf = np.empty(sum(c.uncompressed_size for c in chunks), dtype=np.uint8)
    end, done, err = 0, 0, None
    for c in chunks:
        part = buf[end:end + c.uncompressed_size]
        try:
            _decompress(c, part)
            if _index_records(part)[3] < 0:  # alone: the next chunk would complete it
                msg = "a record overruns its chunk"
                raise ValueError(msg)
        except Exception as e:  # noqa: BLE001 - raised in order, where the chunks are read
            err = e
            break
        end += part.size
        done += 1
    if done == 0:
        return None, 0, err
    arr = buf[:end]
    ops, starts, lens, count = _index_records(arr)
    scanned = None
    if np.all(ops == _OP_MESSAGE):
        scanned = _scan_blocks(arr, ops, starts, lens, count, *channel_map)
    return (arr, (ops, starts, lens, count), scanned), done, err


def _decompress(chunk: _ChunkView, out: NDArray[np.uint8]) -> None:
    """A chunk's records into `out` (its uncompressed size), CRC checked."""

    if chunk.compression == "zstd":
        with zstandard.ZstdDecompressor().stream_reader(chunk.data) as reader:
            n = 0
            while n < out.size and (got := reader.readinto(out[n:])):
                n += got
    elif chunk.compression in ("lz4", ""):
        data = chunk.data
        if chunk.compression == "lz4":
            data = lz4.frame.decompress(data)
        n = len(data)
        if n == out.size:
            out[:] = np.frombuffer(data, dtype=np.uint8)
    else:
        msg = f"unsupported chunk compression {chunk.compression!r}"
        raise ValueError(msg)
    if n != out.size:
        msg = f"a chunk decompressed to {n} bytes, not the {out.size} it declares"
        raise ValueError(msg)
    crc = chunk.uncompressed_crc
    if crc != 0 and (got := _crc32(out)) != crc:
        msg = f"crc validation failed in Chunk, expected: {crc}, calculated: {got}"
        raise ValueError(msg)


class _FileReader:
    """The state of reading one file: schemas, channels and what each channel id is."""

    def __init__(self, path: Path, state: _State) -> None:
        self.path = path
        self.state = state
        self.schemas: dict[int, Any] = {}
        self.channels: dict[int, Any] = {}
        self.kind = np.full(1, _UNDEFINED, dtype=np.int64)  # by channel id, for the kernels

    def _define(self, ch: Any) -> None:
        self.channels[ch.id] = ch
        if ch.id >= self.kind.size:
            grown = np.full(max(ch.id + 1, 2 * self.kind.size), _UNDEFINED, dtype=np.int64)
            grown[:self.kind.size] = self.kind
            self.kind = grown
        schema = self.schemas.get(ch.schema_id)
        topic = ch.topic
        name = topic.removeprefix(f"{TOPIC_ROOT}/")
        if topic in (EVENTS_TOPIC, CONFIG_TOPIC):
            self.kind[ch.id] = _PYTHON
        elif not topic.startswith(f"{TOPIC_ROOT}/") or name.startswith("@") or \
                not self.state.wanted(name) or ch.message_encoding != "protobuf" or \
                schema is None or schema.name != BLOCK_SCHEMA:
            # as mcap's own reader, a schema twind does not write is skipped
            self.kind[ch.id] = _IGNORED
        else:
            self.kind[ch.id] = self.state.slot(name)

    def channel_map(self) -> tuple[NDArray, NDArray, NDArray, int]:
        """What the kernels need to know of the channels defined so far (a snapshot, for a
        worker thread): slot by channel id, slot names and their lengths, slots."""
        state = self.state
        return self.kind.copy(), state.names, state.name_lens, len(state.slots)

    def record(self, rec: Any) -> None:
        """A record outside the kernels (Schema, Channel, Message outside chunks, ...)."""

        if isinstance(rec, Schema):
            self.schemas[rec.id] = rec
        elif isinstance(rec, McapChannel):
            self._define(rec)
        elif isinstance(rec, Message):
            self.message(rec.channel_id, rec.data)
        elif isinstance(rec, Metadata):
            self.state.metadata[rec.name] = dict(rec.metadata)

    def message(self, channel_id: int, data: bytes) -> None:
        """One message by :func:`read_session`'s rules."""

        channel = self.channels.get(channel_id)
        if channel is None:
            msg = f"{self.path}: message on channel {channel_id}, never defined"
            raise RecordingError(msg)
        topic = channel.topic
        if topic == EVENTS_TOPIC:
            self.state.events.append(_json(self.path, topic, data))
            if self.state.sink is not None:
                self.state.sink.event(self.state.events[-1])
            return
        if topic == CONFIG_TOPIC:
            self.state.configs.append(_json(self.path, topic, data))
            self.state.config_seen = True
            return
        if self.kind[channel_id] < 0:
            return
        header, name = scan_sample_block(data, topic)
        if not self.state.wanted(name):
            return
        s = self.state.slot(name)
        slot = self.state.slots[s]
        if slot.unit is None:
            slot.unit = header.unit
        x = block_samples(data, header)
        if self.state.sink is not None:
            self.state.sink.samples(name, np.array([header.sequence]), np.array([x.size]),
                                    np.array([header.gps_start]), np.array([header.rate_hz]), x)
            return
        slot.add(x)
        self.state.meta_i.append(np.array([[header.sequence], [x.size], [s]], np.int64))
        self.state.meta_f.append(np.array([[header.gps_start], [header.rate_hz]]))

    def chunk(self, decoded: Decoded) -> None:
        """The records of consecutive chunks, as :func:`_decode_batch` left them."""
        arr, (ops, starts, lens, count), scanned = decoded
        if np.any(ops != _OP_MESSAGE):
            # schemas and channels defined here (the first chunks): record by record, so
            # that a message before its channel's definition is refused as read_session does
            self._chunk_in_python(arr, ops, starts, lens)
            return
        state = self.state
        if scanned is None or scanned[0] == 2:  # channels defined since it was decoded
            scanned = _scan_blocks(arr, ops, starts, lens, count, *self.channel_map())
        status, _, out, first, mi, mf = scanned
        if status != 0:
            self._chunk_in_python(arr, ops, starts, lens)
            return
        bounds = np.concatenate(([0], np.cumsum(mi[2])))
        for s in np.flatnonzero(np.diff(first)):
            a, b = first[s], first[s + 1]
            slot = state.slots[s]
            if slot.unit is None:
                slot.unit = scan_block(arr[mi[3, a]:mi[3, a] + mi[4, a]].tobytes()).unit
            if state.sink is not None:
                state.sink.samples(slot.name, mi[1, a:b], mi[2, a:b], mf[0, a:b], mf[1, a:b],
                                   out[bounds[a]:bounds[b]])
            else:
                slot.add(out[bounds[a]:bounds[b]], b - a)
        if state.sink is None:
            state.meta_i.append(mi[[1, 2, 5]])
            state.meta_f.append(mf)
        if self.state.python_topics:
            cids = arr[starts].astype(np.int64) | (arr[starts + 1].astype(np.int64) << 8)
            for r in np.flatnonzero(self.kind[cids] == _PYTHON):
                a = int(starts[r])
                self.message(int(cids[r]), arr[a + 22:a + int(lens[r])].tobytes())

    def _chunk_in_python(self, arr: NDArray[np.uint8], ops: NDArray, starts: NDArray,
                         lens: NDArray) -> None:

        buf = arr.tobytes()

        for op, a, n in zip(ops.tolist(), starts.tolist(), lens.tolist(), strict=True):
            if op == _OP_MESSAGE:
                self.message(int(buf[a]) | (int(buf[a + 1]) << 8), buf[a + 22:a + n])
            elif op in (_OP_SCHEMA, _OP_CHANNEL):
                stream = ReadDataStream(BytesIO(buf[a:a + n]))
                self.record(Schema.read(stream) if op == _OP_SCHEMA else McapChannel.read(stream))


def _json(path: Path, topic: str, data: bytes) -> dict[str, Any]:
    try:
        return json.loads(data)
    except ValueError as err:
        msg = f"{path}: {topic}: a message is not JSON ({err})"
        raise RecordingError(msg) from None


class SampleSink(Protocol):
    """What :func:`stream_channels` hands the samples and events to, in recorded order."""

    def samples(self, name: str, sequence: NDArray[np.int64], n_samples: NDArray[np.int64],
                gps: NDArray[np.float64], rate: NDArray[np.float64],
                x: NDArray[np.float64]) -> None:
        """Consecutive blocks of channel `name` as recorded: per block its sequence number,
        sample count, GPS start and rate; `x` their samples joined (never written again: the
        sink may keep it).

        Parameters
        ----------
        name : str
            The channel, e.g. ``C1:SUS-ETMX_SUSPOS_IN1``.
        sequence : numpy.ndarray
            Each block's sequence number.
        n_samples : numpy.ndarray
            Each block's number of samples.
        gps : numpy.ndarray
            Each block's GPS time of its first sample (s).
        rate : numpy.ndarray
            Each block's sample rate (Hz).
        x : numpy.ndarray
            The blocks' samples one after the other, ``n_samples.sum()`` of them.
        """

    def event(self, event: dict[str, Any]) -> None:
        """An injection event."""


@dataclass
class _State:
    """What the files of a session give, together."""

    wanted: Callable[[str], bool]
    slots: list[_Slot] = field(default_factory=list)
    by_name: dict[str, int] = field(default_factory=dict)
    events: list[dict[str, Any]] = field(default_factory=list)
    configs: list[dict[str, Any]] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    config_seen: bool = False
    python_topics: bool = True  # events and config are read by Python, message by message
    sink: SampleSink | None = None  # takes the samples instead of the slots
    # per chunk: (sequence, samples, slot) and (GPS, rate) of every wanted block
    meta_i: list[NDArray[np.int64]] = field(default_factory=list)
    meta_f: list[NDArray[np.float64]] = field(default_factory=list)
    expected: dict[str, int] = field(default_factory=dict)  # messages by topic (summaries)
    names: NDArray[np.uint8] = field(default_factory=lambda: np.zeros((0, 1), np.uint8))
    name_lens: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    def slot(self, name: str) -> int:
        """The slot of channel `name`, made on first use."""
        if name not in self.by_name:
            self.by_name[name] = len(self.slots)
            self.slots.append(_Slot(name, self.expected.get(f"{TOPIC_ROOT}/{name}", 0)))
            raw = [n.encode() for n in self.by_name]
            self.names = np.zeros((len(raw), max(map(len, raw))), np.uint8)
            for i, r in enumerate(raw):
                self.names[i, :len(r)] = np.frombuffer(r, np.uint8)
            self.name_lens = np.array([len(r) for r in raw], np.int64)
        return self.by_name[name]

    def channels(self) -> dict[str, Channel]:
        """Every slot with data, joined, in the order first seen."""
        if not self.meta_i:
            return {}
        mi = np.concatenate(self.meta_i, axis=1)
        mf = np.concatenate(self.meta_f, axis=1)
        self.meta_i, self.meta_f = [], []
        order = np.argsort(mi[2], kind="stable")
        cuts = np.searchsorted(mi[2], np.arange(len(self.slots) + 1), sorter=order)
        out = {}
        for s, slot in enumerate(self.slots):
            take = order[cuts[s]:cuts[s + 1]]
            if take.size:
                out[slot.name] = slot.join(mi[:2, take], mf[:, take])
        return out


@dataclass(frozen=True)
class _ChunkView:
    """A Chunk record whose compressed records are a view of the mapped file."""

    compression: str
    data: memoryview
    uncompressed_size: int
    uncompressed_crc: int


class _Records:
    """The records of an MCAP file in order, read from a memory map: mcap's
    ``StreamReader(emit_chunks=True)`` without copying the chunks (4.5 GB an hour of twelve
    16 kHz channels) or reading them twice for the data section's CRC (each chunk's CRC is
    checked when it is decompressed), nor parsing the indexes.

    Raises mcap's ``InvalidMagic``, ``EndOfFile`` and ``RecordLengthLimitExceeded`` as the
    stream reader does; :attr:`at` is the offset reached.
    """

    def __init__(self, path: Path, size: int) -> None:
        self.path, self.size, self.at = path, size, 0

    def __iter__(self) -> Iterator[Any]:
        # the indexes are not parsed: the file is read in order (an hour's chunk index is
        # 20 000 records)
        kinds = {Opcode.ATTACHMENT: mcap_records.Attachment, Opcode.CHANNEL: mcap_records.Channel,
                 Opcode.DATA_END: mcap_records.DataEnd, Opcode.FOOTER: mcap_records.Footer,
                 Opcode.HEADER: mcap_records.Header, Opcode.METADATA: mcap_records.Metadata,
                 Opcode.SCHEMA: mcap_records.Schema, Opcode.STATISTICS: mcap_records.Statistics}
        if self.size < len(_MAGIC):
            raise InvalidMagic(b"")
        with open(self.path, "rb") as fh:
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        view = memoryview(mm)
        if view[:8] != _MAGIC:
            raise InvalidMagic(bytes(view[:8]))
        self.at = i = len(_MAGIC)
        while True:
            if i + 9 > self.size:
                raise EndOfFile
            op = view[i]
            length = int.from_bytes(view[i + 1:i + 9], "little")
            if length > self.size:
                raise RecordLengthLimitExceeded(op, length, self.size)
            end = i + 9 + length
            if end > self.size:
                raise EndOfFile
            if op == Opcode.CHUNK:
                yield _chunk_view(view[i + 9:end])
            elif op == Opcode.MESSAGE:
                yield mcap_records.Message.read(ReadDataStream(BytesIO(view[i + 9:end])), length)
            elif op in kinds:  # anything else is skipped, as mcap does
                yield kinds[op].read(ReadDataStream(BytesIO(view[i + 9:end])))
                if op == Opcode.FOOTER:
                    if view[end:end + 8] != _MAGIC:
                        raise InvalidMagic(bytes(view[end:end + 8]))
                    return
            self.at = i = end


def _chunk_view(content: memoryview) -> _ChunkView:
    """A Chunk record's fields (MCAP spec: start and end time, uncompressed size and CRC,
    compression, then the records)."""
    size, crc, n = struct.unpack_from("<QII", content, 16)
    compression = bytes(content[32:32 + n]).decode()
    (length,) = struct.unpack_from("<Q", content, 32 + n)
    data = content[40 + n:40 + n + length]
    if len(data) != length:
        msg = "a chunk's records overrun it"
        raise ValueError(msg)
    return _ChunkView(compression, data, size, crc)


def _read_file(path: Path, state: _State, problems: list[str], pool: ThreadPoolExecutor
               ) -> None:
    """Every record of one file, by :func:`~twind.recording.mcapfile.iter_raw_messages`'s rules
    for a file cut short."""

    size = path.stat().st_size
    require_header(path, size)
    reader = _FileReader(path, state)
    state.metadata = {}
    state.config_seen = False
    chunks = 0
    data_end = footer = False
    pending: deque[Future | Any] = deque()

    batch: list[_ChunkView] = []

    def submit() -> None:
        if batch:
            pending.append(pool.submit(_decode_batch, batch.copy(), reader.channel_map()))
            batch.clear()

    def drain(keep: int) -> None:
        nonlocal chunks
        while len(pending) > keep:
            item = pending.popleft()
            try:
                if isinstance(item, Future):
                    decoded, done, err = item.result()
                    if decoded is not None:
                        reader.chunk(decoded)
                    chunks += done
                    if err is not None:
                        raise err
                else:
                    reader.record(item)
            except BaseException:
                pending.clear()  # what follows a damaged chunk is not read, as in read_session
                raise

    truncation = (EndOfFile, McapError, ValueError, struct.error, zstandard.ZstdError)
    records = _Records(path, size)
    try:
        try:
            for record in records:
                if isinstance(record, _ChunkView):
                    batch.append(record)
                    if sum(c.uncompressed_size for c in batch) >= _BATCH_BYTES:
                        submit()
                        drain(_PREFETCH)
                    continue
                submit()
                if isinstance(record, DataEnd):
                    data_end = True
                elif isinstance(record, Footer):
                    footer = True
                elif not data_end:  # the summary repeats schemas and channels
                    pending.append(record)
                drain(_PREFETCH)
        except truncation:
            # the chunks read before the error count; a damaged one among them is the
            # reason given
            submit()
            drain(0)
            raise
        submit()
        drain(0)
    except InvalidMagic as err:
        if records.at <= 8 and size >= 8:
            msg = f"{path}: not an MCAP file ({err})"
            raise RecordingError(msg) from None
        footer = False
        reason = str(err)
    except truncation as err:
        footer = False
        reason = truncation_reason(err, size)
        # damage inside a complete file: the rest is read by its index, the chunks lost named
        # (data_end may be set: the chunks are decoded behind the records read ahead)
        footer = _read_by_index(path, reader, chunks, problems)
    else:
        reason = ""
    if not footer:
        report_truncation(path, data_end, chunks, size, reason, problems)
    if not state.config_seen and CONFIG_METADATA in state.metadata:
        state.configs.append(json.loads(state.metadata[CONFIG_METADATA].get("json", "{}")))


def _read_by_index(path: Path, reader: _FileReader, chunks: int, problems: list[str]) -> bool:
    """The chunks from the `chunks`-th on (file order), read one by one through the file's
    chunk index, a damaged one skipped and reported; False when the file has no usable
    index (or the damage lies beyond its chunks)."""
    with open(path, "rb") as fh:
        summary = indexed_summary(fh)
        if summary is None or chunks >= len(summary.chunk_indexes):
            return False
        for record in (*summary.schemas.values(), *summary.channels.values()):
            reader.record(record)
        offsets = sorted(c.chunk_start_offset for c in summary.chunk_indexes)
        for records in indexed_chunks(fh, summary, offsets[chunks], path, problems):
            for record in records:
                reader.record(record)
    return True


def _message_counts(files: list[Path]) -> tuple[dict[str, int], bool]:
    """Messages per topic over `files`, from their summaries, and whether every file had
    one (else the counts are partial)."""

    counts: dict[str, int] = {}
    whole = True
    for path in files:
        try:
            with open(path, "rb") as fh:
                summary = make_reader(fh).get_summary()
        except Exception:  # noqa: BLE001 - a file cut short: no summary, sizes unknown
            summary = None
        if summary is None or summary.statistics is None:
            whole = False
            continue
        for cid, n in summary.statistics.channel_message_counts.items():
            ch = summary.channels.get(cid)
            if ch is not None:
                counts[ch.topic] = counts.get(ch.topic, 0) + n
    return counts, whole


def event_count(path_or_paths: str | Path | Iterable[str | Path]) -> int | None:
    """The injection events a recording's summaries count, without reading its data; None
    when a file has no summary (cut short).

    Parameters
    ----------
    path_or_paths : path or iterable of paths
        See :func:`~twind.recording.session.session_files`.

    Returns
    -------
    int or None
    """
    counts, whole = _message_counts(session_files(path_or_paths))
    return counts.get(EVENTS_TOPIC, 0) if whole else None


def read_channels(path_or_paths: str | Path | Iterable[str | Path],
                  wanted: Callable[[str], bool] | Iterable[str]) -> Session:
    """Read the channels `wanted` selects from a recording, fast.

    Parameters
    ----------
    path_or_paths : path or iterable of paths
        See :func:`~twind.recording.session.session_files`.
    wanted : callable or iterable of str
        ``wanted(name)`` is true for the channels to read; or their names, every one of
        which must be in the recording.

    Returns
    -------
    Session
        As :func:`~twind.recording.reader.read_session` returns it: the channels in the
        order first recorded (or in the order of `wanted`'s names), every event and
        configuration snapshot.

    Raises
    ------
    RecordingError
        As :func:`~twind.recording.reader.read_session`.

    Warns
    -----
    TruncatedRecordingWarning, GapWarning
        As :func:`~twind.recording.reader.read_session`.
    """
    files = session_files(path_or_paths)
    order: list[str] | None = None
    if not callable(wanted):
        order = list(dict.fromkeys(wanted))
        wanted = set(order).__contains__
    state = _State(wanted, expected=_message_counts(files)[0])
    problems = _read(files, state)
    joined = state.channels()
    if order is not None:
        missing = [n for n in order if n not in joined]
        if missing:
            msg = (f"{some_names(sorted(missing))} not in {files[0]}"
                   f"{f' (and {len(files) - 1} more files)' if len(files) > 1 else ''}")
            raise RecordingError(msg)
        joined = {name: joined[name] for name in order}
    complete = not problems  # truncations only: gaps are problems of a complete file
    warn_gaps(joined, problems)
    warn_unserved(state.events, joined.__contains__, problems)
    return Session(files, joined, state.events, state.configs, complete, problems)


def stream_channels(path_or_paths: str | Path | Iterable[str | Path],
                    wanted: Callable[[str], bool], sink: SampleSink) -> Session:
    """Hand the samples of the channels `wanted` selects to `sink` as they are read, without
    keeping them: hours of 16 kHz channels in the memory of a few chunks.

    Parameters
    ----------
    path_or_paths : path or iterable of paths
        See :func:`~twind.recording.session.session_files`.
    wanted : callable
        ``wanted(name)`` is true for the channels to stream.
    sink : SampleSink
        Gets every block of those channels and every injection event, in recorded order.

    Returns
    -------
    Session
        Events, configuration snapshots and problems as :func:`read_channels` gives them;
        no channels (their gaps are the sink's to notice).

    Raises
    ------
    RecordingError
        As :func:`~twind.recording.reader.read_session`.

    Warns
    -----
    TruncatedRecordingWarning
        As :func:`~twind.recording.reader.read_session`.
    """
    files = session_files(path_or_paths)
    state = _State(wanted, sink=sink)
    problems = _read(files, state)
    return Session(files, {}, state.events, state.configs, not problems, problems)


def _read(files: list[Path], state: _State) -> list[str]:
    """Every file into `state`; the truncations found."""
    problems: list[str] = []
    with ThreadPoolExecutor(_DECODERS, thread_name_prefix="twind-mcap") as pool:
        for path in files:
            _read_file(path, state, problems, pool)
    return problems
