"""Frequency series (measured and modelled transfer functions, residuals) as a Rerun
recording, on the ``frequency_hz`` timeline the session export's Bode views use."""

from __future__ import annotations

import uuid
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import rerun as rr
from numpy.typing import NDArray

from twind.errors import TwindError
from twind.viz.decimate import NS
from twind.viz.rerun_export import FREQ_TIMELINE


def write_spectra_rrd(path: str | Path, name: str,
                      series: Mapping[str, tuple[NDArray[np.float64], NDArray[np.float64]]]
                      ) -> Path:
    """Write each ``entity path -> (frequency_hz, values)`` as a scalar series.

    Parameters
    ----------
    path : str or Path
        The ``.rrd`` to create (an existing file is refused).
    name : str
        Recording name shown in the viewer.
    series : mapping
        Entity path (e.g. ``diagnose/YAW_POS/measured_db``) to frequencies and values.

    Returns
    -------
    Path
    """

    path = Path(path)
    if path.exists():
        msg = f"{path} exists; twind does not overwrite files"
        raise TwindError(msg)
    rec = rr.RecordingStream("twind", recording_id=str(uuid.uuid4()))
    rec.save(path)
    rec.send_recording_name(name)
    for entity, (f, values) in series.items():
        keep = np.isfinite(values) & (np.asarray(f) > 0)
        if not keep.any():
            continue
        rec.log(entity, rr.SeriesLines(names=entity.rsplit("/", 1)[-1]), static=True)
        index = [rr.TimeColumn(FREQ_TIMELINE,
                               duration=np.round(np.asarray(f)[keep] * NS).astype("timedelta64[ns]"))]
        rec.send_columns(entity, indexes=index,
                         columns=rr.Scalars.columns(scalars=np.asarray(values)[keep]))
    rec.flush()
    rec.disconnect()
    return path
