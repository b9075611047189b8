"""Exception hierarchy: every error names what the user must fix."""

from __future__ import annotations


class TwindError(Exception):
    """Base class of all errors twind reports to a user."""


class ConfigError(TwindError):
    """A configuration file is missing a key, has a wrong unit or an impossible value.

    Parameters
    ----------
    source : str
        The file (or other source) the value came from.
    key : str
        Dotted key inside the file, e.g. ``optics.ETMX.suspension.wire_length``.
    problem : str
        What is wrong, in words.
    """

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source, self.key, self.problem = str(source), key, problem
        super().__init__(f"{self.source}: {key}: {problem}")


class FotonError(TwindError):
    """A foton design string or filter file cannot be understood."""


class BusError(TwindError):
    """An endpoint or a Zenoh configuration that cannot be used."""


class TwindWarning(UserWarning):
    """Base class of the warnings twind gives a user: something was read or done, but not
    all of it as asked (the command line prints them as ``twind: warning: ...``)."""


class MeasurementWarning(TwindWarning):
    """Bins of a measurement file that cannot be used (NaN or inf) and are left out."""
