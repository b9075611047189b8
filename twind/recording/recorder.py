"""``twind record``: subscribe to twin channels on the bus and write them to MCAP.

The Zenoh callback only appends the received bytes to a queue; one writer thread scans each
block's header, stamps it, and writes it with the low-level MCAP writer (the bytes as
received, never re-serialized). See :mod:`twind.recording.writer` for the file layout.

Rotation: with ``rotate_bytes`` or ``rotate_seconds`` the recording is a set of complete
MCAP files named after ``out`` with a four-digit index: ``-o run.mcap`` writes
``run-0001.mcap``, ``run-0002.mcap``, ... A file is closed (summary and footer written) and
the next one begun before the first block that would take the file past ``rotate_bytes``
(counting messages not yet compressed at their full size), or whose GPS start is
``rotate_seconds`` or more after the file's first block. Every file starts with the
configuration snapshot, so each can be read on its own; :func:`twind.recording.reader.
read_session` given ``run.mcap`` reads the set in order. Without rotation the file is
exactly ``out``.
"""

from __future__ import annotations

import json
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any

import numpy as np
import zenoh

import twind
from twind import DOFS, OSEMS
from twind.bus.codec import SampleBlock
from twind.bus.keys import all_data, control_key
from twind.bus.session import free_port, zenoh_config
from twind.channels import TEST_POINTS, dof_channel, osem_channel
from twind.recording.session import RecordingError, rotated_name
from twind.recording.sources import Roster
from twind.recording.validate import block_problem, event_problem
from twind.recording.writer import CHUNK_BYTES, CHUNK_SECONDS, BlockHeader, McapSession, scan_block
from twind.timeutil import now_gps

_STOP = object()  # the writer thread's end-of-queue marker
_DATA, _EVENT = 0, 1


@dataclass
class RecordingStats:
    """What a recording wrote.

    Attributes
    ----------
    files : list of Path
    blocks : int
        SampleBlock messages written.
    block_bytes : int
        Their bytes (as on the bus).
    events : int
    channels : set of str
        Topics written.
    dropped : int
        Messages dropped because the writer fell more than ``max_backlog_bytes`` behind.
    undecodable : int
        Messages on data keys that were not SampleBlocks (skipped).
    invalid : int
        Blocks and events no twin sends (:mod:`twind.recording.validate`: a forged time,
        rate, sequence or channel; a block overlapping the one before it), skipped.
    elapsed_s : float
        Wall-clock seconds from subscribing to the end.
    max_backlog_bytes : int
        Largest queue of received but unwritten bytes seen.
    restarts : int
        Times the twin restarted during the recording (its block numbering began again),
        each marked in the file by a ``twin_restart`` event.
    silences : int
        Times no block came for :attr:`Recorder.silence_s` (the twin stopped or became
        unreachable), each marked by a ``twin_silent`` event.
    unserved : int
        Channels whose blocks came from no twin that serves their optic
        (:mod:`twind.recording.sources`), each marked by an ``unserved`` event.
    """

    files: list[Path] = field(default_factory=list)
    blocks: int = 0
    block_bytes: int = 0
    events: int = 0
    channels: set[str] = field(default_factory=set)
    dropped: int = 0
    undecodable: int = 0
    invalid: int = 0
    elapsed_s: float = 0.0
    max_backlog_bytes: int = 0
    restarts: int = 0
    silences: int = 0
    unserved: int = 0

    def summary(self) -> str:
        """One line for the user."""
        names = ", ".join(str(p) for p in self.files[:3]) + (
            f" and {len(self.files) - 3} more" if len(self.files) > 3 else "")
        line = (f"recorded {self.blocks} blocks of {len(self.channels)} channel(s) "
                f"({self.block_bytes / 1e6:.1f} MB) and {self.events} event(s) in "
                f"{self.elapsed_s:.1f} s to {names or 'no file'}")
        if not self.blocks:
            line += " (nothing arrived: is a twin publishing on the endpoints given?)"
        if self.dropped:
            line += f"; DROPPED {self.dropped} messages: the disk could not keep up"
        if self.undecodable:
            line += f"; skipped {self.undecodable} messages that were not SampleBlocks"
        if self.invalid:
            line += f"; skipped {self.invalid} blocks or events no twin sends"
        if self.unserved:
            line += (f"; {self.unserved} channel(s) came from no twin that serves them, "
                     "each marked in the file")
        if self.restarts or self.silences:
            line += (f"; the twin fell silent {self.silences} time(s) and restarted "
                     f"{self.restarts} time(s), each marked in the file")
        return line


class Recorder:
    """Record twin channels (and injection events) from the bus to MCAP.

    Parameters
    ----------
    conf : zenoh.Config
        Session configuration, e.g. ``twind.bus.session.zenoh_config(connect=[...])``.
    out : str or Path
        File to write; with rotation, the stem of the numbered files (module docstring).
        Existing files are refused, never overwritten.
    keyexprs : sequence of str
        Data key expressions; ``twin/**`` is every channel. Injection events
        (``twin/@/<IFO>/events``, which ``twin/**`` does not match) are recorded too unless
        `events` is false.
    ifo : str
        Interferometer prefix, for the events and status keys.
    rotate_bytes : int, optional
        Start a new file before one would exceed this many bytes.
    rotate_seconds : float, optional
        Start a new file when the data reach this many seconds (GPS) past its first block.
    events : bool
        Record ``twin/@/<IFO>/events`` on topic ``twin/@events``.
    status_timeout : float
        Seconds to wait for a twin service to answer ``twin/@/<IFO>/status``, whose reply
        goes into the configuration snapshot.
    chunk_bytes, chunk_seconds : int, float
        Chunk closing thresholds (:mod:`twind.recording.writer`).
    max_backlog_bytes : int
        Received-but-unwritten bytes beyond which new messages are dropped (and counted)
        rather than exhausting memory.
    log : callable, optional
        Receives progress lines; default prints to stderr.
    silence_s : float
        Seconds without a block after which the twin is reported gone (it stopped or is
        unreachable); the recorder goes on and marks its return.
    """

    def __init__(self, conf: zenoh.Config, out: str | Path,
                 keyexprs: Sequence[str] = ("twin/**",), ifo: str = "C1",
                 rotate_bytes: int | None = None, rotate_seconds: float | None = None, *,
                 events: bool = True, status_timeout: float = 1.0,
                 chunk_bytes: int = CHUNK_BYTES, chunk_seconds: float = CHUNK_SECONDS,
                 max_backlog_bytes: int = 1 << 30,
                 log: Callable[[str], None] | None = None, silence_s: float = 5.0) -> None:
        self.conf = conf
        self.out = Path(out)
        self.keyexprs = tuple(keyexprs) or (all_data(),)
        self.ifo = ifo
        for name, value in (("rotate_bytes", rotate_bytes), ("rotate_seconds", rotate_seconds)):
            if value is not None and not (value > 0 and math.isfinite(value)):
                msg = f"{name} must be positive, got {value}"
                raise RecordingError(msg)
        self.rotate_bytes = rotate_bytes
        self.rotate_seconds = rotate_seconds
        self.events = events
        self.status_timeout = status_timeout
        self.chunk_bytes, self.chunk_seconds = chunk_bytes, chunk_seconds
        self.max_backlog_bytes = max_backlog_bytes
        self._log = log or (lambda line: print(line, file=sys.stderr, flush=True))
        if not self.out.parent.is_dir():
            msg = f"{self.out.parent}: no such directory for the recording"
            raise RecordingError(msg)
        first = self._name(1)
        clash = [p for p in (self.out, first) if p.exists()]
        if clash:
            msg = f"{clash[0]} exists; twind does not overwrite recordings"
            raise RecordingError(msg)
        self.stats = RecordingStats()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        # callbacks may run on several Zenoh threads at once (several subscribers or peers),
        # so their counters take a lock; _done_bytes is the writer thread's alone
        self._count_lock = threading.Lock()
        self._enq_bytes = self._done_bytes = 0
        self._dropped = 0
        self._failed = False
        self._error: BaseException | None = None
        self._stop = threading.Event()
        self._session: zenoh.Session | None = None
        self._subs: list[Any] = []
        self._thread: threading.Thread | None = None
        self._file: McapSession | None = None
        self._config: dict[str, Any] = {}
        self._undecodable_keys: set[str] = set()
        self._t_start = 0.0
        self.silence_s = silence_s
        self._last_sequence: dict[str, int] = {}  # the writer thread's, as below
        self._ends: dict[str, float] = {}  # GPS where each channel's last block ends
        self._twin_of: dict[str, str] = {}  # the twin that sent each channel's last block
        self._roster: Roster | None = None  # which twins serve which optics
        self._sourced: dict[str, str] = {}  # channel -> its twin, told or marked unserved
        self._last_block: tuple[float, float] | None = None  # (monotonic, GPS end)
        self._silent = False

    @property
    def rotating(self) -> bool:
        """Whether the recording is a numbered set of files."""
        return bool(self.rotate_bytes or self.rotate_seconds)

    @property
    def files(self) -> list[Path]:
        """Files written so far."""
        return list(self.stats.files)

    def _name(self, index: int) -> Path:
        return rotated_name(self.out, index) if self.rotating else self.out

    # --- life cycle ---------------------------------------------------------------------

    def start(self) -> None:
        """Open the session and subscribe, snapshot the configuration, open the file.

        The subscriptions come first, the moment the session is open: whatever arrives
        while the status query and the file's creation take their time waits in the queue,
        so an event published just after a twin answers its first query is not lost.
        """
        if self._session is not None:
            msg = "this Recorder has already been started"
            raise RecordingError(msg)
        self._session = zenoh.open(self.conf)
        try:
            for key in self.keyexprs:
                self._subs.append(self._session.declare_subscriber(key, self._on_data))
            if self.events:
                self._subs.append(self._session.declare_subscriber(
                    control_key(self.ifo, "events"), self._on_event))
            self._config = self._snapshot()
            self._roster = Roster(self._session, self.ifo, self.status_timeout)
            self._open_file(self._config["gps"])
            self._thread = threading.Thread(target=self._write_loop, name="twind-record",
                                            daemon=True)
            self._thread.start()
        except BaseException:
            self._teardown()
            raise
        self._t_start = time.monotonic()
        if not self._connected():
            self._log("twind record: warning: no Zenoh peer or router reached yet; blocks "
                      "are written once one is (check --connect/--listen)")
        extra = f" and {control_key(self.ifo, 'events')}" if self.events else ""
        self._log(f"twind record: recording {', '.join(self.keyexprs)}{extra} to "
                  f"{self.stats.files[0]}{' (rotating)' if self.rotating else ''}; "
                  "SIGINT or SIGTERM ends the recording")

    def _connected(self) -> bool:
        info = self._session.info
        try:
            return bool(list(info.routers_zid()) or list(info.peers_zid()))
        except (AttributeError, zenoh.ZError):  # an API change must not stop a recording
            return True

    def stop(self) -> RecordingStats:
        """Unsubscribe, write everything received, close the file (summary and footer).

        Returns
        -------
        RecordingStats

        Raises
        ------
        RecordingError
            If writing failed (e.g. the disk filled); the files hold what was written.
        """
        if self._session is None:
            return self.stats
        self._teardown()
        self.stats.elapsed_s = time.monotonic() - self._t_start
        self.stats.dropped = self._dropped
        if self._error is not None:
            msg = f"recording to {self.stats.files[-1]} failed: {self._error}"
            raise RecordingError(msg) from self._error
        return self.stats

    def _teardown(self) -> None:
        # order matters: no callback may enqueue after the end marker
        for sub in self._subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass
        self._subs.clear()
        if self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join()
            self._thread = None
        if self._roster is not None:
            self._roster.close()
            self._roster = None
        if self._file is not None:
            try:
                self._file.close()
            except OSError as err:
                self._error = self._error or err
            self._file = None
        if self._session is not None:
            self._session.close()
            self._session = None

    def run(self, duration: float | None = None, parent: int | None = None) -> RecordingStats:
        """Record until `duration` seconds (wall clock) have passed, SIGINT or SIGTERM, or,
        with `parent`, until process `parent` is no longer this one's parent (it exited or
        was killed: a recorder started by ``twind serve --record`` ends with it).

        Each ends the recording cleanly (every received block written, summary and footer).
        Signal handlers are installed only when called from the main thread, and restored
        on return.

        Parameters
        ----------
        duration : float, optional
            Seconds of wall clock to record; None records until a signal.
        parent : int, optional
            The process id of the process that started this recorder.

        Returns
        -------
        RecordingStats

        Raises
        ------
        RecordingError
            If `duration` is not positive, the recorder was started already, or writing
            failed (e.g. the disk filled); the files hold what was written.
        """
        if duration is not None and not duration > 0:
            msg = f"duration must be positive, got {duration}"
            raise RecordingError(msg)
        previous: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            def on_signal(signum: int, frame: FrameType | None) -> None:
                self._stop.set()

            for sig in (signal.SIGINT, signal.SIGTERM):
                previous[sig] = signal.signal(sig, on_signal)
        try:
            self.start()
            end = None if duration is None else time.monotonic() + duration
            while not self._stop.is_set():
                left = 0.2 if end is None else min(0.2, end - time.monotonic())
                if left <= 0:
                    break
                if parent is not None and os.getppid() != parent:
                    self._log(f"twind record: process {parent}, which started this recorder, "
                              "is gone; closing the recording")
                    break
                self._stop.wait(left)
        finally:
            try:
                # our handlers stay while closing: a second Ctrl-C must not cut the summary
                stats = self.stop()
            finally:
                for sig, handler in previous.items():
                    signal.signal(sig, handler)
        return stats

    def request_stop(self) -> None:
        """Make :meth:`run` return (from another thread)."""
        self._stop.set()

    def __enter__(self) -> Recorder:
        self.start()
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    # --- configuration snapshot -------------------------------------------------------------

    def _snapshot(self) -> dict[str, Any]:
        """What the recorder knows, plus the twin service's status if one answers."""
        key = control_key(self.ifo, "status")
        status: Any = None
        problem = f"no twin service answered {key} within {self.status_timeout:g} s"
        try:
            for reply in self._session.get(key, timeout=self.status_timeout):
                if reply.ok is not None:
                    raw = reply.ok.payload.to_bytes()
                    try:
                        status = json.loads(raw)
                    except ValueError:
                        status = raw.decode(errors="replace")
                    problem = None
                    break
                problem = f"{key} answered an error: {reply.err.payload.to_string()}"
        except zenoh.ZError as err:
            problem = f"{key}: {err}"
        return {"ifo": self.ifo, "gps": now_gps(), "writer": "twind record",
                "keyexprs": list(self.keyexprs), "status": status, "status_problem": problem,
                "recorder": {"twind": twind.__version__, "host": socket.gethostname(),
                             "pid": os.getpid()}}

    # --- the Zenoh side: enqueue only ---------------------------------------------------

    def _on_data(self, sample: zenoh.Sample) -> None:
        self._enqueue(_DATA, sample)

    def _on_event(self, sample: zenoh.Sample) -> None:
        self._enqueue(_EVENT, sample)

    def _enqueue(self, kind: int, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        with self._count_lock:
            if self._failed or self._enq_bytes - self._done_bytes > self.max_backlog_bytes:
                self._dropped += 1
                return
            self._enq_bytes += len(data)
        self._queue.put((kind, str(sample.key_expr), data))

    # --- the writer thread --------------------------------------------------------------

    def _open_file(self, gps: float) -> None:
        path = self._name(len(self.stats.files) + 1)
        self._file = McapSession(path, self.ifo, {**self._config, "gps": gps},
                                 writer="twind record", chunk_bytes=self.chunk_bytes)
        self.stats.files.append(path)

    def _write_loop(self) -> None:
        get, stats = self._queue.get, self.stats
        try:
            while True:
                try:
                    item = get(timeout=0.1)
                except queue.Empty:
                    self._file.maybe_flush(self.chunk_seconds)
                    self._check_silence()
                    continue
                if item is _STOP:
                    return
                kind, key, data = item
                backlog = self._enq_bytes - self._done_bytes  # sampled as it is largest
                if backlog > stats.max_backlog_bytes:
                    stats.max_backlog_bytes = backlog
                self._done_bytes += len(data)
                if kind == _DATA:
                    self._write_block(key, data)
                else:
                    self._write_event(key, data)
                self._file.maybe_flush(self.chunk_seconds)
        except BaseException as err:  # noqa: BLE001 - reported by stop()
            self._error, self._failed = err, True
            self._stop.set()
            # drain, so that the queue does not grow while run() notices
            while self._queue.get() is not _STOP:
                pass

    def _write_event(self, key: str, data: bytes) -> None:
        try:
            event = json.loads(data)
        except ValueError:
            self.stats.undecodable += 1
            self._warn_once(key, "an event that is not JSON")
            return
        problem = event_problem(event)
        if problem:
            self.stats.invalid += 1
            self._warn_once(key, problem)
            return
        self._file.write_event(event)
        self.stats.events += 1

    def _write_block(self, key: str, data: bytes) -> None:
        try:
            header = scan_block(data)
        except ValueError as err:
            self.stats.undecodable += 1
            self._warn_once(key, f"not a twind.v1.SampleBlock ({err})")
            return
        problem = block_problem(key, header) or self._overlap(key, header)
        if problem:
            self.stats.invalid += 1
            self._warn_once(key, problem)
            return
        f = self._file
        if self.rotate_bytes and f.messages > 1 and \
                f.size + f._pending + len(data) > self.rotate_bytes:
            self._rotate(header.gps_start)
        elif self.rotate_seconds and f.first_gps is not None and \
                header.gps_start - f.first_gps >= self.rotate_seconds:
            self._rotate(header.gps_start)
        self._follow(key, header)
        self._file.write_block(data, header, topic=key)
        self._check_source(header)
        self.stats.blocks += 1
        self.stats.block_bytes += len(data)
        self.stats.channels.add(key)

    def _overlap(self, key: str, header: BlockHeader) -> str | None:
        """A block of a channel that repeats, overlaps or numbers below the one before it from
        the same twin, or that another twin sends while one publishes the channel: not
        written (a reader takes a file's blocks of a channel to follow one another)."""
        last = self._last_sequence.get(key)
        end = self._ends.get(key)
        if last is None or end is None:
            return None
        twin = self._twin_of.get(key, "")
        if header.twin != twin:
            if twin and not header.twin:
                return f"a block naming no twin, while {twin} publishes the channel"
            if header.sequence <= last:
                return None  # the channel's twin restarted: a new twin numbers from 0
            return f"a block from twin {header.twin}, while another publishes the channel"
        if header.sequence < last:
            if header.twin:
                return (f"a block numbered {header.sequence} after {last} from the same twin "
                        f"{header.twin}: forged or out of order, not a restart")
            return None  # blocks that do not name their twin: a restart
        if header.sequence == last:
            return "the same block twice"
        if header.gps_start < end - 0.5 / header.rate_hz:
            return f"a block at GPS {header.gps_start:.6f}, inside the one before it"
        return None

    def _follow(self, key: str, header: BlockHeader) -> None:
        """Mark the twin's return after a silence and its restarts (a channel's numbering
        beginning again, from a new twin when blocks name it) in the file, as events."""
        if self._silent:
            self._silent = False
            self._log(f"twind record: blocks arrive again (GPS {header.gps_start:.3f})")
        last = self._last_sequence.get(key)
        if last is not None and header.sequence <= last:  # _overlap passed it: a restart
            self.stats.restarts += 1
            before = self._twin_of.get(key, "")
            self._file.write_event({"event": "twin_restart", "gps": header.gps_start,
                                    "channel": key, "after_sequence": last,
                                    "sequence": header.sequence, "twin": header.twin,
                                    "after_twin": before})
            self.stats.events += 1
            self._log(f"twind record: the twin restarted (its blocks number from "
                      f"{header.sequence} again at GPS {header.gps_start:.3f}); marked in "
                      "the file")
            for k in [k for k, t in self._twin_of.items() if t == before]:  # one mark a twin
                self._last_sequence.pop(k, None)
        self._last_sequence[key] = header.sequence
        self._twin_of[key] = header.twin
        end = header.gps_start + header.n_samples / header.rate_hz
        self._ends[key] = end
        self._last_block = (time.monotonic(), end)

    def _check_source(self, header: BlockHeader) -> None:
        """Mark, once a file, a channel whose blocks come from no twin that serves it."""
        if self._roster is None or self._sourced.get(header.channel) == header.twin:
            return
        known, why = self._roster.verdict(header.twin, header.channel)
        if not known:
            return
        self._sourced[header.channel] = header.twin
        if why:
            self.stats.unserved += 1
            self._file.write_event({"event": "unserved", "gps": header.gps_start,
                                    "channel": header.channel, "twin": header.twin,
                                    "why": why})
            self.stats.events += 1
            self._log(f"twind record: {header.channel} comes from no twin that serves it "
                      f"({why}); recorded, and marked in the file")

    def _check_silence(self) -> None:
        """Report, once, a twin that sent no block for :attr:`silence_s`."""
        if self._silent or self._last_block is None:
            return
        since, gps = self._last_block
        if time.monotonic() - since < self.silence_s:
            return
        self._silent = True
        self.stats.silences += 1
        self._file.write_event({"event": "twin_silent", "gps": gps,
                                "seconds": self.silence_s})
        self.stats.events += 1
        self._log(f"twind record: no block for {self.silence_s:g} s since GPS {gps:.3f}: the "
                  "twin stopped or is unreachable; still recording, its return is marked")

    def _rotate(self, gps: float) -> None:
        self._file.close()
        self._file = None
        self._sourced.clear()  # each file marks its own channels
        self._open_file(gps)

    def _warn_once(self, key: str, what: str) -> None:
        if key not in self._undecodable_keys:
            self._undecodable_keys.add(key)
            self._log(f"twind record: {key}: skipping {what}")


# --- benchmark -------------------------------------------------------------------------------


def synthetic_block(channel: str, sequence: int, gps0: float = 1.4e9, n: int = 1024,
                    rate: float = 16384.0, seed: int | None = None, twin: str = "") -> bytes:
    """The bus bytes of a deterministic SampleBlock (for tests and benchmarks).

    Samples are Gaussian noise from a generator seeded by the channel name and sequence
    (`seed` overrides), so that they are as incompressible as the twin's noise and can be
    regenerated for checking.

    Parameters
    ----------
    channel : str
        The channel, e.g. ``C1:SUS-ETMX_SUSPOS_IN1``.
    sequence : int
        The block's sequence number; its GPS start is ``gps0 + sequence * n / rate``.
    gps0 : float
        GPS time of block 0 (s).
    n : int
        Samples per block.
    rate : float
        Sample rate (Hz).
    seed : int, optional
        Seed of the noise, instead of one from `channel` and `sequence`.
    twin : str
        The publishing twin's identity the block names.

    Returns
    -------
    bytes
        The encoded block (unit ``um``), as the twin publishes it.
    """

    s = seed if seed is not None else zlib.crc32(channel.encode()) * 1_000_003 + sequence
    x = np.random.default_rng(s).standard_normal(n)
    return SampleBlock(channel, gps0 + sequence * n / rate, rate, sequence, x, "um",
                       twin).encode()


def forty_meter_channels(ifo: str = "C1") -> list[str]:
    """The 210 channel names of the 40m's ten optics."""

    optics = ("ETMX", "ETMY", "ITMX", "ITMY", "BS", "PRM", "SRM", "MC1", "MC2", "MC3")
    return [name for optic in optics for name in
            [dof_channel(ifo, optic, d, p) for d in DOFS for p in TEST_POINTS]
            + [osem_channel(ifo, optic, o) for o in OSEMS]]


def recording_benchmark(seconds: float = 2.0, block_samples: int = 1024,
                        rate: float = 16384.0, path: str | Path | None = None,
                        end_to_end: bool = False) -> dict[str, float]:
    """Write throughput of the recorder for the 40m channel set.

    Pre-encodes `seconds` of blocks of the 210 channels (16 blocks/s each of 1024 float64
    samples at 16384 Hz: 3360 blocks/s, 27.6 MB/s) and times the recorder's writer path on
    them: header scan, MCAP message, zstd chunks, file. With `end_to_end`, also records a
    real-time stream of the same blocks published by a subprocess over Zenoh on loopback
    and reports whether every block arrived.

    Parameters
    ----------
    seconds : float
        Seconds of 40m data to write.
    block_samples : int
        Samples per block.
    rate : float
        Sample rate of every channel (Hz).
    path : path, optional
        The MCAP file to write (and keep); by default a temporary one.
    end_to_end : bool
        Also time the stream over Zenoh.

    Returns
    -------
    dict
        ``blocks_per_s``, ``mb_per_s`` (payload, 10^6 bytes), ``x_realtime`` (throughput over
        the 40m's rate), ``file_mb``, ``payload_mb``, and with `end_to_end`: ``e2e_blocks``,
        ``e2e_expected``, ``e2e_dropped``, ``e2e_max_backlog_mb``.

    Raises
    ------
    RecordingError
        With `end_to_end`, if the publishing subprocess failed.
    """

    names = forty_meter_channels()
    per_s = rate / block_samples
    n_seq = max(1, round(seconds * per_s))
    blocks = [synthetic_block(c, k, n=block_samples, rate=rate) for k in range(n_seq)
              for c in names]
    payload = sum(len(b) for b in blocks)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(path) if path else Path(tmp) / "bench.mcap"
        t0 = time.perf_counter()
        with McapSession(out, "C1", writer="recording_benchmark") as f:
            for data in blocks:
                header = scan_block(data)
                f.write_block(data, header, topic=f"twin/{header.channel}")
        wall = time.perf_counter() - t0
        result = {"blocks_per_s": len(blocks) / wall, "mb_per_s": payload / wall / 1e6,
                  "x_realtime": len(blocks) / wall / (len(names) * per_s),
                  "file_mb": out.stat().st_size / 1e6, "payload_mb": payload / 1e6}
        if end_to_end:
            result.update(_end_to_end(Path(tmp), seconds, names, block_samples, rate))
    return result


def _end_to_end(tmp: Path, seconds: float, names: list[str], block_samples: int,
                rate: float) -> dict[str, float]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh_config(listen=[endpoint])
    recorder = Recorder(conf, tmp / "e2e.mcap", log=lambda line: None, status_timeout=0.1)
    recorder.start()
    n_seq = max(1, round(seconds * rate / block_samples))
    code = ("import sys; from twind.recording.recorder import _publish_paced as p; "
            f"p({endpoint!r}, {n_seq}, {block_samples}, {rate})")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60 + 2 * seconds, check=False)
    time.sleep(0.5)
    stats = recorder.stop()
    if proc.returncode:
        msg = f"benchmark publisher failed: {proc.stderr.strip()[-500:]}"
        raise RecordingError(msg)
    return {"e2e_blocks": stats.blocks, "e2e_expected": n_seq * len(names),
            "e2e_dropped": stats.dropped, "e2e_max_backlog_mb": stats.max_backlog_bytes / 1e6}


def _matching(publisher: Any) -> bool:
    """Whether a subscriber matches `publisher` (a bool or a MatchingStatus, by version)."""
    status = publisher.matching_status
    return bool(getattr(status, "matching", status))


def _publish_paced(endpoint: str, n_seq: int, block_samples: int, rate: float) -> None:
    """Publish `n_seq` blocks of every 40m channel at the real-time pace (benchmark helper)."""

    names = forty_meter_channels()
    with zenoh.open(zenoh_config(connect=[endpoint])) as session:
        pubs = {c: session.declare_publisher(f"twin/{c}",
                                             congestion_control=zenoh.CongestionControl.BLOCK)
                for c in names}
        deadline = time.monotonic() + 10
        while not _matching(next(iter(pubs.values()))):
            if time.monotonic() > deadline:
                raise SystemExit("no recorder matched")
            time.sleep(0.01)
        t0 = time.monotonic()
        period = block_samples / rate
        for k in range(n_seq):
            # encode, then publish at the block's wall-clock time, as a real-time twin does
            batch = [(pubs[c], synthetic_block(c, k, n=block_samples, rate=rate))
                     for c in names]
            delay = t0 + (k + 1) * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            for pub, data in batch:
                pub.put(data)
        time.sleep(0.2)
