"""What a recording holds: each channel's samples joined across blocks and files, with its
sequence numbers and gaps, the injection events and configuration snapshots; and the errors
and warnings of reading one."""

from __future__ import annotations

import sys
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from twind.errors import TwindError, TwindWarning
from twind.recording.writer import TOPIC_ROOT, BlockHeader, scan_block


class RecordingError(TwindError):
    """A recording cannot be read, or does not hold what was asked of it."""


class TruncatedRecordingWarning(TwindWarning):
    """A recording ends without its summary: its writer was killed or the disk filled."""


class DamagedRecordingWarning(TwindWarning):
    """A chunk inside a complete recording cannot be read; the rest is read by its index."""


class GapWarning(TwindWarning):
    """Blocks of a channel are missing (sequence numbers or GPS times jump)."""


def rotated_name(out: str | Path, index: int) -> Path:
    """``run-0001.mcap`` for ``("run.mcap", 1)``: the name of a rotated recording's file.

    Parameters
    ----------
    out : path
        The name the recording was given; without a suffix, ``.mcap`` is added.
    index : int
        The file's number, from 1.

    Returns
    -------
    Path
        In the directory of `out`.
    """
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
            msg = f"{name} is not in the recording; it holds {some_names(self.channels)}"
            raise RecordingError(msg) from None

    def __contains__(self, name: object) -> bool:
        return name in self.channels

    def __iter__(self) -> Iterator[str]:
        return iter(self.channels)

    def __len__(self) -> int:
        return len(self.channels)


def some_names(names: Iterable[str], n: int = 4) -> str:
    """The first `n` of `names` and how many more, for a message.

    Parameters
    ----------
    names : iterable of str
        Channel names.
    n : int
        How many to name.

    Returns
    -------
    str

    Examples
    --------
    >>> some_names(["C1:A", "C1:B", "C1:C"], n=2)
    'C1:A, C1:B and 1 more'
    """
    names = list(names)
    if not names:
        return "no channels"
    more = f" and {len(names) - n} more" if len(names) > n else ""
    return ", ".join(names[:n]) + more


@dataclass
class Block:
    """One SampleBlock as read, before its channel is joined."""

    sequence: int
    gps_start: float
    rate: float
    unit: str
    samples: NDArray[np.float64]


def block_samples(data: bytes, header: BlockHeader) -> NDArray[np.float64]:
    """The samples of the SampleBlock `data` whose header is `header`.

    Parameters
    ----------
    data : bytes
        The block's protobuf bytes.
    header : BlockHeader
        As :func:`~twind.recording.writer.scan_block` gives it for `data`.

    Returns
    -------
    numpy.ndarray
        The samples, float64; a read-only view of `data` when they lie in one run.
    """
    # a view on the message bytes: no copy until the channel is joined
    if len(header.runs) == 1:
        offset, n = header.runs[0]
        return np.frombuffer(data, dtype="<f8", count=n // 8, offset=offset)
    if not header.runs:
        return np.empty(0)
    return np.concatenate([np.frombuffer(data, dtype="<f8", count=n // 8, offset=o)
                           for o, n in header.runs])


def join_blocks(name: str, blocks: list[Block]) -> Channel:
    """One channel from its blocks in recorded order: NaN in gaps, errors on overlaps.

    A block recorded twice in a row (same sequence number, GPS start and samples) is kept
    once.

    Parameters
    ----------
    name : str
        The channel, for the gaps and messages.
    blocks : list of Block
        At least one, in recorded order.

    Returns
    -------
    Channel

    Raises
    ------
    RecordingError
        If the sample rate is not positive or changes, or a block overlaps the one before
        or lies off its sample grid.
    """
    rate = blocks[0].rate
    if not rate > 0:
        msg = f"{name}: block {blocks[0].sequence} has sample rate {rate}"
        raise RecordingError(msg)
    pieces: list[NDArray[np.float64]] = []
    gaps: list[Gap] = []
    kept: list[Block] = []
    prev: Block | None = None
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
    """A block's header and channel name (its topic's, when the block names none).

    Parameters
    ----------
    data : bytes
        The block's protobuf bytes.
    topic : str
        The MCAP topic (or Zenoh key) it came under, e.g. ``twin/C1:SUS-ETMX_SUSPOS_IN1``.

    Returns
    -------
    header : BlockHeader
    name : str

    Raises
    ------
    RecordingError
        If `data` is not a SampleBlock.
    """
    try:
        header = scan_block(data)
    except ValueError as err:
        msg = f"{topic}: not a twind.v1.SampleBlock ({err})"
        raise RecordingError(msg) from None
    return header, header.channel or topic.removeprefix(f"{TOPIC_ROOT}/")


def caller_level() -> int:
    """The ``stacklevel`` that makes a warning raised by the function calling this one name
    the first line outside :mod:`twind.recording`: the reader's caller, whichever of the
    reader's paths warned."""
    frame, level = sys._getframe(1), 1
    while frame is not None and Path(frame.f_code.co_filename).parent == _HERE:
        frame, level = frame.f_back, level + 1
    return level


_HERE = Path(__file__).parent


def warn_gaps(channels: dict[str, Channel], problems: list[str]) -> None:
    """One :class:`GapWarning` for the gaps of `channels`, also listed in `problems`.

    Parameters
    ----------
    channels : dict of str to Channel
        The channels read.
    problems : list of str
        Receives the warning's text; nothing when there is no gap.

    Warns
    -----
    GapWarning
    """
    gaps = [g for ch in channels.values() for g in ch.gaps]
    if not gaps:
        return
    lines = [str(g) for g in gaps[:5]]
    more = f"; and {len(gaps) - 5} more" if len(gaps) > 5 else ""
    text = (f"{len(gaps)} gap(s) in {len({g.channel for g in gaps})} channel(s): "
            + "; ".join(lines) + more)
    problems.append(text)
    warnings.warn(text, GapWarning, stacklevel=caller_level())


class Assembler:
    """Blocks of many channels, by name, in arrival order; joined on demand."""

    def __init__(self, wanted: set[str] | None = None) -> None:
        self.blocks: dict[str, list[Block]] = {}
        self.wanted = wanted

    def add(self, data: bytes, topic: str = "") -> BlockHeader | None:
        """Keep the SampleBlock `data` (published under `topic`) if its channel is wanted.

        Parameters
        ----------
        data : bytes
            The block's protobuf bytes.
        topic : str
            The topic or key it came under; names the channel when the block does not.

        Returns
        -------
        BlockHeader or None
            The block's header; None if its channel is not wanted.

        Raises
        ------
        RecordingError
            If `data` is not a SampleBlock.
        """
        header, name = scan_sample_block(data, topic)
        if self.wanted is not None and name not in self.wanted:
            return None
        self.blocks.setdefault(name, []).append(
            Block(header.sequence, header.gps_start, header.rate_hz, header.unit,
                  block_samples(data, header)))
        return header

    def channels(self) -> dict[str, Channel]:
        """Every channel's blocks joined (:func:`join_blocks`)."""
        return {name: join_blocks(name, blocks) for name, blocks in self.blocks.items() if blocks}
