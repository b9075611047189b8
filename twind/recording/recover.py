"""``twind recover``: a valid MCAP file from a killed or damaged one, as ``mcap recover``
does: every message up to the last complete chunk, with its schema and channel, and the
file's metadata, written again with a summary and a chunk index, so that any MCAP reader
(``mcap.reader.make_reader`` included) takes it."""

from __future__ import annotations

from pathlib import Path

from mcap.writer import CompressionType, IndexType
from mcap.writer import Writer as McapWriter

from twind.recording.mcapfile import iter_raw_messages
from twind.recording.session import RecordingError
from twind.recording.writer import library_label


def recover(source: str | Path, out: str | Path) -> tuple[int, list[str]]:
    """Write what `source` still holds to `out` (never overwritten).

    Parameters
    ----------
    source : path
        The killed or damaged MCAP file.
    out : path
        The MCAP file to write; removed again if writing fails.

    Returns
    -------
    messages : int
        Messages written.
    problems : list of str
        What was lost and why (empty for a complete file).

    Raises
    ------
    RecordingError
        If `source` is no MCAP file or `out` exists.
    """
    out = Path(out)
    if out.exists():
        msg = f"{out} exists; twind does not overwrite recordings"
        raise RecordingError(msg)
    problems: list[str] = []
    metadata: dict[str, dict[str, str]] = {}
    schemas: dict[tuple[str, str, bytes], int] = {}
    channels: dict[tuple[str, int], int] = {}
    n = 0
    with open(out, "xb") as fh:
        try:
            writer = McapWriter(fh, compression=CompressionType.ZSTD, enable_crcs=True,
                                index_types=IndexType.ALL)
            writer.start(profile="", library=library_label())
            for m in iter_raw_messages(source, problems, metadata=metadata):
                key = (m.schema_name, m.schema_encoding, m.schema_data)
                if key not in schemas:
                    schemas[key] = (writer.register_schema(*key) if m.schema_name else 0)
                sid = schemas[key]
                if (m.topic, sid) not in channels:
                    channels[m.topic, sid] = writer.register_channel(m.topic,
                                                                     m.message_encoding, sid)
                writer.add_message(channels[m.topic, sid], m.log_time, m.data, m.log_time,
                                   m.sequence)
                n += 1
            for name, record in metadata.items():
                writer.add_metadata(name, record)
            writer.finish()
        except BaseException:
            fh.close()
            out.unlink(missing_ok=True)
            raise
    return n, problems
