"""The parameters ``twind fit`` fits: their names, values in a configuration, and a
simulated optic's truth file."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

from twind.errors import TwindError
from twind.model.params import SOSParams


FIT_PARAMS = ("wire_length_m", "b_m", "R1_m", "coil_N_per_ct", "osem_lever_m",
              "Q_POS", "Q_PIT", "Q_YAW", "Q_SIDE")


LABELS = {"wire_length_m": ("wire length", "l", "m"),
          "b_m": ("break-off above the centre of mass", "b", "m"),
          "R1_m": ("half wire separation at the clamps", "R1", "m"),
          "coil_N_per_ct": ("face coil force per DAC count", "alpha", "N/ct"),
          "osem_lever_m": ("OSEM lever arm", "h", "m"),
          **{f"Q_{d}": (f"{d} quality factor", f"Q_{d}", "") for d in ("POS", "PIT", "YAW",
                                                                       "SIDE")}}
"""Each fit parameter as a person reads it: (what it is, its symbol in docs/model.md, unit)."""


def param_label(name: str) -> str:
    """`name` as a person reads it, e.g. ``wire length l (m)``; `name` itself if unknown."""
    if name not in LABELS:
        return name
    what, symbol, unit = LABELS[name]
    return f"{what} {symbol}" + (f" ({unit})" if unit else "")


class FitError(TwindError):
    """Parameters cannot be fitted to these measurements."""


# ------------------------------------------------------------------------------ parameters
def param_value(sus: SOSParams, name: str) -> float:
    """The value of fit parameter `name` (``Q_<DOF>`` reads ``sus.Q``).

    Parameters
    ----------
    sus : SOSParams
    name : str
        One of :data:`FIT_PARAMS` (or any other field of `sus`).

    Returns
    -------
    float
        In SI units.
    """
    if name.startswith("Q_"):
        return float(sus.Q[name[2:]])
    return float(getattr(sus, name))


def read_truth(path: str | Path) -> dict[str, float]:
    """Fit-parameter values of a ``truth.json`` (``drifted_params``, Q per DOF), as
    ``tests/data/example_null`` holds them for its simulated optic."""
    try:
        given = json.loads(Path(path).read_text())
        given = given.get("drifted_params", given)
        q = given.get("Q", {})
        return {**{n: float(given[n]) for n in FIT_PARAMS if n in given},
                **{f"Q_{d}": float(v) for d, v in q.items() if f"Q_{d}" in FIT_PARAMS}}
    except (OSError, ValueError, AttributeError, TypeError) as err:
        msg = f"{path}: not a truth file of parameter values ({err})"
        raise FitError(msg) from None


def with_params(sus: SOSParams, values: Mapping[str, float]) -> SOSParams:
    """A copy of `sus` with fit parameters set (``Q_POS`` etc. go into ``Q``).

    Parameters
    ----------
    sus : SOSParams
    values : mapping of str to float
        New values by fit parameter name (or any other field of `sus`).

    Returns
    -------
    SOSParams
    """
    return sus.updated(**values)


def check_names(names: Sequence[str]) -> list[str]:
    """`names` if every one is a fit parameter; else a FitError listing the valid ones."""
    unknown = [n for n in names if n not in FIT_PARAMS]
    if unknown or not names:
        msg = (f"unknown fit parameter(s) {unknown}; choose from {', '.join(FIT_PARAMS)}"
               if unknown else "no parameter to fit")
        raise FitError(msg)
    return list(dict.fromkeys(names))
