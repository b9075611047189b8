"""twind: a digital twin of the LIGO 40m small optic suspensions (SOS) and their damping loops.

One subpackage per domain, each importing only those below it (docs/architecture.md):
:mod:`twind.cli`, :mod:`twind.lab`, :mod:`twind.service`, :mod:`twind.viz`,
:mod:`twind.excitation`, :mod:`twind.analysis`, :mod:`twind.recording`, :mod:`twind.config`,
:mod:`twind.simulation`, :mod:`twind.loop`, :mod:`twind.model`, :mod:`twind.client`,
:mod:`twind.bus`. The names every layer shares are here.
"""

__version__ = "0.1.0"

DOFS: tuple[str, ...] = ("POS", "PIT", "YAW", "SIDE")
"""Damped degrees of freedom in CDS order; rows and columns of every 4x4 matrix."""

OSEMS: tuple[str, ...] = ("UL", "UR", "LL", "LR", "SIDE")
"""The OSEMs of an SOS, four on the face and one at the side, in CDS order."""
