"""The 40m twin across hosts on one machine: network namespaces as hosts on one LAN (a
bridge), running what ``deploy/README.md`` describes, and the soak of that fleet.

A router host runs ``zenoh-router.py``, twin hosts run ``twind serve --mode client
--connect tcp/ROUTER:7447`` (the optics split between them), a recorder host runs ``twind
record``, and the commands a person types run on a control-room host. Every address lies
inside the namespaces made here, and everything is torn down at the end. It needs root and
iproute2 (``ip netns``), and a source checkout: ``deploy/`` is beside the package.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from twind.channels import POINT_NAME
from twind.config import load_config
from twind.errors import TwindError
from twind.lab.soak import cpu_seconds, scan_recording
from twind.recording.writer import TOPIC_ROOT

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
"""deploy/ of the source checkout."""
HOSTS = ("router", "twin1", "twin2", "recorder", "control")
OPEN = {"router": ("-c", str(DEPLOY / "zenoh-router.json5")), "twin": (), "recorder": (),
        "control": ()}
"""deploy/'s open layout: what each role adds to its command line."""
ACL = {"router": ("-c", str(DEPLOY / "acl" / "router.json5"), "--cfg",
                  "transport/auth/usrpwd/dictionary_file:"
                  + json.dumps(str(DEPLOY / "acl" / "credentials.example.txt"))),
       "twin": ("--zenoh-config", str(DEPLOY / "acl" / "twin-client.json5")),
       "recorder": ("--zenoh-config", str(DEPLOY / "acl" / "recorder.json5")),
       "control": ("--zenoh-config", str(DEPLOY / "acl" / "operator.json5"))}
"""deploy/acl: the router checks passwords and rights; each role logs in as itself (the
default layout beyond one host)."""
LAYOUTS = {"open": OPEN, "acl": ACL}


def twind(*args: str) -> tuple[str, ...]:
    """The command line of ``twind ARGS`` in this interpreter."""
    return (sys.executable, "-m", "twind", *args)


def hosts_problem() -> str | None:
    """Why namespaced hosts cannot be made here, or None."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if not shutil.which("ip"):
        return "network namespaces need iproute2's ip"
    if not (DEPLOY / "zenoh-router.py").exists():
        return f"{DEPLOY} not found: the fleet runs from a source checkout"
    return None


class Lan:
    """Hosts as network namespaces on one bridge, addressed 10.<net>.0.<k>/24, and the
    deploy/ layout they run (:data:`OPEN` or :data:`ACL`).

    Parameters
    ----------
    names : tuple of str
        The hosts.
    layout : dict, optional
        What each role adds to its command line; default :data:`OPEN`.
    """

    def __init__(self, names: tuple[str, ...], layout: dict | None = None) -> None:
        self.layout = layout or OPEN
        self.tag = f"tw{os.getpid() % 10000}{random.randrange(100)}"
        self.net = random.randrange(100, 250)
        self.addr = {h: f"10.{self.net}.0.{k + 1}" for k, h in enumerate(names)}
        self.procs: list[subprocess.Popen] = []
        self._ns(f"{self.tag}lan")
        self._ip(f"{self.tag}lan", "link", "add", "br0", "type", "bridge")
        self._ip(f"{self.tag}lan", "link", "set", "br0", "up")
        for k, host in enumerate(names):
            ns, a, b = self.ns(host), f"{self.tag}a{k}", f"{self.tag}b{k}"
            self._ns(ns)
            subprocess.run(["ip", "link", "add", a, "type", "veth", "peer", "name", b], check=True)
            subprocess.run(["ip", "link", "set", a, "netns", ns], check=True)
            subprocess.run(["ip", "link", "set", b, "netns", f"{self.tag}lan"], check=True)
            self._ip(ns, "link", "set", a, "name", "eth0")
            self._ip(ns, "addr", "add", f"{self.addr[host]}/24", "dev", "eth0")
            for dev in ("eth0", "lo"):
                self._ip(ns, "link", "set", dev, "up")
            self._ip(f"{self.tag}lan", "link", "set", b, "master", "br0")
            self._ip(f"{self.tag}lan", "link", "set", b, "up")

    def ns(self, host: str) -> str:
        """The namespace of `host`."""
        return f"{self.tag}{host}"

    def _ns(self, ns: str) -> None:
        subprocess.run(["ip", "netns", "add", ns], check=True)

    @staticmethod
    def _ip(ns: str, *args: str) -> None:
        subprocess.run(["ip", "netns", "exec", ns, "ip", *args], check=True)

    def link(self, host: str, up: bool) -> None:
        """Pull a host's cable out, or put it back."""
        self._ip(self.ns(host), "link", "set", "eth0", "up" if up else "down")

    def start(self, host: str, *cmd: str) -> subprocess.Popen:
        """A process on `host`, its output kept."""
        proc = subprocess.Popen(["ip", "netns", "exec", self.ns(host), *cmd],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.procs.append(proc)
        return proc

    def run(self, host: str, *cmd: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
        """A command on `host`, run to its end."""
        return subprocess.run(["ip", "netns", "exec", self.ns(host), *cmd], text=True,
                              capture_output=True, timeout=timeout)

    def close(self) -> None:
        """Kill every process on the hosts and remove the namespaces."""
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        for host in (*self.addr, "lan"):
            ns = f"{self.tag}{host}" if host == "lan" else self.ns(host)
            pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True,
                                  text=True).stdout.split()
            for pid in pids:
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except ProcessLookupError:
                    pass
            subprocess.run(["ip", "netns", "del", ns], check=False)


@contextmanager
def lan(layout: dict | None = None, names: tuple[str, ...] = HOSTS) -> Iterator[Lan]:
    """A :class:`Lan` of `names`, torn down on leaving."""
    net = Lan(names, layout)
    try:
        yield net
    finally:
        net.close()


class Fleet:
    """deploy/'s router, twin hosts and recorder on a :class:`Lan`, and the control room.

    Parameters
    ----------
    net : Lan
        Hosts named ``router``, ``recorder``, ``control`` and those of `optics`.
    optics : dict of str to tuple of str
        The optics each twin host serves.
    recording : Path
        Folder the recorder host writes ``fleet.mcap`` (rotated) into.
    serve_s : float
        Seconds each twin serves before it ends by itself.
    """

    def __init__(self, net: Lan, optics: dict[str, tuple[str, ...]], recording: Path,
                 serve_s: float = 90.0) -> None:
        self.net, self.optics, self.recording, self.serve_s = net, optics, recording, serve_s
        self.twins: dict[str, subprocess.Popen] = {}
        self.recorder: subprocess.Popen | None = None
        self.router_proc: subprocess.Popen | None = None

    @property
    def endpoint(self) -> str:
        """The router's endpoint."""
        return f"tcp/{self.net.addr['router']}:7447"

    def router(self) -> subprocess.Popen:
        """deploy/'s router on the router host."""
        self.router_proc = self.net.start("router", sys.executable, str(DEPLOY / "zenoh-router.py"),
                                          *self.net.layout["router"], "--listen", self.endpoint)
        time.sleep(1.0)
        return self.router_proc

    def twin(self, host: str) -> subprocess.Popen:
        """``twind serve`` of the host's optics, connected to the router."""
        self.twins[host] = self.net.start(host, *twind(
            "serve", "--optics", ",".join(self.optics[host]), "--mode", "client", "--connect",
            self.endpoint, "--duration", f"{self.serve_s:g}", *self.net.layout["twin"]))
        return self.twins[host]

    def start(self) -> None:
        """The router, every twin host and the recorder, once every twin answers."""
        self.router()
        for host in self.optics:
            self.twin(host)
        self.record("fleet")
        self.answering(len(self.optics))
        if self.recorder.poll() is not None:
            msg = f"the recorder host's twind record ended: {self.recorder.communicate()[1]}"
            raise TwindError(msg)

    def record(self, name: str) -> subprocess.Popen:
        """``twind record`` on the recorder host into ``NAME-0001.mcap``, ... (a new file a
        minute), as deploy/twind-recorder.service runs it; returned once subscribed (its
        first file made)."""
        self.recording.mkdir(exist_ok=True)
        self.recorder = self.net.start("recorder", *twind(
            "record", "-o", str(self.recording / f"{name}.mcap"), "--rotate-s", "60", "--mode",
            "client", "--connect", self.endpoint, *self.net.layout["recorder"]))
        deadline = time.monotonic() + 60.0
        while not (self.recording / f"{name}-0001.mcap").exists():
            if self.recorder.poll() is not None or time.monotonic() > deadline:
                self.recorder.kill()
                msg = (f"twind record on the recorder host made no file: "
                       f"{self.recorder.communicate()[1].strip()[-500:]}")
                raise TwindError(msg)
            time.sleep(0.1)
        return self.recorder

    def control(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
        """``twind ARGS`` in the control room, connected to the router as the operator."""
        return self.net.run("control", *twind(*args, "--connect", self.endpoint,
                                               *self.net.layout["control"]), timeout=timeout)

    def status(self) -> list[dict]:
        """Every twin's status, from the control room."""
        out = self.control("status", "--json", "--wait", "60", timeout=90.0)
        if out.returncode != 0:
            msg = f"twind status in the control room failed: {out.stderr.strip()}"
            raise TwindError(msg)
        status = json.loads(out.stdout)
        return status.get("twins", [status])

    def answering(self, n: int, timeout: float = 90.0) -> list[dict]:
        """The status of every twin, once `n` answer."""
        deadline = time.monotonic() + timeout
        while len(status := self.status()) < n:
            if time.monotonic() > deadline:
                msg = f"{len(status)} of {n} twins answer after {timeout:g} s"
                raise TwindError(msg)
            time.sleep(1.0)
        return status

    def end(self) -> None:
        """Stop the recorder (SIGTERM: its file closed whole) and the twins (SIGINT)."""
        if self.recorder is not None:
            self.recorder.send_signal(signal.SIGTERM)
            _, err = self.recorder.communicate(timeout=120)
            if self.recorder.returncode != 0:
                msg = f"the recorder host's twind record failed: {err.strip()[-500:]}"
                raise TwindError(msg)
        for proc in self.twins.values():
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=60)


def split(optics: list[str], hosts: int) -> dict[str, tuple[str, ...]]:
    """`optics` dealt to twin hosts ``twin1`` .. ``twin<hosts>`` in contiguous runs."""
    if not 1 <= hosts <= len(optics):
        msg = f"{hosts} twin hosts for {len(optics)} optics"
        raise TwindError(msg)
    per = -(-len(optics) // hosts)
    return {f"twin{k + 1}": tuple(optics[k * per:(k + 1) * per]) for k in range(hosts)
            if optics[k * per:(k + 1) * per]}


@dataclass
class FleetSoakReport:
    """What a soak of the namespaced fleet measured, per twin host."""

    duration_s: float
    layout: str
    hosts: dict[str, tuple[str, ...]]
    soak: dict  # twind soak --connect --json, from the control room
    recorded: dict[str, dict] = field(default_factory=dict)  # per twin host: blocks, gaps
    cpu: dict[str, float] = field(default_factory=dict)  # per host: of one core, over the soak

    def lines(self) -> list[str]:
        """Human-readable figures, a line per twin host."""
        by_optics = {tuple(t["optics"]): t for t in self.soak["twins"]}
        out = [f"fleet soak: {len(self.hosts)} twin hosts, a router, a recorder and a control "
               f"room as network namespaces, deploy/{self.layout} layout, "
               f"{self.duration_s:g} s"]
        for host, optics in self.hosts.items():
            t, r = by_optics.get(optics), self.recorded.get(host, {})
            out.append(f"{host} ({', '.join(optics)}):")
            out.append(f"  process CPU {100 * self.cpu.get(host, float('nan')):.1f} % of one "
                       "core; " + (twin_line(t) if t else "no figures: it did not answer"))
            out.append(f"  recorded on the recorder host: {r.get('blocks', 0)} blocks, "
                       f"{r.get('gaps', 0)} gaps")
        out.append(f"router CPU {100 * self.cpu.get('router', float('nan')):.1f} %, recorder "
                   f"CPU {100 * self.cpu.get('recorder', float('nan')):.1f} % of one core")
        hostile = self.soak["hostile"]
        out.append(f"undecodable blocks at the control room: {self.soak['undecodable']}; "
                   f"hostile requests refused with a reason: "
                   f"{sum(hostile['refused'].values())} of {sum(hostile['sent'].values())}, "
                   f"{hostile['unanswered']} unanswered")
        return out


def twin_line(t: dict) -> str:
    """One twin's soak figures (``twind soak --connect --json``'s ``twins`` entries)."""
    lat = t["latency_ms"]
    injections = (f"{lat['n']} injections, latency median {lat['median']:.1f} ms, p99 "
                  f"{lat['p99']:.1f} ms" if lat["n"] else "no injection measured")
    return (f"twin {t['twin']}: busy {100 * t['cpu_fraction']:.1f} % of the time computing "
            f"and publishing, "
            f"{t['late_blocks']} late blocks, max lag {1e3 * t['max_lag_s']:.1f} ms, "
            f"{t['dropped_blocks']} dropped; at the control room {t['blocks']} blocks, "
            f"{t['lost']} lost, {t['out_of_order']} out of order; {injections}")


def soak_fleet(duration: float = 60.0, layout: str = "acl", twin_hosts: int = 2,
               hostile: int = 100) -> FleetSoakReport:
    """Build the namespaced fleet serving every optic of the shipped configuration, soak it
    from the control room (``twind soak --connect``) and read the recorder host's files.

    Parameters
    ----------
    duration : float
        Seconds of the soak.
    layout : str
        ``"acl"`` (deploy/acl: passwords and rights at the router) or ``"open"``.
    twin_hosts : int
        Twin hosts the ten optics are split between.
    hostile : int
        Malformed requests the control room sends meanwhile.

    Returns
    -------
    FleetSoakReport

    Raises
    ------
    TwindError
        Where the hosts cannot be made, or a part of the fleet fails.
    """
    problem = hosts_problem()
    if problem:
        msg = f"twind soak --fleet: {problem}"
        raise TwindError(msg)
    hosts = split(list(load_config(None).optics), twin_hosts)
    names = ("router", *hosts, "recorder", "control")
    with tempfile.TemporaryDirectory(prefix="twind-fleet-") as tmp, \
            lan(LAYOUTS[layout], names) as net:
        fleet = Fleet(net, hosts, Path(tmp) / "rec", serve_s=duration + 120.0)
        fleet.start()
        procs = {**fleet.twins, "router": fleet.router_proc, "recorder": fleet.recorder}
        cpu0, t0 = {h: cpu_seconds(p.pid) for h, p in procs.items()}, time.monotonic()
        out = fleet.control("soak", "--duration", f"{duration:g}", "--hostile", str(hostile),
                            "--json", timeout=duration + 120.0)
        cpu = {h: (cpu_seconds(p.pid) - cpu0[h]) / (time.monotonic() - t0)
               for h, p in procs.items()}
        fleet.end()
        if out.returncode != 0:
            msg = f"twind soak --connect in the control room failed: {out.stderr.strip()}"
            raise TwindError(msg)
        topics = scan_recording(sorted(fleet.recording.glob("*.mcap")))
    recorded = {host: {"blocks": sum(n for t, (n, _) in topics.items() if _optic(t) in optics),
                       "gaps": sum(g for t, (_, g) in topics.items() if _optic(t) in optics)}
                for host, optics in hosts.items()}
    return FleetSoakReport(duration, layout, hosts, json.loads(out.stdout), recorded, cpu)


def _optic(topic: str) -> str | None:
    """``ETMX`` of ``twin/C1:SUS-ETMX_SUSPOS_IN1``."""
    match = POINT_NAME.match(topic.removeprefix(f"{TOPIC_ROOT}/"))
    return match["optic"] if match else None
