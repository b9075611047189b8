"""Rerun views of the twin: recorded MCAP sessions as .rrd files (:mod:`.rerun_export`) and the
live channels streamed from Zenoh to a viewer (:mod:`.live`).

The command-line wiring (``twind view``, ``twind rrd``) is re-exported here; nothing imports
rerun until a command runs.
"""

from twind.viz.commands import (
    add_rrd_arguments,
    add_view_arguments,
    rrd_main,
    view_main,
)

__all__ = ["add_rrd_arguments", "add_view_arguments", "mcap_to_rrd", "rrd_main", "view_main"]


def mcap_to_rrd(*args, **kwargs):  # noqa: ANN002, ANN003, ANN201
    """See :func:`twind.viz.rerun_export.mcap_to_rrd`."""
    from twind.viz.rerun_export import mcap_to_rrd as convert

    return convert(*args, **kwargs)
