"""MCAP files read as far as they go: messages in file order through mcap's sequential
:class:`~mcap.stream_reader.StreamReader`, never through the summary at the end, so that a
file whose writer was killed (no summary, no footer, perhaps half a chunk at the end) gives
everything up to its last complete chunk, with a
:class:`~twind.recording.session.TruncatedRecordingWarning`; a damaged chunk inside a
complete file is skipped by the file's chunk index, and the rest read, with a
:class:`~twind.recording.session.DamagedRecordingWarning` giving the time span lost."""

from __future__ import annotations

import json
import struct
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.reader import SeekingReader
from mcap.records import Channel as McapChannel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import MCAP0_MAGIC

from twind.recording.session import (
    DamagedRecordingWarning,
    RecordingError,
    TruncatedRecordingWarning,
    caller_level,
)
from twind.timeutil import unix_ns_to_gps


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
    a recording (a file cut inside the magic is a recording killed at once, read as cut).

    Parameters
    ----------
    path : Path
        The file.
    size : int
        Its size in bytes.

    Raises
    ------
    RecordingError
        If the file is empty, or shorter than the magic and not a beginning of it.
    """
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
        report_truncation(path, data_end, chunks, size, reason, problems)


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
    the time span it held reported (a warning, and in `problems`).

    Parameters
    ----------
    fh : binary file
        The recording, open for reading and seeking.
    summary : mcap.records.Summary
        Its summary, as :func:`indexed_summary` returns it.
    offset : int
        Byte offset in the file; chunks that start before it are skipped (already read).
    path : Path
        The file, for the report.
    problems : list of str or None
        Receives a description of each damaged chunk.

    Yields
    ------
    list
        The records of one chunk, in file order.

    Warns
    -----
    DamagedRecordingWarning
        For each damaged chunk, with the GPS span of its lost messages.
    """
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
            warnings.warn(text, DamagedRecordingWarning, stacklevel=caller_level())
            continue
        yield records


def truncation_reason(err: Exception, size: int) -> str:
    """Why reading stopped early, for the truncation report.

    Parameters
    ----------
    err : Exception
        The error that stopped the reading.
    size : int
        The file's size in bytes.

    Returns
    -------
    str
    """
    if size < 8:
        return "shorter than the MCAP magic"
    return f"{type(err).__name__}: {err}" if str(err) else type(err).__name__


def report_truncation(path: Path, data_end: bool, chunks: int, size: int, reason: str,
                      problems: list[str] | None) -> None:
    """Warn (and note in `problems`) that `path` stops without its summary and footer.

    Parameters
    ----------
    path : Path
        The file.
    data_end : bool
        Whether its DataEnd record was read (the data are complete).
    chunks : int
        Number of complete chunks read.
    size : int
        The file's size in bytes.
    reason : str
        Why reading stopped, as :func:`truncation_reason` gives it; "" for none.
    problems : list of str or None
        Receives the description.

    Warns
    -----
    TruncatedRecordingWarning
    """
    where = "after its data" if data_end else f"after {chunks} complete chunk(s)"
    text = (f"{path}: the recording ends {where} without its summary and footer "
            f"({size} bytes; the writer was killed or the disk filled?); read up to there"
            + (f" [{reason}]" if reason else ""))
    if problems is not None:
        problems.append(text)
    warnings.warn(text, TruncatedRecordingWarning, stacklevel=caller_level())


class JsonDecoderFactory(McapDecoderFactory):
    """An mcap ``DecoderFactory`` for the JSON topics (``twin/@events``, ``twin/@config``).

    ``make_reader(fh, decoder_factories=[mcap_protobuf.decoder.DecoderFactory(),
    JsonDecoderFactory()]).iter_decoded_messages()`` then decodes every topic of a session.
    """

    def decoder_for(self, message_encoding: str, schema: Any) -> Callable[[bytes], Any] | None:
        """``json.loads`` for message encoding ``json``, else None.

        Parameters
        ----------
        message_encoding : str
            The channel's message encoding.
        schema : mcap.records.Schema or None
            The channel's schema (not used: JSON needs none).

        Returns
        -------
        callable or None
            A decoder from the message bytes.
        """
        return json.loads if message_encoding == "json" else None
