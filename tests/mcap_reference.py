"""An independent reading of MCAP sessions, for the tests: the one twind's fast engine
(:mod:`twind.recording.fastread`) must agree with, block by block."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from twind.recording.mcapfile import RawMessage, iter_raw_messages
from twind.recording.session import (
    Assembler,
    RecordingError,
    Session,
    session_files,
    some_names,
    warn_gaps,
)
from twind.recording.writer import (
    BLOCK_SCHEMA,
    CONFIG_METADATA,
    CONFIG_TOPIC,
    EVENTS_TOPIC,
    TOPIC_ROOT,
)


def _json(m: RawMessage) -> dict[str, Any]:
    """A JSON message's object."""
    try:
        return json.loads(m.data)
    except ValueError as err:
        msg = f"{m.file}: {m.topic}: a message is not JSON ({err})"
        raise RecordingError(msg) from None


def reference_session(path_or_paths: str | Path | Iterable[str | Path],
                 channels: Iterable[str] | None = None) -> Session:
    """A recording read by the plain Python path: mcap's own StreamReader message by
    message (:func:`~twind.recording.mcapfile.iter_raw_messages`), each SampleBlock decoded
    by protobuf; what :func:`~twind.recording.reader.read_session`'s engine must equal."""
    files = session_files(path_or_paths)
    order = list(dict.fromkeys(channels)) if channels is not None else None
    wanted = set(order) if order is not None else None
    wanted_topics = None if wanted is None else {f"{TOPIC_ROOT}/{c}" for c in wanted}

    def keep(topic: str) -> bool:
        return wanted_topics is None or topic in wanted_topics or topic.startswith(
            f"{TOPIC_ROOT}/@")

    problems: list[str] = []
    assembler = Assembler(wanted)
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
            msg = (f"{some_names(missing)} not in {files[0]}"
                   f"{f' (and {len(files) - 1} more files)' if len(files) > 1 else ''}")
            raise RecordingError(msg)
        joined = {name: joined[name] for name in order}  # in the order asked for
    complete = not problems
    warn_gaps(joined, problems)
    return Session(files, joined, events, configs, complete, problems)