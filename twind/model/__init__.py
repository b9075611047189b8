"""Suspension physics: parameters, the analytical T000134 model, the geometric rigid-body model.

Nothing here knows about buses, files or the damping loop.
"""

from twind.model.params import SOSParams

__all__ = ["SOSParams"]
