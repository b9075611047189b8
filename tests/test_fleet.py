"""The 40m twin across hosts: network namespaces as hosts on one LAN (a bridge), the router of
deploy/ on its own host, two twin hosts splitting optics, a recorder host and a control room,
every address inside the namespaces the test makes.

It runs what deploy/README.md describes: ``zenoh-router.py -c zenoh-router.json5``, ``twind
serve --mode client --connect tcp/ROUTER:7447`` per twin host, ``twind record`` on the
recorder host, and the commands a person types in the control room.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from test_deploy_acl import _pki_cryptography, tls_client, tls_twin

from twind.recording.reader import read_session

pytestmark = pytest.mark.skipif(
    not os.environ.get("TWIND_REQUIRE_NETNS") and (os.geteuid() != 0 or not shutil.which("ip")),
    reason="network namespaces need root and iproute2 (CI requires them)")

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
HOSTS = ("router", "twin1", "twin2", "recorder", "control")
OPTICS = {"twin1": ("ETMX", "ETMY"), "twin2": ("ITMX", "ITMY")}
OPEN = {"router": ("-c", str(DEPLOY / "zenoh-router.json5")), "twin": (), "recorder": (),
        "control": ()}
"""deploy/'s open layout: what each role adds to its command line."""
ACL = {"router": ("-c", str(DEPLOY / "acl" / "router.json5"), "--cfg",
                  "transport/auth/usrpwd/dictionary_file:"
                  + json.dumps(str(DEPLOY / "acl" / "credentials.example.txt"))),
       "twin": ("--zenoh-config", str(DEPLOY / "acl" / "twin-client.json5")),
       "recorder": ("--zenoh-config", str(DEPLOY / "acl" / "recorder.json5")),
       "control": ("--zenoh-config", str(DEPLOY / "acl" / "operator.json5"))}
"""deploy/acl: the router checks passwords and rights; each role logs in as itself."""


class Lan:
    """Hosts as network namespaces on one bridge, addressed 10.<net>.0.<k>/24, and the
    deploy/ layout they run (:data:`OPEN` or :data:`ACL`)."""

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
        return subprocess.run(["ip", "netns", "exec", self.ns(host), *cmd], text=True,
                              capture_output=True, timeout=timeout)

    def close(self) -> None:
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
def lan(layout: dict | None = None) -> Iterator[Lan]:
    net = Lan(HOSTS, layout)
    try:
        yield net
    finally:
        net.close()


def _twind(*args: str) -> tuple[str, ...]:
    return (sys.executable, "-m", "twind", *args)


def _status(net: Lan, router: str) -> list[dict]:
    out = net.run("control", *_twind("status", "--json", "--connect", router, "--wait", "60",
                                     *net.layout["control"]))
    assert out.returncode == 0, out.stderr
    status = json.loads(out.stdout)
    return status.get("twins", [status])


def _router(net: Lan) -> subprocess.Popen:
    """deploy/'s router on the router host."""
    proc = net.start("router", sys.executable, str(DEPLOY / "zenoh-router.py"),
                     *net.layout["router"], "--listen", _endpoint(net))
    time.sleep(1.0)
    return proc


def _endpoint(net: Lan) -> str:
    return f"tcp/{net.addr['router']}:7447"


def _twin(net: Lan, host: str) -> subprocess.Popen:
    return net.start(host, *_twind("serve", "--optics", ",".join(OPTICS[host]), "--mode",
                                   "client", "--connect", _endpoint(net), "--duration", "90",
                                   *net.layout["twin"]))


def _fleet(net: Lan, rec: Path) -> tuple[dict[str, subprocess.Popen], subprocess.Popen]:
    """The router, both twin hosts and the recorder, once both twins answer."""
    _router(net)
    twins = {h: _twin(net, h) for h in OPTICS}
    rec.mkdir()
    recorder = net.start("recorder", *_twind("record", "-o", str(rec / "fleet.mcap"),
                                             "--mode", "client", "--connect", _endpoint(net),
                                             *net.layout["recorder"]))
    _answering(net, 2)
    assert recorder.poll() is None, recorder.communicate()
    return twins, recorder


def _answering(net: Lan, n: int, timeout: float = 90.0) -> list[dict]:
    """The status of every twin, once `n` answer."""
    deadline = time.monotonic() + timeout
    while len(status := _status(net, _endpoint(net))) < n:
        assert time.monotonic() < deadline, status
        time.sleep(1.0)
    return status


def _end(twins: dict[str, subprocess.Popen], recorder: subprocess.Popen) -> None:
    recorder.send_signal(signal.SIGTERM)
    _, err = recorder.communicate(timeout=60)
    assert recorder.returncode == 0, err
    for proc in twins.values():
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)


def test_the_fleet_across_hosts(tmp_path: Path) -> None:
    """Two twin hosts, a router, a recorder and a control room: status lists both twins with
    their optics, a third twin of optics already served is refused at its start, an injection
    reaches the twin that serves its optic and says which, a twin
    host's cable pulled for 10 s costs its channels that span only, recorded as a gap with
    its GPS times, and the other twin's channels none."""
    rec = tmp_path / "rec"
    with lan() as net:
        twins, recorder = _fleet(net, rec)
        serving = {tuple(s["optics"]): s["twin"] for s in _answering(net, 2)}
        assert set(serving) == {OPTICS["twin1"], OPTICS["twin2"]}
        second = net.run("control", *_twind("serve", "--optics", "ITMX,ETMX", "--mode",
                                             "client", "--connect", _endpoint(net)), timeout=120)
        assert second.returncode == 2, second.stderr  # refused before it serves anything
        assert f"ETMX already served on this bus by twin {serving[OPTICS['twin1']]}" in \
            second.stderr or f"ITMX already served on this bus by twin " \
            f"{serving[OPTICS['twin2']]}" in second.stderr, second.stderr
        out = net.run("control", *_twind("inject", "C1:SUS-ITMY_SUSPOS_EXC", "sine", "--freq",
                                          "3", "--amp", "0.1", "--duration", "5", "--connect",
                                          _endpoint(net)))
        assert out.returncode == 0, out.stderr
        assert f"started by twin {serving[OPTICS['twin2']]}" in out.stderr

        net.link("twin2", up=False)
        time.sleep(10.0)
        net.link("twin2", up=True)
        _answering(net, 2)  # the twin host back on the bus
        time.sleep(3.0)
        _end(twins, recorder)

    session = read_session(sorted(rec.glob("*.mcap")))
    assert not [g for g in session.gaps if "ETM" in g.channel]  # the other host lost nothing
    itm = [g for g in session.gaps if "ITM" in g.channel]
    assert len(itm) == 42, [str(g) for g in itm]  # each channel of both optics, once
    for g in itm:
        assert 10.0 <= g.gps_end - g.gps_start < 20.0, str(g)  # the outage, not more


def test_a_twin_host_and_the_router_restarted(tmp_path: Path) -> None:
    """A twin host killed and started again, then the router: each outage is a gap in the
    recording with its GPS span (a restart where the twin's numbering began again), and the
    fleet answers again without a hand on it."""
    rec = tmp_path / "rec"
    with lan() as net:
        twins, recorder = _fleet(net, rec)
        twins["twin1"].kill()
        twins["twin1"].communicate()
        time.sleep(3.0)
        twins["twin1"] = _twin(net, "twin1")
        _answering(net, 2)
        time.sleep(2.0)
        router = net.procs[0]
        router.kill()
        router.communicate()
        time.sleep(5.0)
        _router(net)
        _answering(net, 2)
        time.sleep(3.0)
        _end(twins, recorder)

    session = read_session(sorted(rec.glob("*.mcap")))
    by_channel: dict[str, list] = {}
    for g in session.gaps:
        by_channel.setdefault(g.channel, []).append(g)
    assert len(by_channel) == 84  # every channel of the four optics
    for channel, gaps in by_channel.items():
        restarted = [g for g in gaps if g.restarted]
        assert len(restarted) == ("ETM" in channel), [str(g) for g in gaps]
        assert all(3.0 <= g.gps_end - g.gps_start < 60.0 for g in gaps), [str(g) for g in gaps]


def test_the_fleet_behind_the_acl_router(tmp_path: Path) -> None:
    """deploy/acl on the hosts: the router checks each role's password and rights. The
    operator in the control room sees both twins and injects; a viewer's injection reaches
    no twin and is said to be refused by access rights; the recorder, logged in as the
    recorder, records every optic of both twin hosts."""
    rec = tmp_path / "rec"
    with lan(ACL) as net:
        twins, recorder = _fleet(net, rec)
        inject = ("inject", "C1:SUS-ETMX_SUSPOS_EXC", "sine", "--freq", "3", "--amp", "0.1",
                  "--duration", "2", "--connect", _endpoint(net), "--timeout", "2")
        out = net.run("control", *_twind(*inject, *ACL["control"]))
        assert out.returncode == 0, out.stderr
        viewer = net.run("control", *_twind(*inject, "--zenoh-config",
                                            str(DEPLOY / "acl" / "viewer.json5")))
        assert viewer.returncode == 2 and "access rights" in viewer.stderr, viewer.stderr
        time.sleep(3.0)
        _end(twins, recorder)
    session = read_session(sorted(rec.glob("*.mcap")))
    optics = {c.split("-")[1].split("_")[0] for c in session.channels}
    assert optics == {"ETMX", "ETMY", "ITMX", "ITMY"}
    assert [e["event"] for e in session.events].count("start") == 1  # the operator's only


def test_a_tls_twin_host_and_its_clients_on_other_hosts(tmp_path: Path) -> None:
    """deploy/tls across hosts: a twin host serving TLS only with client certificates, its
    server certificate for the host's address; the recorder host records with the
    "recorder" certificate, the control room's operator sees the twin and injects, a
    viewer's injection is refused by the rights its certificate has."""
    pki = tmp_path / "pki"
    pki.mkdir()
    with lan() as net:
        twin_at = f"tls/{net.addr['twin1']}:7447"
        _pki_cryptography(pki, ("operator", "viewer", "recorder"), (net.addr["twin1"],))
        twin = tls_twin(pki, tmp_path)

        def client(cn: str) -> str:
            return tls_client(pki, cn, tmp_path)

        serve = net.start("twin1", *_twind("serve", "--optics", "ETMX", "--zenoh-config", twin,
                                           "--listen", twin_at, "--duration", "90"))
        status = net.run("control", *_twind("status", "--json", "--wait", "60", "--connect",
                                            twin_at, "--zenoh-config", client("operator")))
        assert status.returncode == 0, (status.stderr, serve.poll())
        assert json.loads(status.stdout)["optics"] == ["ETMX"]
        rec = tmp_path / "rec"
        rec.mkdir()
        recorder = net.start("recorder", *_twind("record", "-o", str(rec / "tls.mcap"),
                                                 "--mode", "client", "--connect", twin_at,
                                                 "--zenoh-config", client("recorder")))
        deadline = time.monotonic() + 30
        while not list(rec.glob("*.mcap")):  # subscribed: its first file made
            assert recorder.poll() is None and time.monotonic() < deadline, \
                recorder.communicate()
            time.sleep(0.2)
        inject = ("inject", "C1:SUS-ETMX_SUSPOS_EXC", "sine", "--freq", "3", "--amp", "0.1",
                  "--duration", "2", "--connect", twin_at, "--timeout", "2", "--zenoh-config")
        assert net.run("control", *_twind(*inject, client("operator"))).returncode == 0
        viewer = net.run("control", *_twind(*inject, client("viewer")))
        assert viewer.returncode == 2 and "access rights" in viewer.stderr, viewer.stderr
        time.sleep(3.0)
        _end({"twin1": serve}, recorder)
    session = read_session(sorted(rec.glob("*.mcap")))
    assert "C1:SUS-ETMX_SUSPOS_IN1" in session.channels
    assert [e["event"] for e in session.events].count("start") == 1
