"""A short soak of the service: nothing lost on the bus or on disk, every attack refused."""

from __future__ import annotations

import pytest
from servicekit import free_port

from twind.lab.soak import soak


@pytest.mark.slow
def test_short_soak() -> None:
    report = soak(duration=8.0, optics="ETMX", hostile=60, port=free_port(), injections_every=1.0,
                  suspend=2.0, pauses=2)  # test_hostile pauses one 16 times
    print("\n".join(report.lines()))
    assert report.bus_blocks > 0 and report.bus_lost == 0 and report.bus_out_of_order == 0
    assert report.bus_corrupt == 0 and report.bus_misdelivered == 0
    resumed = report.suspended  # a subscriber suspended for 2 s, then read again
    assert resumed["blocks"] > 0 and resumed["corrupt"] == resumed["misdelivered"] == 0
    assert report.mcap_blocks >= report.bus_blocks and report.mcap_gaps == 0
    assert sum(report.hostile_sent.values()) == 60
    assert report.hostile_refused == report.hostile_sent  # every kind, every request
    assert set(report.hostile_sent) == {"inject", "filter", "params", "stop"}
    assert report.hostile_unanswered == 0 and not report.crashed
    assert report.watchdog.endswith("tripped under a 42 um drive and re-armed")
    assert len(report.latency_s) >= 3
    assert report.service_latency["n"] >= len(report.latency_s)  # the watchdog's drive too
