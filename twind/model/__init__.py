"""Suspension physics: parameters, the analytical T000134 model, the geometric rigid-body model,
the OSEMs and the CDS matrices, and the plant the damping loop sees; the physics left out.

Nothing here knows about buses, files or the damping loop's filters.
"""

from twind.model.params import SOSParams

__all__ = ["SOSParams"]
