"""``twind soak``: serve the twin for a while and measure what the service promises.

A ``twind serve --record`` process runs the configured optics in real time; this process
subscribes to every channel (another process, as a commissioner's script would), injects
short sines and measures the latency from request to the first published excitation sample,
sends malformed and hostile requests, and at the end reads the recording back. Printed:
CPU use of the service, lag, late blocks, lost or out-of-order blocks on the bus and in the
MCAP files, latency percentiles, and how many hostile requests were refused with a reason.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from twind.bus.codec import SampleBlock
from twind.bus.keys import all_data, control_key
from twind.bus.session import zenoh_config
from twind.client import TwinClient


@dataclass
class SoakReport:
    """Figures of one soak run."""

    duration_s: float
    optics: str
    cpu_fraction: float
    late_blocks: int
    max_lag_s: float
    bus_blocks: int
    bus_lost: int
    bus_out_of_order: int
    mcap_blocks: int
    mcap_gaps: int
    latency_s: list[float] = field(default_factory=list)
    hostile_sent: int = 0
    hostile_refused: int = 0
    hostile_unanswered: int = 0
    block_s: float = 1 / 16

    def lines(self) -> list[str]:
        """Human-readable figures."""
        lat = np.array(self.latency_s) if self.latency_s else np.array([np.nan])
        return [
            f"served {self.optics} for {self.duration_s:.0f} s: service CPU "
            f"{100 * self.cpu_fraction:.1f} % of one core, {self.late_blocks} late blocks, "
            f"max lag {1e3 * self.max_lag_s:.1f} ms",
            f"subscriber in another process: {self.bus_blocks} blocks, {self.bus_lost} lost, "
            f"{self.bus_out_of_order} out of order",
            f"MCAP recording: {self.mcap_blocks} blocks, {self.mcap_gaps} gaps",
            f"injection latency (request -> first excitation sample published), "
            f"{len(self.latency_s)} injections: median {1e3 * np.median(lat):.1f} ms, "
            f"p99 {1e3 * np.percentile(lat, 99):.1f} ms (target: one block + 10 ms = "
            f"{1e3 * self.block_s + 10:.1f} ms)",
            f"hostile requests: {self.hostile_sent} sent, {self.hostile_refused} refused with a "
            f"reason, {self.hostile_unanswered} unanswered",
        ]


class _Watcher:
    """Counts every block per channel and notes when excitation blocks arrive."""

    def __init__(self, endpoint: str) -> None:
        self.last: dict[str, int] = {}
        self.blocks = self.lost = self.out_of_order = 0
        self.first_nonzero: dict[str, list[tuple[float, float, float]]] = defaultdict(list)
        self._lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(connect=[endpoint], mode="client"))
        self.sub = self.session.declare_subscriber(all_data(), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        now = time.monotonic()
        block = SampleBlock.decode(sample.payload.to_bytes())
        with self._lock:
            self.blocks += 1
            last = self.last.get(block.channel)
            if last is not None and block.sequence != last + 1:
                if block.sequence > last + 1:
                    self.lost += block.sequence - last - 1
                else:
                    self.out_of_order += 1
            self.last[block.channel] = block.sequence
            if block.channel.endswith("_EXC"):
                nz = np.flatnonzero(block.samples)
                if nz.size:
                    gps = block.gps_start + nz[0] / block.rate_hz
                    self.first_nonzero[block.channel].append((gps, now, block.gps_start))

    def arrival_of(self, channel: str, start_gps: float, timeout: float = 5.0) -> float | None:
        """Monotonic time at which the block holding `start_gps` of `channel` arrived."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                for gps, arrived, _ in self.first_nonzero[channel]:
                    if abs(gps - start_gps) < 1e-6:
                        return arrived
            time.sleep(0.005)
        return None

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


HOSTILE = [
    b"not json", b"[1, 2, 3]", b"{}", json.dumps({"channel": "C1:SUS-ETMZ_SUSPOS_EXC",
                                                 "waveform": "sine", "freq": 1, "amp": 0.1}).encode(),
    json.dumps({"channel": "C1:SUS-ETMX_SUSPOS_EXC", "waveform": "sine", "freq": float("nan"),
                "amp": 0.1}).encode(),
    json.dumps({"channel": "C1:SUS-ETMX_SUSPOS_EXC", "waveform": "sine", "freq": 1.0,
                "amp": 1e9}).encode(),
    json.dumps({"channel": "C1:SUS-ETMX_SUSPOS_EXC", "waveform": "sine", "freq": 1.0,
                "amp": 0.1, "duration": -5}).encode(),
    json.dumps({"channel": "C1:SUS-ETMX_SUSPOS_EXC", "waveform": "sine", "freq": -3.0,
                "amp": 0.1}).encode(),
    json.dumps({"channel": "C1:SUS-ETMX_SUSPOS_EXC", "waveform": "warble", "amp": 0.1}).encode(),
    json.dumps({"channel": "C1:SUS-ETMX_SUSPOS_EXC", "waveform": "stream",
                "samples": [1e6] * 20000}).encode(),
    json.dumps({"channel": "C1:SUS-ETMX_SUSPOS_EXC", "waveform": "noise", "amp": 0.1,
                "shape": "zpk([1],[oops"}).encode(),
]


def _hostile(endpoint: str, n: int, ifo: str) -> tuple[int, int]:
    refused = unanswered = 0
    with zenoh.open(zenoh_config(connect=[endpoint], mode="client")) as s:
        key = control_key(ifo, "inject")
        for i in range(n):
            replies = list(s.get(key, payload=HOSTILE[i % len(HOSTILE)], timeout=5.0))
            if not replies or replies[0].ok is None:
                unanswered += 1
                continue
            reply = json.loads(replies[0].ok.payload.to_string())
            if not reply.get("accepted") and reply.get("reason"):
                refused += 1
    return refused, unanswered


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def soak(duration: float = 60.0, optics: str = "all", hostile: int = 1000, port: int = 17461,
         injections_every: float = 2.0, config: str | None = None) -> SoakReport:
    """Run the soak (see module docstring) and return its figures."""
    endpoint = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="twind-soak-") as tmp:
        cmd = [sys.executable, "-m", "twind", "serve", "--optics", optics, "--listen", endpoint,
               "--record", tmp] + (["--config", config] if config else [])
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            client = TwinClient.wait([endpoint], timeout=90, alive=lambda: proc.poll() is None)
            watcher = _Watcher(endpoint)
            status0 = client.status()
            cpu0, t0 = _cpu_seconds(proc.pid), time.monotonic()
            hostile_result: list[tuple[int, int]] = []
            attack = threading.Thread(target=lambda: hostile_result.append(
                _hostile(endpoint, hostile, status0["ifo"])), daemon=True)
            attack.start()
            latencies = _inject_periodically(client, watcher, status0, t0 + duration,
                                             injections_every)
            attack.join(timeout=max(1.0, t0 + duration - time.monotonic() + 30))
            cpu = (_cpu_seconds(proc.pid) - cpu0) / (time.monotonic() - t0)
            status = client.status()
            client.close()
            watcher.close()
        finally:
            proc.terminate()
            proc.wait(timeout=60)
        mcap_blocks, mcap_gaps = _scan_recording(sorted(Path(tmp).glob("*.mcap")))
    refused, unanswered = hostile_result[0] if hostile_result else (0, hostile)
    return SoakReport(
        duration_s=duration, optics=", ".join(status["optics"]), cpu_fraction=cpu,
        late_blocks=status["late_blocks"], max_lag_s=status["max_lag_s"],
        bus_blocks=watcher.blocks, bus_lost=watcher.lost,
        bus_out_of_order=watcher.out_of_order,
        mcap_blocks=mcap_blocks, mcap_gaps=mcap_gaps, latency_s=latencies, hostile_sent=hostile,
        hostile_refused=refused, hostile_unanswered=unanswered, block_s=status["block_s"])


def _scan_recording(files: list[Path]) -> tuple[int, int]:
    """Blocks and sequence gaps of a recording, read as a stream: an hour of the 40m is
    ~50 GB, far more than memory holds."""
    from twind.recording.reader import iter_raw_messages

    last: dict[str, int] = {}
    blocks = gaps = 0
    for path in files:
        for m in iter_raw_messages(path, topics=lambda t: not t.startswith("twin/@")):
            blocks += 1
            prev = last.get(m.topic)
            if prev is not None and m.sequence != prev + 1:
                gaps += 1
            last[m.topic] = m.sequence
    return blocks, gaps


def _inject_periodically(client: TwinClient, watcher: _Watcher, status: dict, until: float,
                         every: float) -> list[float]:
    optic = status["optics"][0]
    channels = [f"{status['ifo']}:SUS-{optic}_SUS{d}_EXC" for d in ("POS", "PIT", "YAW", "SIDE")]
    latencies = []
    rng = np.random.default_rng(0)
    k = 0
    while time.monotonic() + every < until:
        channel = channels[k % len(channels)]
        k += 1
        t_req = time.monotonic()
        reply = client.query("inject", {"channel": channel, "waveform": "sine", "freq": 5.0,
                                        "amp": 0.01, "duration": 0.5})
        if reply.get("accepted"):
            # a sine starts at zero: its first non-zero sample is the one after the start
            arrived = watcher.arrival_of(channel, reply["start_gps"] + 1 / status["rate_hz"])
            if arrived is not None:
                latencies.append(arrived - t_req)
        # random intervals, so requests fall at every phase of the block clock
        time.sleep(max(0.0, rng.uniform(0.5, 1.5) * every - (time.monotonic() - t_req)))
    return latencies
