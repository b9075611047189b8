"""A free-swinging measurement on a served twin, as the 40m makes one: each DOF rung up
through its damping loop by a sine at its mode, the damping gains set to zero together, the
OSEMs read from the bus while the optic rings down, the gains put back."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from twind import DOFS, OSEMS
from twind.analysis.identification.modes import modes_hz
from twind.channels import dof_channel, osem_channel
from twind.client import TwinClient
from twind.config import OpticConfig
from twind.errors import TwindError
from twind.excitation.checks import DEFAULT_LIMITS
from twind.recording.reader import as_array, getdata

DRIVE_S = 20.0
"""Twin seconds each DOF is driven at its mode before the release: many times the damped
loop's settling time (its Q of a few at about 1 Hz), so the optic swings at full amplitude."""

DRIVE_RMS = 0.8
"""The drive's RMS as a fraction of the ``_EXC`` limit (``service.exc_rms``): with the damping
on, a sine at a mode moves the optic by about its amplitude."""

LEAD_WALL_S = 2.0
"""Wall seconds between a request and the twin time it is meant for (the drive's start, the
first ringdown sample read): time for the request and the subscription to land."""


def served_ringdown(client: TwinClient, optic: OpticConfig, duration_s: float, bus: Any,
                    progress: Callable[[str], None] = lambda _: None
                    ) -> tuple[NDArray[np.float64], float]:
    """Ring down `optic` on the twin `client` talks to and read its five OSEMs from the bus.

    Each DOF's ``_EXC`` carries a sine at the configured model's mode frequency
    (:data:`DRIVE_RMS` of the default limit) for :data:`DRIVE_S`; then every damping gain of
    the optic goes to zero at once, the sines stop and `duration_s` twin seconds of OSEM
    readings are read from the bus (`bus`, a ``zenoh.Config`` for
    :func:`~twind.recording.reader.getdata`). The gains come back (with their ramp)
    whatever happens, also on Ctrl-C.

    Parameters
    ----------
    client : TwinClient
        A client to the twin that runs the optic.
    optic : OpticConfig
        The optic as configured; its model's mode frequencies set the drive.
    duration_s : float
        Twin seconds of ringdown to read.
    bus : zenoh.Config
        Where to read the OSEMs from.
    progress : callable
        ``progress(line)`` is told each stage (drive, release).

    Returns
    -------
    sen : ndarray, shape (5, n)
        The OSEM readings (um), UL, UR, LL, LR, SIDE.
    rate_hz : float

    Raises
    ------
    TwindError
        If the twin does not run the optic, its watchdog is tripped, a damping gain is
        already zero (the drive goes through the damping loops), or an injection is refused.
    """
    name, status = optic.name, client.status()
    if name not in status.optics:
        msg = f"the twin runs {', '.join(status.optics)}, not {name}"
        raise TwindError(msg)
    if status.watchdogs.get(name) == "tripped":
        msg = f"{name}'s watchdog is tripped: re-arm it first (TwinClient.rearm)"
        raise TwindError(msg)
    gains = {d: m.gain for d, m in client.params(name).filters.items()}
    off = [d for d in DOFS if gains[d] == 0]
    if off:
        msg = (f"{name}'s {', '.join(off)} damping gain is zero: the drive rings the optic up "
               "through its damping loops, switch them on first")
        raise TwindError(msg)
    lead = LEAD_WALL_S * status.speed
    start = status.gps + lead
    amp = DRIVE_RMS * DEFAULT_LIMITS.rms * math.sqrt(2)
    ids: list[str] = []
    try:
        for dof, f in modes_hz(optic).items():
            ids.append(client.inject(dof_channel(client.ifo, name, dof, "EXC"), "sine", freq=f,
                                     amp=amp, duration=2 * DRIVE_S, ramp=2.0, start_gps=start))
        progress(f"{name}: driving every DOF at its mode for {DRIVE_S:g} s")
        _wait_until(client, start + DRIVE_S)
        for dof in DOFS:
            client.set_gain(name, dof, 0.0, ramp=0.0)
        released = client.status().gps
        _stop(client, ids)
        progress(f"{name}: released at GPS {released:.1f}, reading {duration_s:g} s of ringdown")
        data = getdata([osem_channel(client.ifo, name, o) for o in OSEMS], duration_s,
                       start=released + lead,
                       source=bus,
                       timeout=2 * duration_s / status.speed + 60)
    finally:
        _stop(client, ids)
        for dof in DOFS:
            client.set_gain(name, dof, gains[dof])
    return as_array(data)


def _wait_until(client: TwinClient, gps: float) -> None:
    """Return once the twin's time has reached `gps`."""
    while (now := client.status()).gps < gps:
        time.sleep(min(0.5, max(0.01, 0.5 * (gps - now.gps) / now.speed)))


def _stop(client: TwinClient, ids: list[str]) -> None:
    """Stop the excitations `ids` that still run (the others ended or were never accepted)."""
    running = {e.id for e in client.status().excitations}
    for exc_id in ids:
        if exc_id in running:
            client.stop(exc_id)
