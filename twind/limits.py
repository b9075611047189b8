"""What a running twin accepts from its clients (the ``[service]`` table of an
interferometer file): light enough for a client to know the defaults without the physics."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ServiceLimits:
    """What a running twin accepts from its clients: the ``[service]`` table of an
    interferometer file, every key optional (these defaults otherwise).

    Attributes
    ----------
    exc_peak, exc_rms : float
        The sum of the excitations on one ``_EXC`` test point, in its units (um or urad):
        well inside the OSEMs' range.
    drive_peak, drive_rms : float
        The same on one excitation past the damping filters (``LSC_EXC``, ``ASCPIT_EXC``,
        ``ASCYAW_EXC``), in DAC counts: a 16-bit DAC's range, and a sine filling it.
    excitations_per_channel : int
        Excitations running or scheduled on one test point.
    excitations : int
        Excitations running or scheduled in all.
    schedule_ahead_s : float
        How far ahead of the twin's time an excitation may be scheduled (s).
    request_bytes : int
        The largest control request (a stream's samples travel in it).
    watchdog_um : float
        An OSEM reading beyond this (um from its centre), or not finite, trips the optic's
        watchdog: its damping outputs are zeroed until a request re-arms it.
    changes_per_minute : int
        ``params`` and ``filter`` changes accepted in any minute (each rebuilds and checks a
        loop, time the pacing thread shares).
    subscriber_wait_s : float
        How long the twin waits for a subscriber that reads nothing (suspended with Ctrl-Z,
        hung) before Zenoh closes that subscriber's session. Blocks wait for a slow reader,
        so that a recording has no gap, but one stalled client holds the loop and every
        other subscriber at most this long; it reconnects when it runs again.
    waveform_bytes : int
        Memory the running and scheduled excitations' waveforms may hold in all (a
        multisine keeps its whole period: 32 MB for 2^22 samples), so that a few short
        requests cannot fill the host's memory.
    """

    exc_peak: float = 100.0
    exc_rms: float = 30.0
    drive_peak: float = 32768.0
    drive_rms: float = 23170.0
    excitations_per_channel: int = 16
    excitations: int = 64
    schedule_ahead_s: float = 86400.0
    request_bytes: int = 8_000_000
    watchdog_um: float = 1000.0
    changes_per_minute: int = 60
    subscriber_wait_s: float = 0.5
    waveform_bytes: int = 512_000_000
