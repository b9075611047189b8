"""GPS time, as CDS stamps every block."""

from __future__ import annotations

import time

GPS_EPOCH_UNIX = 315964800  # 1980-01-06T00:00:00Z in Unix seconds
LEAP_SECONDS = 18  # TAI-UTC minus 19 s, constant since 2017-01-01


def now_gps() -> float:
    """Current GPS time (s)."""
    return time.time() - GPS_EPOCH_UNIX + LEAP_SECONDS


def gps_to_unix_ns(gps: float) -> int:
    """Unix time in ns of a GPS time (for MCAP log times)."""
    return int(round((gps + GPS_EPOCH_UNIX - LEAP_SECONDS) * 1e9))


def unix_ns_to_gps(ns: int) -> float:
    """GPS time of a Unix time in ns (an MCAP log time)."""
    return ns / 1e9 - GPS_EPOCH_UNIX + LEAP_SECONDS
