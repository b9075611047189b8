"""``twind export``: a recording's channels as NumPy ``.npz`` or HDF5 (``.h5``/``.hdf5``).

``.npz``: one float64 array per channel, named by the channel name
(``C1:SUS-ETMX_SUSPOS_IN1``), with float64 scalars ``<channel>:t0`` (GPS s of sample 0) and
``<channel>:rate`` (Hz); a channel with gaps also gets ``<channel>:gaps``, an (n, 2) array of
the GPS [start, end) of each gap.

HDF5: one dataset per channel at the root, named by the channel name, with attributes
``t0``, ``rate``, ``unit`` and, if it has gaps, ``gaps`` as above.

Missing blocks are never joined silently: their samples are NaN (so sample ``i`` is at
``t0 + i / rate``), a :class:`twind.recording.session.GapWarning` is issued, and they are
listed in :attr:`ExportResult.gaps` and in the file.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from twind.recording.reader import read_session
from twind.recording.session import Gap, RecordingError

FORMATS = {".npz": "npz", ".h5": "hdf5", ".hdf5": "hdf5"}


@dataclass
class ExportResult:
    """What :func:`export` wrote.

    Attributes
    ----------
    path : Path
    format : str
        ``"npz"`` or ``"hdf5"``.
    channels : list of str
    gaps : dict of str to list of Gap
        Channels with gaps only.
    problems : list of str
        Truncated files and gaps, as warned.
    """

    path: Path
    format: str
    channels: list[str]
    gaps: dict[str, list[Gap]]
    problems: list[str]


def export(path_in: str | Path | Iterable[str | Path], path_out: str | Path,
           channels: Iterable[str] | None = None) -> ExportResult:
    """Export a recording's channels to ``.npz`` or HDF5.

    Parameters
    ----------
    path_in : path or iterable of paths
        The recording (see :func:`twind.recording.session.session_files`).
    path_out : str or Path
        ``*.npz``, ``*.h5`` or ``*.hdf5``; an existing file is refused.
    channels : iterable of str, optional
        Default all.

    Returns
    -------
    ExportResult

    Raises
    ------
    RecordingError
        For an unknown output suffix, an existing output, a missing channel or an
        unreadable recording.
    """
    path_out = Path(path_out)
    fmt = FORMATS.get(path_out.suffix.lower())
    if fmt is None:
        msg = f"{path_out}: export writes .npz, .h5 or .hdf5, not {path_out.suffix or 'no suffix'}"
        raise RecordingError(msg)
    if path_out.exists():
        msg = f"{path_out} exists; twind export does not overwrite files"
        raise RecordingError(msg)
    session = read_session(path_in, None if channels is None else list(channels))
    if not session.channels:
        msg = f"{session.files[0]}: no channels recorded"
        raise RecordingError(msg)
    try:
        if fmt == "npz":
            _write_npz(session.channels, path_out)
        else:
            _write_hdf5(session.channels, path_out, session.files)
    except FileExistsError:
        msg = f"{path_out} exists; twind export does not overwrite files"
        raise RecordingError(msg) from None
    gaps = {name: ch.gaps for name, ch in session.channels.items() if ch.gaps}
    return ExportResult(path_out, fmt, list(session.channels), gaps, session.problems)


def _gap_array(gaps: list[Gap]) -> np.ndarray:
    return np.array([[g.gps_start, g.gps_end] for g in gaps], dtype=np.float64).reshape(-1, 2)


def _write_npz(channels: dict, path: Path) -> None:
    arrays: dict[str, np.ndarray] = {}
    for name, ch in channels.items():
        arrays[name] = np.asarray(ch.samples, dtype=np.float64)
        arrays[f"{name}:t0"] = np.float64(ch.t0)
        arrays[f"{name}:rate"] = np.float64(ch.rate)
        if ch.gaps:
            arrays[f"{name}:gaps"] = _gap_array(ch.gaps)
    fh = open(path, "xb")  # noqa: SIM115 - "x": never replace a file made meanwhile
    try:
        with fh:
            np.savez(fh, **arrays)
    except BaseException:
        path.unlink(missing_ok=True)  # no half-written export left behind
        raise


def _write_hdf5(channels: dict, path: Path, sources: list[Path]) -> None:

    f = h5py.File(path, "x")  # "x": fail if the file exists (then nothing to clean up)
    try:
        with f:
            f.attrs["source"] = ", ".join(str(p) for p in sources)
            for name, ch in channels.items():
                ds = f.create_dataset(name, data=np.asarray(ch.samples, dtype=np.float64))
                ds.attrs["t0"] = float(ch.t0)
                ds.attrs["rate"] = float(ch.rate)
                ds.attrs["unit"] = ch.unit
                if ch.gaps:
                    ds.attrs["gaps"] = _gap_array(ch.gaps)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
