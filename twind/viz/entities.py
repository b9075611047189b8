"""Rerun entity paths of the twin's channels.

``C1:SUS-ETMX_SUSPOS_IN1`` → ``sus/ETMX/POS/IN1``; ``C1:SUS-ETMX_ULSEN_OUT`` →
``sus/ETMX/OSEM/UL``; any other name → ``channels/<name>`` (escaped). The viewer's entity tree
then groups test points by optic and degree of freedom, and one time-series view per
``sus/<optic>/<dof>`` overlays EXC, IN1, IN2 and OUT.
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Iterable

import rerun.blueprint as rrb

from twind import DOFS
from twind.channels import DOF_CHANNEL, OSEM_CHANNEL


def entity_path(channel: str) -> str:
    """The Rerun entity path of a channel."""
    if m := DOF_CHANNEL.match(channel):
        return f"sus/{m['optic']}/{m['dof']}/{m['point']}"
    if m := OSEM_CHANNEL.match(channel):
        return f"sus/{m['optic']}/OSEM/{m['osem']}"
    return "channels/" + re.sub(r"[^A-Za-z0-9_\-]", "_", channel)


def matcher(patterns: Iterable[str] | str | None):  # noqa: ANN201 - Callable[[str], bool]
    """A predicate on channel names: shell-style patterns (``C1:SUS-ETMX_*``), comma-separated
    or as a list; None or empty selects every channel."""
    if isinstance(patterns, str):
        patterns = [p for p in patterns.split(",")]
    pats = [p.strip() for p in patterns or () if p.strip()]
    if not pats:
        return lambda _name: True
    return lambda name: any(fnmatch.fnmatchcase(name, p) for p in pats)


def blueprint(optics: Iterable[str], bode: Iterable[str] = (),  # noqa: ANN201
              timeline: str = "gps"):
    """The default layout: a tab per optic (a time-series view per DOF and one of the OSEMs),
    a tab of Bode views (one per excitation and transfer function: magnitude, phase,
    coherence) when there are any, and the events log below.

    Parameters
    ----------
    optics : iterable of str
        The optics to give a tab, e.g. ``ETMX``.
    bode : iterable of str
        Entity paths of the transfer functions, ``bode/<optic>/<dof>/<excitation>/IN1_EXC``.
    timeline : str
        The timeline the time panel shows first (``gps``, ``utc`` or ``frequency_hz``).

    Returns
    -------
    rerun.blueprint.Blueprint
    """

    tabs = []
    for optic in optics:
        views = [rrb.TimeSeriesView(origin=f"sus/{optic}/{dof}", name=f"{optic} {dof}")
                 for dof in DOFS]
        views.append(rrb.TimeSeriesView(origin=f"sus/{optic}/OSEM", name=f"{optic} OSEMs"))
        tabs.append(rrb.Grid(*views, grid_columns=2, name=optic))
    bode = list(bode)
    if bode:
        views = [rrb.TimeSeriesView(origin=f"{base}/{leaf}",
                                    name=f"{base.removeprefix('bode/')} {leaf}")
                 for base in bode for leaf in ("magnitude_db", "phase_deg", "coherence")]
        tabs.append(rrb.Grid(*views, grid_columns=3, name="Bode (timeline frequency_hz)"))
    main = rrb.Tabs(*tabs) if tabs else rrb.TimeSeriesView(origin="/")
    return rrb.Blueprint(rrb.Vertical(main, rrb.TextLogView(origin="events", name="events"),
                                      row_shares=[4, 1]),
                         rrb.TimePanel(timeline=timeline), collapse_panels=False)
