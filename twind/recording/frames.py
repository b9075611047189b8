"""Recordings of the lab's data system: gwpy HDF5 files and GWF frames.

At the 40m, data come from NDS (``cdsutils getdata``, gwpy's ``TimeSeriesDict.get``) and are
saved with ``TimeSeriesDict.write`` as HDF5 or GWF: the test points as ``_DQ`` channels at
their own rates, and no injection events. :func:`read_frames` reads such files into a
:class:`~twind.recording.session.Session` with no events, under the twin's channel names
(:func:`renamer`: ``_DQ`` dropped, prefixes renamed). gwpy reads both formats: HDF5 through
h5py, GWF through the frame library of the ``lalsuite`` wheel (``pip install
'twind[frames]'``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from twind.recording.session import Channel, RecordingError, Session, some_names

FORMATS = {".h5": "hdf5", ".hdf5": "hdf5", ".hdf": "hdf5", ".gwf": "gwf"}
"""File suffixes gwpy's readers are chosen by."""
_INSTALL = "pip install 'twind[frames]'"


def is_frames(path: str | Path) -> bool:
    """Whether `path` is named as a gwpy HDF5 file or a GWF frame."""
    return Path(path).suffix.lower() in FORMATS


def parse_map(pairs: Iterable[str]) -> dict[str, str]:
    """``--map`` arguments (``RECORDED=TWIN``) as a mapping.

    Raises
    ------
    RecordingError
        For an argument without ``=`` or with an empty side.
    """
    out = {}
    for pair in pairs:
        old, sep, new = pair.partition("=")
        if not (sep and old and new):
            msg = f"--map {pair!r}: give RECORDED=TWIN, e.g. C2:SUS-ETMX_=C1:SUS-ETMX_"
            raise RecordingError(msg)
        out[old] = new
    return out


def renamer(mapping: Mapping[str, str] | None = None) -> Callable[[str], str]:
    """A recorded channel's name as the twin's: the longest prefix of `mapping` that
    matches replaced by its value, and a final ``_DQ`` (the data system's name for a
    stored test point) dropped.

    Parameters
    ----------
    mapping : mapping of str to str, optional
        Recorded prefix (or whole name) to the twin's, e.g. ``{"C2:": "C1:"}``.

    Examples
    --------
    >>> renamer({"C2:": "C1:"})("C2:SUS-ETMX_SUSPOS_IN1_DQ")
    'C1:SUS-ETMX_SUSPOS_IN1'
    """
    prefixes = sorted(mapping or {}, key=len, reverse=True)

    def rename(name: str) -> str:
        for old in prefixes:
            if name.startswith(old):
                name = mapping[old] + name[len(old):]
                break
        return name.removesuffix("_DQ")

    return rename


def read_frames(paths: Sequence[str | Path], channels: Callable[[str], bool] | None = None,
                mapping: Mapping[str, str] | None = None) -> Session:
    """Read gwpy HDF5 files or GWF frames (one format, in time order) into a session.

    Parameters
    ----------
    paths : sequence of path
        Files written by ``TimeSeriesDict.write``; several are joined in time.
    channels : callable, optional
        Keeps the channels whose twin name it accepts; default all.
    mapping : mapping of str to str, optional
        Recorded names to the twin's (:func:`renamer`).

    Returns
    -------
    Session
        No events; each channel at its recorded rate and start.

    Raises
    ------
    RecordingError
        If gwpy (or, for GWF, its frame library) is missing, a file is not readable in its
        format, the files mix formats or leave a gap, two names become one, or no channel
        is kept.
    """
    files = [Path(p) for p in paths]
    fmt = _one_format(files)
    try:  # optional and slow to import: only for these files
        from gwpy.timeseries import TimeSeriesDict
    except ImportError:
        msg = f"reading {files[0]} needs gwpy: {_INSTALL}"
        raise RecordingError(msg) from None
    rename = renamer(mapping)
    recorded = _names(files[0], fmt)
    twin = [rename(n) for n in recorded]
    doubled = sorted({t for t in twin if twin.count(t) > 1})
    if doubled:
        msg = f"{files[0]}: several recorded channels become {doubled[0]} once renamed"
        raise RecordingError(msg)
    kept = {r: t for r, t in zip(recorded, twin, strict=True) if channels is None or channels(t)}
    if not kept:
        msg = f"{files[0]}: none of its channels is wanted here; it holds {some_names(recorded)}"
        raise RecordingError(msg)
    try:
        data = TimeSeriesDict.read([str(f) for f in files], list(kept), format=fmt)
    except ImportError as err:
        msg = f"reading GWF frames needs the frame library ({err}): {_INSTALL}"
        raise RecordingError(msg) from None
    except (OSError, ValueError, KeyError, RuntimeError) as err:
        msg = f"{', '.join(map(str, files))}: not readable as {fmt} ({err})"
        raise RecordingError(msg) from None
    return Session(files, {kept[r]: _channel(kept[r], s) for r, s in data.items()}, [], [],
                   True, [])


def same_channels(paths: Sequence[str | Path]) -> bool:
    """Whether every file holds the same channels: pieces of one recording (read together
    by :func:`read_frames`), not measurements exported one file each.

    Raises
    ------
    RecordingError
        If a file is missing or not readable in its format, or the files mix formats.
    """
    files = [Path(p) for p in paths]
    fmt = _one_format(files)
    first = set(_names(files[0], fmt))
    return all(set(_names(f, fmt)) == first for f in files[1:])


def _one_format(files: list[Path]) -> str:
    """The format of `files`, refused when they mix or are missing."""
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        msg = f"no such file: {', '.join(missing)}"
        raise RecordingError(msg)
    formats = {FORMATS.get(f.suffix.lower()) for f in files}
    if len(formats) != 1 or None in formats:
        msg = f"{', '.join(map(str, files))}: give HDF5 files or GWF frames, not a mixture"
        raise RecordingError(msg)
    return formats.pop()


def _names(path: Path, fmt: str) -> list[str]:
    """The channel names stored in one file."""
    try:
        if fmt == "hdf5":
            with h5py.File(path, "r") as f:
                return [k for k, v in f.items() if isinstance(v, h5py.Dataset)]
        from gwpy.io.gwf import iter_channel_names  # gwpy is optional: see read_frames
        return list(iter_channel_names(str(path)))
    except ImportError as err:
        msg = f"{path}: reading GWF frames needs the frame library ({err}): {_INSTALL}"
        raise RecordingError(msg) from None
    except (OSError, ValueError, RuntimeError) as err:
        msg = f"{path}: not readable as {fmt} ({err})"
        raise RecordingError(msg) from None


def _channel(name: str, series: Any) -> Channel:  # noqa: ANN401 - a gwpy TimeSeries
    """A gwpy series as a session's channel of one block."""
    t0 = float(series.t0.to_value("s"))
    unit = "" if series.unit is None else str(series.unit)
    return Channel(name, "" if unit == "dimensionless" else unit,
                   float(series.sample_rate.to_value("Hz")), t0,
                   np.asarray(series.value, dtype=np.float64), np.zeros(1, np.int64),
                   np.array([t0]))
