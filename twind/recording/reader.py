"""Read twind sessions: MCAP files (one, or a rotated set), the data system's HDF5 files or
GWF frames, or the live bus.

:func:`read_session` returns every channel's samples joined across blocks and files, with
the sequence numbers and any gaps (:mod:`twind.recording.fastread` is its engine);
:func:`getdata` gives a GPS span of some channels, from a recording or from the bus, as gwpy
``TimeSeriesDict`` when gwpy is installed.
"""

from __future__ import annotations

import math
import queue
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from numpy.typing import NDArray

from twind.bus.keys import data_key
from twind.bus.session import DEFAULT_ENDPOINT, ENDPOINT, zenoh_config, zenoh_message
from twind.recording.fastread import read_channels
from twind.recording.frames import is_frames, read_frames
from twind.recording.session import Assembler, Channel, RecordingError, Session, some_names
from twind.recording.writer import TOPIC_ROOT
from twind.timeutil import now_gps


def read_session(path_or_paths: str | Path | Iterable[str | Path],
                 channels: Iterable[str] | None = None) -> Session:
    """Read a recording: one MCAP file, a rotated set, or a list of files.

    Parameters
    ----------
    path_or_paths : path or iterable of paths
        See :func:`~twind.recording.session.session_files`.
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
        is returned (:mod:`twind.recording.mcapfile`).
    GapWarning
        For missing blocks, which are NaN in the samples and listed in ``Channel.gaps``.
    """
    return read_channels(path_or_paths, (lambda name: True) if channels is None else channels)


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
            source: Any = None, timeout: float | None = None,
            mapping: Mapping[str, str] | None = None) -> Any:
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
        A recording: MCAP (see :func:`session_files`), or gwpy HDF5 files or GWF frames
        (:func:`~twind.recording.frames.read_frames`), the files ``twind tf`` takes; or the
        bus to subscribe to for `duration` seconds: a Zenoh endpoint such as
        ``"tcp/127.0.0.1:7447"`` (the default) or a configuration.
    timeout : float, optional
        Bus only: wall-clock seconds to wait for the data; default ``2 * duration + 10`` plus
        the wait until `start`.
    mapping : mapping of str to str, optional
        HDF5 and GWF: recorded channel names to the twin's (``--map``;
        :func:`~twind.recording.frames.renamer`). `channels` are the twin's names.

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
    elif _frames(source):
        joined = read_frames([source] if isinstance(source, str | Path) else source,
                             set(names).__contains__, mapping).channels
    else:
        joined = read_session(source, names).channels
    missing = [n for n in names if n not in joined]
    if missing:
        msg = f"{missing[0]} is not in the recording; it holds {some_names(joined)}"
        raise RecordingError(msg)
    if start is None:
        start = max(joined[n].t0 for n in names)
    if duration is None:
        duration = min(joined[n].t_end for n in names) - start
    parts = {}
    for n in names:
        x, t0 = _slice(joined[n], start, duration)
        parts[n] = (x, t0, joined[n])
    return _as_series(parts)


def _frames(source: Any) -> bool:  # noqa: ANN401 - a path or paths
    """Whether `source` names HDF5 files or GWF frames."""
    paths = [source] if isinstance(source, str | Path) else source
    return isinstance(paths, list | tuple) and bool(paths) and all(
        isinstance(p, str | Path) and is_frames(p) for p in paths)


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
    assembler = Assembler(set(names))
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
                           f"(is a twin publishing {some_names(silent or names)}?)")
                    raise RecordingError(msg)
        finally:
            for s in subs:
                s.undeclare()
    return assembler.channels()
