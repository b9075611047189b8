"""twind: a digital twin of the LIGO 40m small optic suspensions (SOS) and their damping loops.

Rooms of the package, one per domain:

- :mod:`twind.model`      suspension physics (analytical T000134, geometric rigid body) and configs
- :mod:`twind.loop`       the CDS damping loop: OSEM matrices, foton filters, filter modules
- :mod:`twind.simulation` the fixed-step engine at the 16384 Hz model rate, noise, benchmarks
"""

__version__ = "0.1.0"

DOFS: tuple[str, ...] = ("POS", "PIT", "YAW", "SIDE")
"""Damped degrees of freedom in CDS order; rows and columns of every 4x4 matrix."""
