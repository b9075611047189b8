"""``twind soak``: serve the twin for a while and measure what the service promises.

A ``twind serve --record`` process runs the configured optics in real time; this process
subscribes to every channel (another process, as a commissioner's script would), injects
short sines and measures the latency from request to the first published excitation sample,
sends malformed and hostile requests, suspends a second subscriber for a while (as Ctrl-Z
does), and at the end reads the recording back. Printed: CPU use of the service, lag, late
blocks, lost or out-of-order blocks on the bus and in the MCAP files, latency percentiles,
how many hostile requests were refused with a reason, and what the suspended subscriber
cost the twin and found when it ran again.

:func:`soak_connected` (``twind soak --connect``) soaks twins already serving behind a router
instead, and gives each twin's figures; :mod:`twind.lab.fleet` builds such a fleet.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from twind.bus.codec import SampleBlock
from twind.bus.keys import all_data, control_key
from twind.bus.session import zenoh_config
from twind.channels import POINT_NAME, dof_channel
from twind.client import TwinClient
from twind.config import DEFAULT_CONFIG, load_config
from twind.errors import TwindError
from twind.protocol import StatusReply
from twind.recording.mcapfile import iter_raw_messages


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
    bus_corrupt: int
    bus_misdelivered: int
    mcap_blocks: int
    mcap_gaps: int
    bus_anomalies: list[str] = field(default_factory=list)  # what the subscriber saw amiss
    latency_s: list[float] = field(default_factory=list)  # at the subscriber
    service_latency: dict = field(default_factory=dict)  # status's injection_latency_s
    hostile_sent: dict[str, int] = field(default_factory=dict)
    hostile_refused: dict[str, int] = field(default_factory=dict)
    hostile_unanswered: int = 0
    block_s: float = 1 / 16
    crashed: bool = False
    log_tail: str = ""  # the end of the service's output, when it crashed
    load: int = 0
    watchdog: str = ""
    suspended: dict = field(default_factory=dict)  # the suspended subscriber's figures

    def lines(self) -> list[str]:
        """Human-readable figures."""
        lat = np.array(self.latency_s) if self.latency_s else np.array([np.nan])
        subscriber = {"n": lat.size if self.latency_s else 0, "median": np.median(lat),
                      "p99": np.percentile(lat, 99), "max": lat.max()}
        return [
            f"served {self.optics} for {self.duration_s:.0f} s: service CPU "
            f"{100 * self.cpu_fraction:.1f} % of one core, {self.late_blocks} late blocks, "
            f"max lag {1e3 * self.max_lag_s:.1f} ms",
            f"subscriber in another process: {self.bus_blocks} blocks, {self.bus_lost} lost, "
            f"{self.bus_out_of_order} out of order, {self.bus_corrupt} undecodable, "
            f"{self.bus_misdelivered} of another channel"
            + "".join(f"\n  {a}" for a in self.bus_anomalies),
            f"MCAP recording: {self.mcap_blocks} blocks, {self.mcap_gaps} gaps",
            f"injection latency (request -> first excitation sample published; target: one "
            f"block + 10 ms = {1e3 * self.block_s + 10:.1f} ms): at the service, "
            f"{_ms(self.service_latency)}; at a subscriber in another process, "
            f"{_ms(subscriber)}",
            "hostile requests refused with a reason, of those sent: " + ", ".join(
                f"{verb} {self.hostile_refused.get(verb, 0)}/{n}"
                for verb, n in self.hostile_sent.items()) + f"; {self.hostile_unanswered} "
            "unanswered",
            _suspended_line(self.suspended),
            f"service crashed: {'YES' if self.crashed else 'no'}; other processes loading the "
            f"cores: {self.load}; watchdog: {self.watchdog or 'not exercised'}",
        ] + ([f"the service's last output:\n{self.log_tail}"] if self.crashed else [])


def _suspended_line(s: dict) -> str:
    if not s:
        return "suspended subscriber: not exercised"
    return (f"a subscriber paused {s['pauses']} times for 0.1-0.4 s, then suspended for "
            f"{s['seconds']:g} s (SIGSTOP): {s['late_blocks']} "
            f"blocks late meanwhile, the twin's max lag then {1e3 * s['max_lag_s']:.1f} ms "
            f"(service.subscriber_wait_s = {s['wait_s']:g} s); resumed, it read "
            f"{s['blocks']} blocks, missed {s['lost']} while away, {s['out_of_order']} out of "
            f"order, {s['corrupt']} undecodable, {s['misdelivered']} of another channel")


def _ms(latency: dict) -> str:
    if not latency.get("n"):
        return "no injection"
    return (f"{latency['n']} injections: median {1e3 * latency['median']:.1f} ms, p99 "
            f"{1e3 * latency['p99']:.1f} ms, max {1e3 * latency['max']:.1f} ms")


class _Watcher:
    """Counts every block per channel and notes when excitation blocks arrive."""

    def __init__(self, endpoint: str, config_file: str | None = None) -> None:
        self.last: dict[str, int] = {}
        self.per_channel: dict[str, Counter] = defaultdict(Counter)  # blocks, lost, ...
        self.corrupt = self.misdelivered = 0
        self.anomalies: list[str] = []  # the first few, with when and what
        self._t0 = time.monotonic()
        self.first_nonzero: dict[str, list[tuple[float, float, float]]] = defaultdict(list)
        self._lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(connect=[endpoint], mode="client",
                                               config_file=config_file))
        self.sub = self.session.declare_subscriber(all_data(), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        now = time.monotonic()
        data = sample.payload.to_bytes()
        key = str(sample.key_expr)
        try:
            block = SampleBlock.decode(data)
        except Exception as err:  # noqa: BLE001 - a block that arrives damaged is counted
            with self._lock:
                self.corrupt += 1
                self._note(f"undecodable on {key}: {len(data)} bytes, {data[:24].hex()} "
                           f"({type(err).__name__})")
            return
        with self._lock:
            counts = self.per_channel[block.channel]
            counts["blocks"] += 1
            if not key.endswith(block.channel):
                self.misdelivered += 1
                self._note(f"{key} delivered a block of {block.channel} (sequence "
                           f"{block.sequence})")
            last = self.last.get(block.channel)
            if last is not None and block.sequence != last + 1:
                if block.sequence > last + 1:
                    counts["lost"] += block.sequence - last - 1
                else:
                    counts["out_of_order"] += 1
                self._note(f"{block.channel}: sequence {block.sequence} after {last}")
            self.last[block.channel] = block.sequence
            if block.channel.endswith("_EXC"):
                nz = np.flatnonzero(block.samples)
                if nz.size:
                    gps = block.gps_start + nz[0] / block.rate_hz
                    self.first_nonzero[block.channel].append((gps, now, block.gps_start))

    def _note(self, what: str) -> None:
        if len(self.anomalies) < 8:
            self.anomalies.append(f"t = {time.monotonic() - self._t0:.1f} s: {what}")

    def wait_for(self, optics: set[str], timeout: float = 20.0) -> None:
        """Return once blocks of every optic of `optics` arrive (the subscription has
        reached every twin, through a router too), or after `timeout`."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                seen = {m["optic"] for c in self.per_channel if (m := POINT_NAME.match(c))}
            if optics <= seen:
                return
            time.sleep(0.05)

    def arrival_of(self, channel: str, start_gps: float, deadline: float) -> float | None:
        """Monotonic time at which the block holding `start_gps` of `channel` arrived, or
        None if it has not by the monotonic time `deadline`."""
        while True:
            with self._lock:
                for gps, arrived, _ in self.first_nonzero[channel]:
                    if abs(gps - start_gps) < 1e-6:
                        return arrived
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.005)

    def total(self, what: str) -> int:
        """``blocks``, ``lost`` or ``out_of_order``, over every channel."""
        with self._lock:
            return sum(c[what] for c in self.per_channel.values())

    def counts(self) -> dict[str, int]:
        """What arrived, and what arrived amiss."""
        return {**{k: self.total(k) for k in ("blocks", "lost", "out_of_order")},
                "corrupt": self.corrupt, "misdelivered": self.misdelivered}

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def watch_until_told(endpoint: str) -> None:
    """A :class:`_Watcher` in a process of its own: says ``ready``, counts until a line
    arrives on stdin, then prints its counts as JSON."""
    watcher = _Watcher(endpoint)
    print("ready", flush=True)
    sys.stdin.readline()
    watcher.close()
    print(json.dumps(watcher.counts()), flush=True)


def _request(obj: dict) -> bytes:
    return json.dumps(obj).encode()


_SINE = {"channel": "C1:SUS-ETMX_SUSPOS_EXC", "waveform": "sine", "freq": 1.0, "amp": 0.1}
ARRIVAL_GRACE_S = 5.0  # after the last injection, for its first sample to reach the watcher
HOSTILE = [
    b"not json", b"[1, 2, 3]", b"{}",
    _request({**_SINE, "channel": "C1:SUS-ETMZ_SUSPOS_EXC"}),
    _request({**_SINE, "freq": float("nan")}),
    _request({**_SINE, "amp": 1e9}),
    _request({**_SINE, "duration": -5}),
    _request({**_SINE, "freq": -3.0}),
    _request({**_SINE, "waveform": "warble"}),
    _request({"channel": _SINE["channel"], "waveform": "stream", "samples": [1e6] * 20000}),
    _request({**_SINE, "waveform": "noise", "shape": "zpk([1],[oops"}),
    # what it implies later: a ramp no stop could run, a start years ahead
    _request({**_SINE, "duration": "inf", "ramp": 1e300}),
    _request({**_SINE, "duration": "inf", "ramp": 6e14}),
    _request({**_SINE, "start_gps": 2e9}),
]
"""Malformed or hostile ``inject`` requests, each refused with a reason."""
HOSTILE_CONTROL = [
    ("filter", _request({"optic": "ETMX", "dof": "POS", "gain": -30.0, "ramp": 0})),
    ("filter", _request({"optic": "ETMX", "dof": "POS", "gain": 1e300, "ramp": 0})),
    ("filter", b'{"optic": "ETMX", "dof": "POS", "gain": NaN}'),
    ("filter", _request({"optic": "ETMX", "dof": "ROLL", "fm": 1})),
    ("params", _request({"optic": "ETMX", "set": {"mass_kg": 1e-7}})),
    ("params", _request({"optic": "ETMX", "set": {"wire_length_m": -1.0}})),
    ("params", _request({"optic": "ETMX", "watchdog": "off"})),
    ("stop", _request({"id": ["not", "an", "id"]})),
]
"""Hostile requests of the other verbs (poisoned gains, an unstable optic...)."""


def _hostile(endpoint: str, n: int, ifo: str, config_file: str | None = None,
             ) -> tuple[dict[str, int], dict[str, int], int]:
    """Send `n` hostile requests, inject's and the other verbs' in turn: (sent and refused
    with a reason, per verb; unanswered)."""
    attacks = [("inject", p) for p in HOSTILE] + HOSTILE_CONTROL
    sent: dict[str, int] = defaultdict(int)
    refused: dict[str, int] = defaultdict(int)
    unanswered = 0
    with zenoh.open(zenoh_config(connect=[endpoint], mode="client",
                                 config_file=config_file)) as s:
        for i in range(n):
            verb, payload = attacks[i % len(attacks)]
            sent[verb] += 1
            replies = list(s.get(control_key(ifo, verb), payload=payload, timeout=5.0))
            if not replies or replies[0].ok is None:
                unanswered += 1
                continue
            reply = json.loads(replies[0].ok.payload.to_string())
            if not reply.get("ok") and reply.get("reason"):
                refused[verb] += 1
    return dict(sent), dict(refused), unanswered


def cpu_seconds(pid: int) -> float:
    """CPU seconds (user and system) process `pid` has used."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def soak(duration: float = 60.0, optics: str = "all", hostile: int = 1000, port: int = 17461,
         injections_every: float = 2.0, config: str | None = None, load: int = 0,
         suspend: float = 6.0, pauses: int = 16) -> SoakReport:
    """Run the soak (see module docstring) and return its figures; `load` busy processes
    share the cores with it; after the injections a second subscriber is paused `pauses`
    times for 0.1-0.4 s, then suspended for `suspend` seconds.

    Parameters
    ----------
    duration : float
        Seconds of injections and hostile requests.
    optics : str
        The optics served: comma-separated names, or ``"all"``.
    hostile : int
        Hostile requests sent.
    port : int
        TCP port the service listens on (localhost).
    injections_every : float
        Seconds between the short sines injected.
    config : str, optional
        Configuration file; default the shipped one with the watchdog lowered to
        :data:`SOAK_WATCHDOG_UM`.
    load : int
        Busy processes run beside it.
    suspend : float
        Seconds the second subscriber is suspended.
    pauses : int
        Short pauses of the second subscriber before it.

    Returns
    -------
    SoakReport
    """
    endpoint = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="twind-soak-") as tmp:
        config = config or _watchful_config(Path(tmp))
        cmd = [sys.executable, "-m", "twind", "serve", "--optics", optics, "--listen", endpoint,
               "--record", tmp, "--config", config]
        log_path = Path(tmp) / "serve.log"  # a file, not a pipe nobody reads while it fills
        log = log_path.open("w")
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, text=True)
        busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                for _ in range(load)]
        try:
            client = TwinClient.wait([endpoint], timeout=90, alive=lambda: proc.poll() is None)
            watcher = _Watcher(endpoint)
            status0 = client.status()
            cpu0, t0 = cpu_seconds(proc.pid), time.monotonic()
            hostile_result: list[tuple[int, int]] = []
            attack = threading.Thread(target=lambda: hostile_result.append(
                _hostile(endpoint, hostile, status0.ifo)), daemon=True)
            attack.start()
            latencies = _inject_periodically(client, watcher, _targets([status0]),
                                             status0.rate_hz,
                                             t0 + duration, injections_every)[status0.twin]
            latencies = [t for t in latencies if t is not None]
            attack.join(timeout=max(1.0, t0 + duration - time.monotonic() + 30))
            watchdog = _trip_and_rearm(client, status0)
            cpu = (cpu_seconds(proc.pid) - cpu0) / (time.monotonic() - t0)
            status = client.status()
            suspended = _suspend_a_subscriber(client, endpoint, suspend, pauses, config)
            client.close()
            watcher.close()
        finally:
            for p in busy:
                p.kill()
            crashed = proc.poll() is not None
            proc.terminate()
            proc.wait(timeout=60)
            log.close()
            log_tail = log_path.read_text()[-3000:] if crashed else ""
        topics = scan_recording(sorted(Path(tmp).glob("*.mcap"))).values()
        mcap_blocks, mcap_gaps = sum(n for n, _ in topics), sum(g for _, g in topics)
    sent, refused, unanswered = hostile_result[0] if hostile_result else ({}, {}, hostile)
    return SoakReport(
        duration_s=duration, optics=", ".join(status.optics), cpu_fraction=cpu,
        late_blocks=status.late_blocks, max_lag_s=status.max_lag_s,
        bus_blocks=watcher.total("blocks"), bus_lost=watcher.total("lost"),
        bus_out_of_order=watcher.total("out_of_order"), bus_corrupt=watcher.corrupt,
        bus_misdelivered=watcher.misdelivered, bus_anomalies=watcher.anomalies,
        mcap_blocks=mcap_blocks, mcap_gaps=mcap_gaps, latency_s=latencies,
        service_latency=status.injection_latency_s, hostile_sent=sent,
        hostile_refused=refused, hostile_unanswered=unanswered, block_s=status.block_s,
        crashed=crashed, load=load, watchdog=watchdog, log_tail=log_tail, suspended=suspended)


SOAK_WATCHDOG_UM = 20.0
"""The soak's twin trips its watchdogs at this OSEM reading (um): the default (1000 um) is
beyond what the excitation limits can drive (a sine at the RMS limit near POS's resonance
reads ~46 um), so the soak lowers it to see one trip."""


def _watchful_config(folder: Path) -> str:
    """The default configuration with the watchdog at :data:`SOAK_WATCHDOG_UM`, in `folder`."""
    text = DEFAULT_CONFIG.read_text()
    if "watchdog_um" not in text:
        msg = f"{DEFAULT_CONFIG} has no [service] watchdog_um"
        raise TwindError(msg)
    lines = [f"watchdog_um = {SOAK_WATCHDOG_UM}" if line.startswith("watchdog_um") else line
             for line in text.splitlines()]
    (folder / "optics").symlink_to(DEFAULT_CONFIG.parent / "optics")
    path = folder / DEFAULT_CONFIG.name
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _trip_and_rearm(client: TwinClient, status: StatusReply) -> str:
    """Drive one optic's POS at the RMS limit near its resonance until its watchdog trips,
    then re-arm it: what a commissioner sees, in words."""
    optic = status.optics[0]
    reply = client.query("inject", {"channel": dof_channel(status.ifo, optic, "POS", "EXC"),
                                    "waveform": "sine", "freq": 1.0, "amp": 42.0,
                                    "duration": 20.0})
    if not reply.get("accepted"):
        return f"drive refused ({reply.get('reason')})"
    deadline = time.monotonic() + 20
    while client.status().watchdogs[optic] != "tripped" and time.monotonic() < deadline:
        time.sleep(0.1)
    tripped = client.status().watchdogs[optic] == "tripped"
    client.query("stop", {"id": reply["id"]})
    rearmed = client.rearm(optic).watchdog
    return (f"{optic} tripped under a 42 um drive and re-armed" if tripped and
            rearmed == "armed" else f"{optic}: tripped {tripped}, after re-arm {rearmed}")


def _suspend_a_subscriber(client: TwinClient, endpoint: str, seconds: float, pauses: int,
                          config: str) -> dict:
    """Subscribe in another process, deschedule it `pauses` times for 0.1-0.4 s (through
    Zenoh's shared memory, such pauses damaged blocks), then suspend it for `seconds`
    (SIGSTOP, as Ctrl-Z does) and resume it: what the twin lost meanwhile (late blocks,
    lag) and what the subscriber read."""
    proc = subprocess.Popen([sys.executable, "-c", "from twind.lab.soak import "
                             f"watch_until_told; watch_until_told({endpoint!r})"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        if proc.stdout.readline().strip() != "ready":
            msg = "the subscriber to suspend did not start"
            raise TwindError(msg)
        time.sleep(1.0)
        before = client.status()
        for pause in [*np.random.default_rng(0).uniform(0.1, 0.4, pauses), seconds]:
            proc.send_signal(signal.SIGSTOP)
            time.sleep(pause)
            proc.send_signal(signal.SIGCONT)
            time.sleep(0.4)
        time.sleep(3.0)  # it reconnects and reads again
        after = client.status()
        counts = json.loads(proc.communicate("\n", timeout=30)[0])
    finally:
        proc.send_signal(signal.SIGCONT)
        proc.kill()
    return {"seconds": seconds, "pauses": pauses, **counts,
            "late_blocks": after.late_blocks - before.late_blocks,
            "max_lag_s": after.max_lag_s,
            "wait_s": load_config(config, []).service.subscriber_wait_s}


def scan_recording(files: list[Path]) -> dict[str, tuple[int, int]]:
    """Blocks and sequence gaps of a recording per topic, read as a stream: an hour of the
    40m is ~50 GB, far more than memory holds.

    Parameters
    ----------
    files : list of Path
        The recording's files, in order.

    Returns
    -------
    dict of str to (int, int)
        ``(blocks, gaps)`` by data topic.
    """
    last: dict[str, int] = {}
    counts: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for path in files:
        for m in iter_raw_messages(path, topics=lambda t: not t.startswith("twin/@")):
            counts[m.topic][0] += 1
            prev = last.get(m.topic)
            if prev is not None and m.sequence != prev + 1:
                counts[m.topic][1] += 1
            last[m.topic] = m.sequence
    return {topic: (n, gaps) for topic, (n, gaps) in counts.items()}


def _targets(statuses: list[StatusReply]) -> list[tuple[str, str]]:
    """(twin, EXC channel) of the POS, PIT, YAW and SIDE test points of each twin's first
    optic, the twins taken in turn."""
    return [(st.twin, dof_channel(st.ifo, st.optics[0], dof, "EXC"))
            for dof in ("POS", "PIT", "YAW", "SIDE") for st in statuses]


def _inject_periodically(client: TwinClient, watcher: _Watcher, targets: list[tuple[str, str]],
                         rate_hz: float, until: float, every: float,
                         ) -> dict[str, list[float | None]]:
    """Short sines on `targets` in turn until `until`: each twin's latencies from request to
    the first non-zero excitation sample at `watcher` (None for one accepted but not seen
    within `ARRIVAL_GRACE_S` of the last request). Arrivals are looked up after the last
    request, so a late block on a busy host neither stalls the requests nor goes uncounted."""
    requested: list[tuple[str, str, float, float]] = []  # twin, channel, GPS, when asked
    rng = np.random.default_rng(0)
    k = 0
    while time.monotonic() + every < until:
        twin, channel = targets[k % len(targets)]
        k += 1
        t_req = time.monotonic()
        reply = client.query("inject", {"channel": channel, "waveform": "sine", "freq": 5.0,
                                        "amp": 0.01, "duration": 0.5})
        if reply.get("accepted"):
            # a sine starts at zero: its first non-zero sample is the one after the start
            requested.append((twin, channel, reply["start_gps"] + 1 / rate_hz, t_req))
        # random intervals, so requests fall at every phase of the block clock
        time.sleep(max(0.0, rng.uniform(0.5, 1.5) * every - (time.monotonic() - t_req)))
    latencies: dict[str, list[float | None]] = {twin: [] for twin, _ in targets}
    deadline = time.monotonic() + ARRIVAL_GRACE_S
    for twin, channel, gps, t_req in requested:
        arrived = watcher.arrival_of(channel, gps, deadline)
        latencies[twin].append(None if arrived is None else arrived - t_req)
    return latencies


def soak_connected(endpoint: str, duration: float = 60.0, config_file: str | None = None,
                   hostile: int = 100, injections_every: float = 2.0) -> dict:
    """Soak the twins already serving behind `endpoint` (a fleet's router): subscribe to
    every channel, inject short sines on each twin in turn and send hostile requests, then
    ask every twin what it cost.

    Parameters
    ----------
    endpoint : str
        The router or twin to connect to.
    duration : float
        Seconds of injections and hostile requests.
    config_file : str, optional
        Zenoh configuration (credentials, TLS), e.g. deploy/acl/operator.json5.
    hostile : int
        Malformed requests sent meanwhile.
    injections_every : float
        Mean seconds between injections.

    Returns
    -------
    dict
        ``duration_s``, ``hostile`` (sent, refused, unanswered), ``undecodable`` (blocks
        this subscriber could not decode) and ``twins``: per twin its identity, optics, CPU
        over the soak, late blocks, max lag, dropped blocks, the blocks of its optics this
        subscriber saw, lost and out of order, and the injection latency (ms).

    Raises
    ------
    TwindError
        If no twin answers.
    """
    with TwinClient([endpoint], config_file=config_file) as client:
        before = {st.twin: st for st in map(StatusReply.from_json, client.replies("status"))}
        if not before:
            msg = f"no twin answers status at {endpoint}"
            raise TwindError(msg)
        watcher = _Watcher(endpoint, config_file)
        watcher.wait_for({o for st in before.values() for o in st.optics})
        t0 = time.monotonic()
        first = next(iter(before.values()))
        attack: list = []
        thread = threading.Thread(target=lambda: attack.append(
            _hostile(endpoint, hostile, first.ifo, config_file)), daemon=True)
        thread.start()
        latencies = _inject_periodically(client, watcher, _targets(list(before.values())),
                                         first.rate_hz, t0 + duration, injections_every)
        thread.join(timeout=max(1.0, t0 + duration - time.monotonic() + 30))
        after = {st.twin: st for st in map(StatusReply.from_json, client.replies("status"))}
        watcher.close()
    twins = [_twin_figures(b, after.get(twin), watcher, latencies.get(twin, []))
             for twin, b in before.items()]
    sent, refused, unanswered = attack[0] if attack else ({}, {}, hostile)
    return {"duration_s": duration, "twins": twins, "undecodable": watcher.corrupt,
            "hostile": {"sent": sent, "refused": refused, "unanswered": unanswered}}


def _twin_figures(before: StatusReply, after: StatusReply | None, watcher: _Watcher,
                  latencies: list[float | None]) -> dict:
    """One twin's figures over the soak, from its status before and after (None: it did not
    answer at the end) and what the subscriber counted of its optics' channels."""
    optics = set(before.optics)
    seen = Counter()
    for channel, counts in watcher.per_channel.items():
        match = POINT_NAME.match(channel)
        if match and match["optic"] in optics:
            seen.update(counts)
    lat = np.array([t for t in latencies if t is not None]) * 1e3
    figures = {"twin": before.twin, "optics": before.optics, "answered_at_end": bool(after),
               "injected": len(latencies),
               "blocks": seen["blocks"], "lost": seen["lost"],
               "out_of_order": seen["out_of_order"],
               "latency_ms": {"n": int(lat.size),
                              "median": float(np.median(lat)) if lat.size else None,
                              "p99": float(np.percentile(lat, 99)) if lat.size else None}}
    after = after or before
    busy = after.cpu_fraction * after.uptime_s - before.cpu_fraction * before.uptime_s
    elapsed = after.uptime_s - before.uptime_s
    figures.update(cpu_fraction=busy / elapsed if elapsed > 0 else 0.0,
                   late_blocks=after.late_blocks - before.late_blocks,
                   max_lag_s=after.max_lag_s,
                   dropped_blocks=after.dropped_blocks - before.dropped_blocks)
    return figures
