"""LIGO channel names of the twin's test points, e.g. ``C1:SUS-ETMX_SUSPOS_IN1``."""

from __future__ import annotations

import re
from collections.abc import Iterator

import numpy as np
from numpy.typing import NDArray

from twind import DOFS, OSEMS

TEST_POINTS = ("EXC", "IN1", "IN2", "OUT")
UNITS = {"POS": "um", "PIT": "urad", "YAW": "urad", "SIDE": "um"}
DOF_CHANNEL = re.compile(
    r"^(?P<ifo>\w+):SUS-(?P<optic>\w+?)_SUS(?P<dof>POS|PIT|YAW|SIDE)_(?P<point>\w+)$")
"""A damping test point's name, parsed into ``ifo``, ``optic``, ``dof`` and ``point``."""


def dof_channel(ifo: str, optic: str, dof: str, point: str) -> str:
    """The name of a damping test point.

    Parameters
    ----------
    ifo : str
        The interferometer prefix, e.g. ``C1``.
    optic : str
        E.g. ``ETMX``.
    dof : str
        ``POS``, ``PIT``, ``YAW`` or ``SIDE``.
    point : str
        ``EXC``, ``IN1``, ``IN2`` or ``OUT``.

    Returns
    -------
    str

    Examples
    --------
    >>> dof_channel("C1", "ETMX", "POS", "IN1")
    'C1:SUS-ETMX_SUSPOS_IN1'
    """
    return f"{ifo}:SUS-{optic}_SUS{dof}_{point}"


def osem_channel(ifo: str, optic: str, osem: str) -> str:
    """The name of an OSEM's calibrated reading (um).

    Parameters
    ----------
    ifo : str
        The interferometer prefix, e.g. ``C1``.
    optic : str
        E.g. ``ETMX``.
    osem : str
        ``UL``, ``UR``, ``LL``, ``LR`` or ``SIDE``.

    Returns
    -------
    str

    Examples
    --------
    >>> osem_channel("C1", "ETMX", "UL")
    'C1:SUS-ETMX_ULSEN_OUT'
    """
    return f"{ifo}:SUS-{optic}_{osem}SEN_OUT"


def block_channels(ifo: str, block) -> Iterator[tuple[str, str, NDArray[np.float64]]]:  # noqa: ANN001
    """Every channel of an engine block as ``(name, unit, samples)``.

    Parameters
    ----------
    ifo : str
        The interferometer prefix, e.g. ``C1``.
    block : twind.simulation.engine.Block
        One block of every test point of every optic.

    Yields
    ------
    name : str
        The channel, e.g. ``C1:SUS-ETMX_SUSPOS_IN1``.
    unit : str
        ``um`` or ``urad`` for EXC, IN1 and IN2 and the OSEMs, ``ct`` for OUT.
    samples : numpy.ndarray
        A view of the block's samples of that channel.
    """
    for o, optic in enumerate(block.optics):
        for d, dof in enumerate(DOFS):
            for point in TEST_POINTS:
                unit = "ct" if point == "OUT" else UNITS[dof]
                yield dof_channel(ifo, optic, dof, point), unit, getattr(block, point.lower())[o, d]
        for j, osem in enumerate(OSEMS):
            yield osem_channel(ifo, optic, osem), "um", block.sen[o, j]
