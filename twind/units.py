"""Quantities written as ``"number unit"`` strings in configuration files.

A config states units so that a value given in millimetres is not silently read as metres.
Only the units a suspension commissioner writes are known; anything else is an error that
names the unit.
"""

from __future__ import annotations

import re

# unit -> (dimension, factor to the SI/CDS unit of that dimension)
UNITS: dict[str, tuple[str, float]] = {
    "m": ("length", 1.0), "cm": ("length", 1e-2), "mm": ("length", 1e-3),
    "um": ("length", 1e-6), "nm": ("length", 1e-9),
    "kg": ("mass", 1.0), "g": ("mass", 1e-3),
    "kg m^2": ("inertia", 1.0), "kg*m^2": ("inertia", 1.0), "g cm^2": ("inertia", 1e-7),
    "N/m": ("stiffness", 1.0), "kN/m": ("stiffness", 1e3),
    "N/ct": ("actuation", 1.0), "mN/ct": ("actuation", 1e-3), "uN/ct": ("actuation", 1e-6),
    "nN/ct": ("actuation", 1e-9),
    "s": ("time", 1.0), "ms": ("time", 1e-3), "us": ("time", 1e-6),
    "Hz": ("frequency", 1.0), "kHz": ("frequency", 1e3),
    "ct": ("counts", 1.0),
    "ct s/um": ("velocity gain", 1.0), "ct s/urad": ("velocity gain", 1.0),
    "m/rtHz": ("length ASD", 1.0), "nm/rtHz": ("length ASD", 1e-9),
    "rad/rtHz": ("angle ASD", 1.0), "nrad/rtHz": ("angle ASD", 1e-9),
    "m/s^2": ("acceleration", 1.0),
    "kg/m^3": ("density", 1.0), "g/cm^3": ("density", 1e3),
    "Pa": ("pressure", 1.0), "MPa": ("pressure", 1e6), "GPa": ("pressure", 1e9),
    "in": ("length", 0.0254),
}

_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*$")


def parse_quantity(text: str | float | int, dimension: str) -> float:
    """Convert ``"0.248 m"`` (or ``"248 mm"``) to a float in the SI unit of `dimension`.

    Parameters
    ----------
    text : str or number
        The value as written. A bare number is accepted only for dimensionless values.
    dimension : str
        Expected dimension, a key of the second column of :data:`UNITS`, or
        ``"dimensionless"``.

    Returns
    -------
    float
        The value in the SI (or CDS) unit of that dimension.

    Raises
    ------
    ValueError
        With a message naming the problem (missing unit, unknown unit, wrong dimension).
    """
    if dimension == "dimensionless":
        if isinstance(text, bool) or not isinstance(text, (int, float)):
            msg = f"expected a plain number, got {text!r}"
            raise ValueError(msg)
        return float(text)
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        units = sorted(u for u, (d, _) in UNITS.items() if d == dimension)
        msg = f"{text!r} has no unit; write it as a string with a {dimension} unit, e.g. \"{text} {units[0]}\""
        raise ValueError(msg)
    match = _QUANTITY.match(str(text))
    if match is None:
        msg = f"{text!r} is not of the form \"number unit\""
        raise ValueError(msg)
    number, unit = float(match.group(1)), match.group(2)
    if unit not in UNITS:
        msg = f"unknown unit {unit!r} in {text!r}"
        raise ValueError(msg)
    found, factor = UNITS[unit]
    if found != dimension:
        msg = f"wrong unit: {text!r} is a {found}, expected a {dimension}"
        raise ValueError(msg)
    return number * factor
