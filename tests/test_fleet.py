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
import shutil
import signal
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from test_deploy_acl import _pki_cryptography, tls_client, tls_twin

from twind.lab.fleet import ACL, DEPLOY, Fleet, lan, twind
from twind.recording.reader import read_session
from twind.recording.session import TruncatedRecordingWarning

pytestmark = [pytest.mark.slow, pytest.mark.skipif(
    not os.environ.get("TWIND_REQUIRE_NETNS") and (os.geteuid() != 0 or not shutil.which("ip")),
    reason="network namespaces need root and iproute2 (CI requires them)")]

OPTICS = {"twin1": ("ETMX", "ETMY"), "twin2": ("ITMX", "ITMY")}


@contextmanager
def fleet(rec: Path, layout: dict | None = None) -> Iterator[Fleet]:
    """deploy/'s router, both twin hosts and the recorder on namespaced hosts, answering."""
    with lan(layout) as net:
        running = Fleet(net, OPTICS, rec)
        running.start()
        yield running


def test_the_fleet_across_hosts(tmp_path: Path) -> None:
    """Two twin hosts, a router, a recorder and a control room: status lists both twins with
    their optics, a third twin of optics already served is refused at its start, an injection
    reaches the twin that serves its optic and says which, a twin
    host's cable pulled for 10 s costs its channels that span only, recorded as a gap with
    its GPS times, and the other twin's channels none."""
    rec = tmp_path / "rec"
    with fleet(rec) as f:
        serving = {tuple(s["optics"]): s["twin"] for s in f.answering(2)}
        assert set(serving) == {OPTICS["twin1"], OPTICS["twin2"]}
        second = f.control("serve", "--optics", "ITMX,ETMX", "--mode", "client", timeout=120)
        assert second.returncode == 2, second.stderr  # refused before it serves anything
        assert f"ETMX already served on this bus by twin {serving[OPTICS['twin1']]}" in \
            second.stderr or f"ITMX already served on this bus by twin " \
            f"{serving[OPTICS['twin2']]}" in second.stderr, second.stderr
        out = f.control("inject", "C1:SUS-ITMY_SUSPOS_EXC", "sine", "--freq", "3", "--amp",
                        "0.1", "--duration", "5")
        assert out.returncode == 0, out.stderr
        assert f"started by twin {serving[OPTICS['twin2']]}" in out.stderr

        f.net.link("twin2", up=False)
        time.sleep(10.0)
        f.net.link("twin2", up=True)
        f.answering(2)  # the twin host back on the bus
        time.sleep(3.0)
        f.end()

    session = read_session(sorted(rec.glob("*.mcap")))
    assert not [g for g in session.gaps if "ETM" in g.channel]  # the other host lost nothing
    itm = [g for g in session.gaps if "ITM" in g.channel]
    assert len(itm) == 48, [str(g) for g in itm]  # each channel of both optics, once
    for g in itm:
        assert 10.0 <= g.gps_end - g.gps_start < 20.0, str(g)  # the outage, not more


def test_a_twin_host_and_the_router_restarted(tmp_path: Path) -> None:
    """A twin host killed and started again, then the router: each outage is a gap in the
    recording with its GPS span (a restart where the twin's numbering began again), and the
    fleet answers again without a hand on it."""
    rec = tmp_path / "rec"
    with fleet(rec) as f:
        time.sleep(2.0)  # the recorder holds blocks of twin1 before it goes: a restart is seen
        f.twins["twin1"].kill()
        f.twins["twin1"].communicate()
        time.sleep(3.0)
        f.twin("twin1")
        f.answering(2)
        time.sleep(2.0)
        f.router_proc.kill()
        f.router_proc.communicate()
        time.sleep(5.0)
        f.router()
        f.answering(2)
        time.sleep(3.0)
        f.end()

    session = read_session(sorted(rec.glob("*.mcap")))
    by_channel: dict[str, list] = {}
    for g in session.gaps:
        by_channel.setdefault(g.channel, []).append(g)
    assert len(by_channel) == 96  # every channel of the four optics
    for channel, gaps in by_channel.items():
        restarted = [g for g in gaps if g.restarted]
        assert len(restarted) == ("ETM" in channel), [str(g) for g in gaps]
        assert all(3.0 <= g.gps_end - g.gps_start < 60.0 for g in gaps), [str(g) for g in gaps]


def test_the_fleet_behind_the_acl_router(tmp_path: Path) -> None:
    """deploy/acl on the hosts: the router checks each role's password and rights. The
    operator in the control room sees both twins and injects; a viewer's injection reaches
    no twin and is said to be refused by access rights; the recorder, logged in as the
    recorder, records every optic of both twin hosts. ``twind soak --connect`` from the
    control room gives each twin host's figures. The recorder killed and started again 5 s
    later (deploy/twind-recorder.service's RestartSec) into files of its own: the files
    read together lose only the outage, a gap with its GPS span."""
    rec = tmp_path / "rec"
    with fleet(rec, ACL) as f:
        time.sleep(2.0)
        f.recorder.kill()
        f.recorder.communicate()
        time.sleep(5.0)
        f.record("restarted")
        inject = ("inject", "C1:SUS-ETMX_SUSPOS_EXC", "sine", "--freq", "3", "--amp", "0.1",
                  "--duration", "2", "--timeout", "2")
        out = f.control(*inject)
        assert out.returncode == 0, out.stderr
        viewer = f.net.run("control", *twind(*inject, "--connect", f.endpoint, "--zenoh-config",
                                             str(DEPLOY / "acl" / "viewer.json5")))
        assert viewer.returncode == 2 and "access rights" in viewer.stderr, viewer.stderr
        soak = f.control("soak", "--duration", "8", "--hostile", "20", "--json", timeout=120)
        assert soak.returncode == 0, soak.stderr
        time.sleep(3.0)
        f.end()
    figures = json.loads(soak.stdout)
    assert sorted(tuple(t["optics"]) for t in figures["twins"]) == sorted(OPTICS.values())
    for t in figures["twins"]:
        assert t["answered_at_end"] and t["blocks"] > 100 and t["latency_ms"]["n"] >= 1, t
    assert sum(figures["hostile"]["refused"].values()) == 20, figures["hostile"]
    files = sorted(rec.glob("*.mcap"))
    assert [p.name for p in files] == ["fleet-0001.mcap", "restarted-0001.mcap"]
    with pytest.warns(TruncatedRecordingWarning):
        session = read_session(files)
    optics = {c.split("-")[1].split("_")[0] for c in session.channels}
    assert optics == {"ETMX", "ETMY", "ITMX", "ITMY"}
    assert len(session.gaps) == 96, [str(g) for g in session.gaps]  # each channel, once
    for g in session.gaps:
        assert 5.0 <= g.gps_end - g.gps_start < 15.0, str(g)  # the outage and a chunk
    starts = [e for e in session.events if e["event"] == "start"]
    assert len(starts) == 1 + sum(t["injected"] for t in figures["twins"]), starts


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

        serve = net.start("twin1", *twind("serve", "--optics", "ETMX", "--zenoh-config", twin,
                                           "--listen", twin_at, "--duration", "90"))
        status = net.run("control", *twind("status", "--json", "--wait", "60", "--connect",
                                            twin_at, "--zenoh-config", client("operator")))
        assert status.returncode == 0, (status.stderr, serve.poll())
        assert json.loads(status.stdout)["optics"] == ["ETMX"]
        rec = tmp_path / "rec"
        rec.mkdir()
        recorder = net.start("recorder", *twind("record", "-o", str(rec / "tls.mcap"),
                                                 "--mode", "client", "--connect", twin_at,
                                                 "--zenoh-config", client("recorder")))
        deadline = time.monotonic() + 30
        while not list(rec.glob("*.mcap")):  # subscribed: its first file made
            assert recorder.poll() is None and time.monotonic() < deadline, \
                recorder.communicate()
            time.sleep(0.2)
        inject = ("inject", "C1:SUS-ETMX_SUSPOS_EXC", "sine", "--freq", "3", "--amp", "0.1",
                  "--duration", "2", "--connect", twin_at, "--timeout", "2", "--zenoh-config")
        assert net.run("control", *twind(*inject, client("operator"))).returncode == 0
        viewer = net.run("control", *twind(*inject, client("viewer")))
        assert viewer.returncode == 2 and "access rights" in viewer.stderr, viewer.stderr
        time.sleep(3.0)
        recorder.send_signal(signal.SIGTERM)
        assert recorder.communicate(timeout=60) and recorder.returncode == 0
        serve.send_signal(signal.SIGINT)
        serve.communicate(timeout=60)
    session = read_session(sorted(rec.glob("*.mcap")))
    assert "C1:SUS-ETMX_SUSPOS_IN1" in session.channels
    assert [e["event"] for e in session.events].count("start") == 1
