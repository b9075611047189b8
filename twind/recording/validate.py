"""What a twin would never send: blocks and events a recorder keeps out of its file.

A twin's blocks carry their channel on their own key, a GPS time, a positive rate and a
sequence number MCAP can hold; its events are JSON objects with GPS times, and those about
an excitation carry its id, channel and start.
Anything else on the bus (a forged block, a careless client's test message) is skipped and
counted, so that one bad message neither stops a recording nor spoils its file.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from twind.recording.writer import TOPIC_ROOT, BlockHeader

__all__ = ["GPS_MAX", "RATE_MAX", "SEQUENCE_LIMIT", "block_problem", "event_problem",
           "excitation_problem"]

GPS_MAX = 5e9
"""Latest GPS time (s, year 2138) recorded; MCAP's log time, ns since 1970 in 64 bits, ends
in 2262."""
RATE_MAX = 1e7
"""Highest sample rate (Hz) taken for a real channel's."""
SEQUENCE_LIMIT = 2**32
"""MCAP numbers its messages in 32 bits."""


def _time(value: object) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value) and 0 <= value < GPS_MAX)


def block_problem(key: str, header: BlockHeader) -> str | None:
    """Why a block is not one a twin sends, or None.

    Parameters
    ----------
    key : str
        The key it arrived on.
    header : BlockHeader
        Its fields (:func:`twind.recording.writer.scan_block`).

    Returns
    -------
    str or None
    """
    if key != f"{TOPIC_ROOT}/{header.channel}":
        return f"a block of {header.channel!r} on another channel's key"
    if not _time(header.gps_start):
        return f"a block at GPS {header.gps_start!r}, not a time"
    if not (math.isfinite(header.rate_hz) and 0 < header.rate_hz <= RATE_MAX):
        return f"a block at {header.rate_hz!r} Hz"
    if header.sequence >= SEQUENCE_LIMIT:
        return f"a block numbered {header.sequence}, beyond MCAP's 32 bits"
    if header.n_samples == 0:
        return "a block without samples"
    return None


def event_problem(event: Any) -> str | None:
    """Why a decoded event is not one a twin publishes, or None.

    Parameters
    ----------
    event : object
        The event's JSON, decoded.

    Returns
    -------
    str or None
    """
    if not isinstance(event, Mapping):
        return "an event that is not a JSON object"
    for field in ("gps", "start_gps"):
        if field in event and not _time(event[field]):
            return f"an event with {field} {event[field]!r}, not a time"
    for field in ("event", "id", "channel"):
        if field in event and not isinstance(event[field], str):
            return f"an event whose {field} is not a string"
    return None


def excitation_problem(event: Mapping[str, Any]) -> str | None:
    """Why an event about an excitation lacks what a reader of it needs, or None: a start
    its id, channel and start time; a stop or an end its id and time.

    Parameters
    ----------
    event : mapping
        An event that passed :func:`event_problem`.

    Returns
    -------
    str or None
    """
    kind = event.get("event")
    needs = {"start": ("id", "channel", "start_gps"), "stop": ("id", "gps"),
             "end": ("id", "gps")}.get(kind, ())
    missing = [f for f in needs if f not in event]
    return f"a {kind!r} event without {', '.join(missing)}" if missing else None
