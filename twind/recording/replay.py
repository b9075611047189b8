"""``twind replay``: publish a recording on the bus again, paced as it was recorded.

Every SampleBlock message is published, byte for byte as recorded, on its topic as key
(``twin/C1:SUS-ETMX_SUSPOS_IN1``); injection events (``twin/@events``) go to
``twin/@/<IFO>/events``; the configuration snapshot is not published. The pacing is the
recorded log times (the blocks' GPS starts) scaled by ``rate``: a consumer sees the same
blocks with the same GPS stamps and sequence numbers as the original subscribers did. With
``loop`` the recording starts again one block duration after its last block, with the same
bytes (GPS stamps and sequence numbers repeat).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from twind.bus.keys import control_key
from twind.recording.mcapfile import RawMessage, iter_raw_messages
from twind.recording.session import RecordingError, session_files
from twind.recording.writer import BLOCK_SCHEMA, CONFIG_TOPIC, EVENTS_TOPIC, scan_block


@dataclass
class ReplayStats:
    """What a replay published.

    Attributes
    ----------
    messages : int
    bytes : int
    loops : int
        Passes through the recording completed (or begun, if stopped).
    elapsed_s : float
        Wall-clock seconds from the first message published to the last.
    recorded_span_s : float
        Log-time span of one pass (first to last message), for comparison with elapsed_s.
    keys : set of str
    """

    messages: int = 0
    bytes: int = 0
    loops: int = 0
    elapsed_s: float = 0.0
    recorded_span_s: float = 0.0
    keys: set[str] = field(default_factory=set)


def check_rate(rate: float) -> float:
    """`rate` as :func:`replay` takes it (0 for inf: as fast as possible), checked."""
    if math.isnan(rate) or rate < 0:
        msg = f"replay rate must be >= 0 (0 or inf: as fast as possible), got {rate}"
        raise RecordingError(msg)
    return 0.0 if math.isinf(rate) else rate


def replay(path: str | Path | Iterable[str | Path], conf: zenoh.Config, rate: float = 1.0,
           loop: bool = False, *, ifo: str | None = None, events: bool = True,
           wait_subscribers: float = 2.0, stop: threading.Event | None = None,
           log: Callable[[str], None] | None = None) -> ReplayStats:
    """Publish a recording on the bus with its original pacing scaled by `rate`.

    Parameters
    ----------
    path : path or iterable of paths
        A recording: one file, a rotated set's name, or a list (see
        :func:`twind.recording.session.session_files`).
    conf : zenoh.Config
    rate : float
        Speed-up: 1 is as recorded, 2 twice as fast; 0 or ``inf`` as fast as possible.
    loop : bool
        Start again at the end, until `stop` is set.
    ifo : str, optional
        Interferometer of the events key; default the recording's.
    events : bool
        Publish the recorded injection events.
    wait_subscribers : float
        Seconds to wait, before the first message, for a subscriber to match it (a
        subscriber's declaration takes a moment to reach a new session); then publish
        regardless.
    stop : threading.Event, optional
        Set it to end the replay early.
    log : callable, optional
        Receives progress lines.

    Returns
    -------
    ReplayStats

    Raises
    ------
    RecordingError
        If the recording is missing or unreadable, or `rate` is negative.
    """
    rate = check_rate(rate)
    files = session_files(path)
    stop = stop or threading.Event()
    stats = ReplayStats()
    pubs: dict[str, Any] = {}
    with zenoh.open(conf) as session:
        def publisher(key: str) -> Any:
            pub = pubs.get(key)
            if pub is None:
                # BLOCK: a replay as fast as possible must not lose messages to a full queue
                pub = session.declare_publisher(
                    key, congestion_control=zenoh.CongestionControl.BLOCK)
                pubs[key] = pub
            return pub

        wall0: float | None = None  # wall time of the current pass's first message
        first_wall = last_wall = 0.0
        period_ns = 0  # one pass, from its first message to one block after its last
        while not stop.is_set():
            log0: int | None = None
            one = _Pass(files, ifo, events, first=stats.loops == 0)
            for key, m in one:
                if stop.is_set():
                    break
                pub = publisher(key)
                if wall0 is None:
                    _wait_for_subscriber(pub, wait_subscribers, stop)
                    wall0 = first_wall = time.monotonic()
                if log0 is None:
                    log0 = m.log_time
                    stats.loops += 1
                if rate:
                    delay = wall0 + (m.log_time - log0) / 1e9 / rate - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        break
                pub.put(m.data)
                last_wall = time.monotonic()
                stats.messages += 1
                stats.bytes += len(m.data)
                stats.keys.add(key)
                if stats.loops == 1:
                    stats.recorded_span_s = (m.log_time - log0) / 1e9
            if stop.is_set() or not loop:
                break
            if log0 is None:
                msg = f"{files[0]}: nothing to replay (no blocks or events)"
                raise RecordingError(msg)
            if stats.loops == 1:
                period_ns = max(one.end_ns - log0, round(stats.recorded_span_s * 1e9))
            # the next pass starts one block after the last one of this pass
            wall0 = wall0 + (period_ns / 1e9 / rate if rate else time.monotonic() - wall0)
            if log:
                log(f"twind replay: pass {stats.loops} done, {stats.messages} messages")
        stats.elapsed_s = last_wall - first_wall
        time.sleep(0.05)  # let the last messages leave before the session closes
    return stats


class _Pass:
    """One pass over a recording: each message to publish with its key, and (on the first
    pass) where the last block ends."""

    def __init__(self, files: list[Path], ifo: str | None, events: bool, first: bool) -> None:
        self.files, self.ifo, self.events, self.first = files, ifo, events, first
        self.end_ns = 0

    def __iter__(self) -> Iterator[tuple[str, RawMessage]]:
        for path in self.files:
            metadata: dict[str, dict[str, str]] = {}
            for m in iter_raw_messages(path, metadata=metadata):
                key = self._key(m, metadata)
                if key is not None:
                    yield key, m

    def _key(self, m: RawMessage, metadata: dict[str, dict[str, str]]) -> str | None:
        """Where `m` is published; None for what a replay leaves out (the configuration, or
        the events when not wanted)."""
        if m.topic == EVENTS_TOPIC:
            if not self.events:
                return None
            if self.ifo is None:
                self.ifo = metadata.get("twind.session", {}).get("ifo", "C1")
            return control_key(self.ifo, "events")
        if m.topic == CONFIG_TOPIC or m.schema_name != BLOCK_SCHEMA:
            return None
        if self.first:
            h = scan_block(m.data)
            self.end_ns = max(self.end_ns, m.log_time + round(h.n_samples / h.rate_hz * 1e9))
        return m.topic


def _wait_for_subscriber(pub: Any, timeout: float, stop: threading.Event) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not stop.is_set():
        status = pub.matching_status
        if bool(getattr(status, "matching", status)):
            time.sleep(0.05)  # the other subscribers of the session arrive together
            return
        time.sleep(0.01)
