"""JSON that every reader accepts: NaN and infinities, which Python's ``json`` writes as the
bare words ``NaN`` and ``Infinity`` (not JSON), become ``null``."""

from __future__ import annotations

import json
import math
from typing import IO, Any

import numpy as np


def finite(obj: Any) -> Any:  # noqa: ANN401 - any JSON-able value
    """`obj` with every non-finite float (Python or numpy) replaced by None, and numpy
    scalars and arrays turned into Python ones."""
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite(obj.tolist())
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def dumps(obj: Any, **kw: Any) -> str:  # noqa: ANN401
    """:func:`json.dumps` of :func:`finite` (`obj`); ``allow_nan`` is off."""
    return json.dumps(finite(obj), allow_nan=False, **kw)


def dump(obj: Any, fp: IO[str], **kw: Any) -> None:  # noqa: ANN401
    """:func:`json.dump` of :func:`finite` (`obj`); ``allow_nan`` is off.

    Parameters
    ----------
    obj : object
        Any value :func:`json.dump` takes, numpy scalars and arrays too.
    fp : file
        A text file open for writing.
    **kw
        As :func:`json.dump` takes them (``indent``, ``default``...).
    """
    json.dump(finite(obj), fp, allow_nan=False, **kw)
