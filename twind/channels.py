"""Channel names of test points: a site's convention (``<IFO>:<SYSTEM>-<OPTIC>_<SUFFIX>``) and
the 40m's names of the twin's, e.g. ``C1:SUS-ETMX_SUSPOS_IN1``."""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind import DOFS, OSEMS

TEST_POINTS = ("EXC", "IN1", "IN2", "OUT")
DRIVE_POINTS = {"POS": "LSC", "PIT": "ASCPIT", "YAW": "ASCYAW"}
"""The filter modules past the damping filters whose EXC drives a DOF's coils directly (the
40m's SUS models sum them with the damping OUT before the output matrix); SIDE has none."""
UNITS = {"POS": "um", "PIT": "urad", "YAW": "urad", "SIDE": "um"}
DOF_CHANNEL = re.compile(
    r"^(?P<ifo>\w+):SUS-(?P<optic>\w+?)_SUS(?P<dof>POS|PIT|YAW|SIDE)_(?P<point>\w+)$")
"""A damping test point's name, parsed into ``ifo``, ``optic``, ``dof`` and ``point``."""
OSEM_CHANNEL = re.compile(
    rf"^(?P<ifo>\w+):SUS-(?P<optic>\w+?)_(?P<osem>{'|'.join(OSEMS)})SEN_OUT$")
"""An OSEM reading's name (:func:`osem_channel`), parsed into ``ifo``, ``optic`` and ``osem``."""


EXC_POINT = re.compile(r"(?P<ifo>[A-Z][A-Z0-9]*):(?P<system>[A-Z][A-Z0-9]*)-"
                       r"(?P<optic>[A-Z][A-Z0-9]*)_(?P<point>[A-Z0-9_]+)_EXC")
"""An excitation test point of any site, upper case as in the CDS models (which of them a
twin has, the twin says): ``C1:SUS-ETMX_SUSPOS_EXC``, ``K1:VIS-SRM_TM_TEST_P_EXC``."""


def parse_dof_channel(channel: str) -> tuple[str, str, str, str] | None:
    """``(ifo, optic, dof, point)`` of a damping test point (:data:`DOF_CHANNEL`), or None."""
    m = DOF_CHANNEL.match(channel)
    return (m["ifo"], m["optic"], m["dof"], m["point"]) if m else None


POINT_NAME = re.compile(r"^(?P<ifo>[A-Za-z0-9]+):(?P<system>[A-Za-z0-9]+)-(?P<optic>[A-Za-z0-9]+)_"
                        r"(?P<suffix>\w+)$")
"""Any CDS test point's name: interferometer, system, optic, and what follows the optic."""
STORED = "_DQ"
"""What the data system appends to a test point it stores (``K1:VIS-PR3_IM_DAMP_L_IN1_DQ``,
``..._TM_OPLEV_PIT_DIAG_DQ``): a file saved from stored data names the test point so."""


@dataclass(frozen=True)
class Convention:
    """How a site names its test points: ``<ifo>:<system>-<OPTIC>_<suffix>``, the suffix a
    filter module and a point (``SUSPOS_IN1`` at the 40m, ``IM_DAMP_L_IN1`` or
    ``TM_TEST_P_EXC`` at KAGRA, ``TM_OPLEV_PIT_DIAG``). A site's configuration declares it
    (``[channels]``); the analysis never spells a site's names itself.

    Attributes
    ----------
    ifo : str
        The interferometer prefix: ``C1`` (the 40m), ``K1`` (KAGRA).
    system : str
        The subsystem: ``SUS`` at the 40m, ``VIS`` at KAGRA.
    """

    ifo: str = "C1"
    system: str = "SUS"

    def channel(self, optic: str, suffix: str) -> str:
        """The full name of `optic`'s test point `suffix`.

        Examples
        --------
        >>> Convention("K1", "VIS").channel("SRM", "IM_DAMP_L_IN1")
        'K1:VIS-SRM_IM_DAMP_L_IN1'
        """
        return f"{self.ifo}:{self.system}-{optic}_{suffix}"

    def parse(self, name: str) -> tuple[str, str] | None:
        """``(optic, suffix)`` of a channel of this site and system, else None; a stored
        channel (a final :data:`STORED`) is read as the test point it stores, since a file
        saved from the data system names its readbacks so.

        Examples
        --------
        >>> Convention("K1", "VIS").parse("K1:VIS-SRM_TM_TEST_P_EXC")
        ('SRM', 'TM_TEST_P_EXC')
        >>> Convention("K1", "VIS").parse("K1:VIS-PR3_IM_DAMP_L_IN1_DQ")
        ('PR3', 'IM_DAMP_L_IN1')
        >>> Convention("K1", "VIS").parse("C1:SUS-ETMX_SUSPOS_IN1") is None
        True
        """
        m = POINT_NAME.match(name)
        if not m or m["ifo"] != self.ifo or m["system"] != self.system:
            return None
        return m["optic"], m["suffix"].removesuffix(STORED)


C1 = Convention("C1", "SUS")
"""The 40m's convention, which the twin's own channels follow."""


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


def drive_channel(ifo: str, optic: str, dof: str) -> str:
    """The name of the excitation that drives `dof`'s coils past the damping filters.

    Parameters
    ----------
    ifo : str
        The interferometer prefix, e.g. ``C1``.
    optic : str
        E.g. ``ETMX``.
    dof : str
        ``POS``, ``PIT`` or ``YAW`` (:data:`DRIVE_POINTS`).

    Returns
    -------
    str

    Examples
    --------
    >>> drive_channel("C1", "ETMX", "PIT")
    'C1:SUS-ETMX_ASCPIT_EXC'
    """
    return f"{ifo}:SUS-{optic}_{DRIVE_POINTS[dof]}_EXC"


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
        ``um`` or ``urad`` for EXC, IN1 and IN2 and the OSEMs, ``ct`` for OUT and the
        excitations past the damping filters (:func:`drive_channel`).
    samples : numpy.ndarray
        A view of the block's samples of that channel.
    """
    for o, optic in enumerate(block.optics):
        for d, dof in enumerate(DOFS):
            for point in TEST_POINTS:
                unit = "ct" if point == "OUT" else UNITS[dof]
                yield dof_channel(ifo, optic, dof, point), unit, getattr(block, point.lower())[o, d]
            if dof in DRIVE_POINTS:
                yield drive_channel(ifo, optic, dof), "ct", block.lsc[o, d]
        for j, osem in enumerate(OSEMS):
            yield osem_channel(ifo, optic, osem), "um", block.sen[o, j]
