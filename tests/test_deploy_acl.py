"""deploy/: the Zenoh configurations do what deploy/README.md says, on loopback.

- acl/twin.json5 (user/password + access control on the twin's session): ``operator`` gets
  answers from inject; ``viewer`` gets status and the data, but its inject query reaches no
  queryable and gets no reply, and what it publishes under twin/** never reaches the twin;
  no credentials or a wrong password cannot connect.
- acl/router.json5 (the same rights enforced by a router between users and a twin that logs
  in as ``twin``), run by deploy/zenoh-router.py.
- tls/twin.json5 + tls/client.json5 (TLS only, client certificates, rights by certificate
  common name), with certificates made in the test (cryptography, or deploy/tls/make-certs.sh
  with openssl): the operator's and viewer's rights as above; plain TCP, a client without a
  certificate and one whose certificate another CA signed cannot connect.

The twin is a stand-in (the control queryables and one data channel on a session opened with
the configuration under test, which is all Zenoh's access control sees), or ``twind serve``
itself where it runs.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import shutil
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

import numpy as np
import pytest
import zenoh
from servicekit import free_port, running

from twind.bus.codec import SampleBlock
from twind.bus.keys import all_data, control_key, data_key
from twind.bus.session import zenoh_config
from twind.client import AccessRefused, TwinClient, TwinUnreachable
from twind.protocol import StatusReply
from twind.recording.reader import read_session
from twind.recording.session import RecordingError, TruncatedRecordingWarning

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
CREDENTIALS = DEPLOY / "acl" / "credentials.example.txt"
CHANNEL = "C1:SUS-ETMX_SUSPOS_IN1"
VERBS = ("status", "inject", "stop", "params", "filter")
NO_REPLY_S = 1.5  # how long a refused query is given to (not) get an answer


def config(path: Path | str | None, **keys: object) -> zenoh.Config:
    """A deploy/ configuration with some keys replaced (``a__b`` stands for ``a/b``)."""
    conf = zenoh.Config.from_file(str(path)) if path else zenoh.Config()
    for key, value in keys.items():
        conf.insert_json5(key.replace("__", "/"), json.dumps(value))
    return conf


def materialise(conf: zenoh.Config, path: Path) -> str:
    """Write `conf` to a file, for ``--zenoh-config`` and ``TwinClient(config_file=...)``."""
    path.write_text(str(conf))
    return str(path)


STATUS = StatusReply(twin="stand-in", ifo="C1", optics=["ETMX"], rate_hz=16384.0,
                     block_s=1 / 16, speed=1.0, gps=0.0, uptime_s=0.0, blocks=0,
                     real_time_factor=0.0, lag_s=0.0, max_lag_s=0.0, late_blocks=0,
                     dropped_blocks=0, injection_latency_s={}, cpu_fraction=0.0,
                     excitations=[], config="", watchdogs={"ETMX": "armed"})
"""What the stand-in answers to status: a status as a twin sends it."""


class StandIn:
    """The twin as access control sees it: its five control queryables, its events and one
    data channel published every 20 ms, on a session opened with the configuration under test.
    It records the requests that reach it and any foreign publication under twin/**."""

    def __init__(self, conf: zenoh.Config) -> None:
        self.session = zenoh.open(conf)
        self.reached: list[tuple[str, dict]] = []
        self.foreign: list[str] = []
        self.queryables = [self.session.declare_queryable(control_key("C1", v), self._answer(v))
                           for v in VERBS]
        self.pub = self.session.declare_publisher(data_key(CHANNEL))
        self.sub = self.session.declare_subscriber(all_data(), self._on_sample)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._publish, daemon=True)
        self._thread.start()

    def _answer(self, verb: str):  # noqa: ANN202
        def on_query(query: zenoh.Query) -> None:
            request = json.loads(query.payload.to_string()) if query.payload is not None else {}
            self.reached.append((verb, request))
            reply = {"ok": True, "ifo": "C1", "verb": verb, "twin": "stand-in"}
            if verb == "inject":
                reply |= {"accepted": True, "id": f"exc-{len(self.reached)}"}
            elif verb == "stop":
                reply |= {"stopped": [request.get("id")]}
            elif verb == "status":
                reply |= STATUS.to_json()
            query.reply(query.key_expr, json.dumps(reply))

        return on_query

    def _on_sample(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        if data.startswith(b"spoof"):
            self.foreign.append(str(sample.key_expr))

    def _publish(self) -> None:
        seq = 0
        while not self._stop.wait(0.02):
            block = SampleBlock(CHANNEL, 1.4e9 + seq / 16, 16384.0, seq, np.zeros(64), "um")
            self.pub.put(block.encode())
            seq += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.session.close()


@contextmanager
def standin(conf: zenoh.Config) -> Iterator[StandIn]:
    twin = StandIn(conf)
    try:
        yield twin
    finally:
        twin.close()


class Watcher:
    """A client session subscribed to the twin's data (and allowed to try publishing)."""

    def __init__(self, endpoint: str, config_file: str | None) -> None:
        self.session = zenoh.open(zenoh_config(connect=[endpoint], mode="client",
                                               config_file=config_file))
        self.blocks: list[SampleBlock] = []
        self.sub = self.session.declare_subscriber(
            all_data(), lambda s: self.blocks.append(SampleBlock.decode(s.payload.to_bytes()))
            if not s.payload.to_bytes().startswith(b"spoof") else None)

    def wait_for_data(self, channel: str | None = None, timeout: float = 5.0) -> set[str]:
        """The channels seen once any block (or one of `channel`) has come, or at `timeout`:
        a step's channels arrive one block at a time, so the first may be another's."""
        deadline = time.monotonic() + timeout
        seen: set[str] = set()
        while time.monotonic() < deadline and not ((channel in seen) if channel else seen):
            time.sleep(0.05)
            seen = {b.channel for b in list(self.blocks)}  # the subscriber appends meanwhile
        return seen

    def close(self) -> None:
        self.session.close()


def cannot_connect(endpoint: str, conf: zenoh.Config) -> bool:
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    try:
        session = zenoh.open(conf)
    except zenoh.ZError:
        return True
    session.close()
    return False


def wait_until_answering(endpoint: str, config_file: str, proc: subprocess.Popen | None = None,
                         timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with TwinClient(connect=[endpoint], timeout=1.0, config_file=config_file) as c:
                c.status()
            return
        except (TwinUnreachable, zenoh.ZError):
            if (proc is not None and proc.poll() is not None) or time.monotonic() > deadline:
                out = proc.communicate()[1][-3000:] if proc is not None else ""
                pytest.fail(f"nothing answered status on {endpoint}: {out}")
            time.sleep(0.2)


def round_trip(session: zenoh.Session) -> None:
    """A status query answered over `session`'s link: what the session sent before it (a
    put, a declaration) has reached the router and, when routed, the twin."""
    list(session.get(control_key("C1", "status"), timeout=5.0))


def recorded(folder: Path, channel: str = CHANNEL, timeout: float = 60.0) -> None:
    """Wait until the recording being written in `folder` holds a block of `channel`
    (`timeout` bounds a stuck test, not the recorder)."""
    deadline = time.monotonic() + timeout
    while True:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TruncatedRecordingWarning)
            try:
                if len(read_session(sorted(folder.glob("*.mcap")))[channel].sequences):
                    return
            except RecordingError:  # no file yet, or no block of it in a closed chunk
                pass
        assert time.monotonic() < deadline, f"no block of {channel} recorded in {folder}"
        time.sleep(0.1)


def check_rights(endpoint: str, operator_cfg: str, viewer_cfg: str,
                 twin: StandIn | None) -> None:
    """The operator drives; the viewer watches and gets no answer from inject."""
    with TwinClient(connect=[endpoint], timeout=5.0, config_file=operator_cfg) as op:
        assert op.status().ifo == "C1"
        exc = op.inject("C1:SUS-ETMX_SUSPOS_EXC", "sine", freq=3.0, amp=0.1, duration=2.0)
        assert exc.startswith("exc-")
        assert op.stop(exc) == [exc]
    watcher = Watcher(endpoint, viewer_cfg)
    try:
        with TwinClient(connect=[endpoint], timeout=NO_REPLY_S, config_file=viewer_cfg) as viewer:
            status = viewer.status()
            assert status.ifo == "C1"
            before = list(twin.reached) if twin else None
            # the twin never hears of it; the client tells the refusal from a missing twin
            with pytest.raises(AccessRefused, match="access rights of this session do not allow"):
                viewer.inject("C1:SUS-ETMX_SUSPOS_EXC", "sine", freq=3.0, amp=0.1, duration=2.0)
            for verb in ("stop", "params", "filter"):
                with pytest.raises(AccessRefused, match=verb):
                    viewer.query(verb, {"all": True})
            if twin is not None:
                # the refused queries never reached the twin; the client's status probes did
                assert {verb for verb, _ in twin.reached[len(before):]} <= {"status"}
        assert CHANNEL in watcher.wait_for_data(CHANNEL)
        watcher.session.put(data_key(CHANNEL), b"spoof from the viewer")
        round_trip(watcher.session)
        if twin is not None:
            assert twin.foreign == []
    finally:
        watcher.close()


# ------------------------------------------------------------------------------ the files
def test_deploy_configurations_load() -> None:
    files = sorted(DEPLOY.glob("**/*.json5"))
    assert len(files) >= 9
    for path in files:
        zenoh.Config.from_file(str(path))  # raises on a key Zenoh does not know
    router = zenoh.Config.from_file(str(DEPLOY / "zenoh-router.json5"))
    assert json.loads(router.get_json("mode")) == "router"
    assert json.loads(router.get_json("scouting/multicast/enabled")) is False
    users = {line.split(":")[0] for line in CREDENTIALS.read_text().split()}
    assert users == {"operator", "viewer", "recorder", "twin"}
    for role in ("operator", "viewer", "recorder"):
        auth = json.loads(zenoh.Config.from_file(str(DEPLOY / "acl" / f"{role}.json5"))
                          .get_json("transport/auth/usrpwd"))
        assert f"{auth['user']}:{auth['password']}" in CREDENTIALS.read_text().split()
    units = {p.name: p.read_text() for p in DEPLOY.glob("*.service")}
    assert set(units) == {"twind-router.service", "twind@.service", "twind-recorder.service"}
    assert "--optics %i" in units["twind@.service"]
    # beyond one host access control is the default: the router checks, each role logs in
    assert "ExecStart=/usr/bin/zenohd -c /etc/twind/acl/router.json5" in \
        units["twind-router.service"]
    env = dict(line.split("=", 1) for line in (DEPLOY / "twind.env.example").read_text()
               .splitlines() if line and not line.startswith("#"))
    assert env["TWIND_ZENOH_CONFIG"] == "/etc/twind/acl/twin-client.json5"
    assert env["TWIND_RECORDER_ZENOH_CONFIG"] == "/etc/twind/acl/recorder.json5"


# ------------------------------------------------------------------------------ user/password
def _twin_acl(port: int) -> zenoh.Config:
    return config(DEPLOY / "acl" / "twin.json5", mode="peer",
                  listen__endpoints=[f"tcp/127.0.0.1:{port}"],
                  scouting__multicast__enabled=False,
                  transport__auth__usrpwd__dictionary_file=str(CREDENTIALS))


def test_usrpwd_acl_on_the_twin() -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with standin(_twin_acl(port)) as twin:
        check_rights(endpoint, str(DEPLOY / "acl" / "operator.json5"),
                     str(DEPLOY / "acl" / "viewer.json5"), twin)
        verbs = [v for v, _ in twin.reached]
        assert verbs.count("inject") == 1 and "status" in verbs  # only the operator's inject
        assert cannot_connect(endpoint, config(None))  # no credentials
        assert cannot_connect(endpoint, config(None, transport__auth__usrpwd__user="viewer",
                                               transport__auth__usrpwd__password="guess"))


def serving(*args: str) -> AbstractContextManager[subprocess.Popen]:
    """``twind serve --optics ETMX ARGS`` in a subprocess (not waited for: its clients may
    need credentials to see it)."""
    return running([sys.executable, "-m", "twind", "serve", "--optics", "ETMX", *args])


def test_usrpwd_acl_on_twind_serve(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    conf = materialise(config(DEPLOY / "acl" / "twin.json5",
                              transport__auth__usrpwd__dictionary_file=str(CREDENTIALS)),
                       tmp_path / "twin.json5")
    with serving("--zenoh-config", conf, "--listen", endpoint) as proc:
        wait_until_answering(endpoint, str(DEPLOY / "acl" / "operator.json5"), proc)
        check_rights(endpoint, str(DEPLOY / "acl" / "operator.json5"),
                     str(DEPLOY / "acl" / "viewer.json5"), None)
        assert cannot_connect(endpoint, config(None))


@contextmanager
def router(config_file: Path, port: int, *cfg: str) -> Iterator[str]:
    """deploy/zenoh-router.py on a loopback port."""
    endpoint = f"tcp/127.0.0.1:{port}"
    args = [sys.executable, str(DEPLOY / "zenoh-router.py"), "-c", str(config_file),
            "--listen", endpoint]
    for item in cfg:
        args += ["--cfg", item]
    with running(args, timeout=10) as proc:
        line = proc.stdout.readline()  # printed once the session is open
        assert "listening" in line, proc.communicate()[1][-2000:]
        yield endpoint


def test_plain_router_routes_data_and_queries() -> None:
    """deploy/README.md's layout: router, a twin in client mode behind it, a client."""
    with router(DEPLOY / "zenoh-router.json5", free_port()) as endpoint:
        with serving("--mode", "client", "--connect", endpoint,
                     "--zenoh-config", str(DEPLOY / "zenoh-client.json5")) as proc:
            wait_until_answering(endpoint, None, proc)  # type: ignore[arg-type]
            watcher = Watcher(endpoint, None)
            try:
                assert watcher.wait_for_data()
            finally:
                watcher.close()


def test_usrpwd_acl_on_the_router() -> None:
    dictionary = f"transport/auth/usrpwd/dictionary_file:{json.dumps(str(CREDENTIALS))}"
    with router(DEPLOY / "acl" / "router.json5", free_port(), dictionary) as endpoint:
        twin_conf = config(DEPLOY / "acl" / "twin-client.json5", mode="client",
                           connect__endpoints=[endpoint], scouting__multicast__enabled=False)
        with standin(twin_conf) as twin:
            wait_until_answering(endpoint, str(DEPLOY / "acl" / "operator.json5"))
            check_rights(endpoint, str(DEPLOY / "acl" / "operator.json5"),
                         str(DEPLOY / "acl" / "viewer.json5"), twin)
            assert cannot_connect(endpoint, config(None))
            # a user cannot pose as the twin: the router lets no queryable in from a viewer
            fake = zenoh.open(config(DEPLOY / "acl" / "viewer.json5", mode="client",
                                     connect__endpoints=[endpoint],
                                     scouting__multicast__enabled=False))
            try:
                q = fake.declare_queryable(
                    control_key("C1", "status"),
                    lambda query: query.reply(query.key_expr, '{"ok": false}'))
                round_trip(fake)
                op = zenoh.open(config(DEPLOY / "acl" / "operator.json5", mode="client",
                                       connect__endpoints=[endpoint],
                                       scouting__multicast__enabled=False))
                try:
                    replies = list(op.get(control_key("C1", "status"), timeout=2.0))
                finally:
                    op.close()
                answers = [json.loads(r.ok.payload.to_string()) for r in replies if r.ok]
                assert answers and all(a["ok"] for a in answers)  # only the real twin's
                q.undeclare()
            finally:
                fake.close()


def test_usrpwd_acl_on_the_router_with_twind_serve(tmp_path: Path) -> None:
    """The secured multi-host recipe: twind serve logs in to the ACL router as "twin"."""
    dictionary = f"transport/auth/usrpwd/dictionary_file:{json.dumps(str(CREDENTIALS))}"
    with router(DEPLOY / "acl" / "router.json5", free_port(), dictionary) as endpoint, \
            serving("--mode", "client", "--connect", endpoint,
                    "--zenoh-config", str(DEPLOY / "acl" / "twin-client.json5")) as proc:
        wait_until_answering(endpoint, str(DEPLOY / "acl" / "operator.json5"), proc)
        check_rights(endpoint, str(DEPLOY / "acl" / "operator.json5"),
                     str(DEPLOY / "acl" / "viewer.json5"), None)


# ------------------------------------------------------------------------------ TLS
def _pki_cryptography(folder: Path, common_names: tuple[str, ...],
                      hosts: tuple[str, ...] = ("localhost", "127.0.0.1")) -> None:
    """A CA, the twin's server certificate for `hosts` (names or addresses) and client
    certificates."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.timezone.utc)

    def name(cn: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    def write(stem: str, key: ec.EllipticCurvePrivateKey, cert: x509.Certificate) -> None:
        (folder / f"{stem}.key").write_bytes(key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption()))
        (folder / f"{stem}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))

    def builder(subject: str, issuer: x509.Name,
                public_key) -> x509.CertificateBuilder:  # noqa: ANN001
        return (x509.CertificateBuilder().subject_name(name(subject)).issuer_name(issuer)
                .public_key(public_key).serial_number(x509.random_serial_number())
                .not_valid_before(now - datetime.timedelta(minutes=5))
                .not_valid_after(now + datetime.timedelta(days=1)))

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (builder("twind test CA", name("twind test CA"), ca_key.public_key())
          .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                       content_commitment=False, key_encipherment=False,
                                       data_encipherment=False, key_agreement=False,
                                       encipher_only=False, decipher_only=False), critical=True)
          .sign(ca_key, hashes.SHA256()))
    (folder / "ca.pem").write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    for cn in ("twin", *common_names):
        key = ec.generate_private_key(ec.SECP256R1())
        usage = [ExtendedKeyUsageOID.CLIENT_AUTH]
        b = builder(cn, ca.subject, key.public_key()).add_extension(
            x509.BasicConstraints(ca=False, path_length=None), critical=True)
        if cn == "twin":
            usage.append(ExtendedKeyUsageOID.SERVER_AUTH)
            b = b.add_extension(x509.SubjectAlternativeName(
                [_alt_name(x509, h) for h in hosts]), critical=False)
        b = b.add_extension(x509.ExtendedKeyUsage(usage), critical=False)
        write(cn, key, b.sign(ca_key, hashes.SHA256()))


def _alt_name(x509, host: str):  # noqa: ANN001, ANN202 - cryptography's module and name
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def _pki_openssl(folder: Path, common_names: tuple[str, ...]) -> None:
    subprocess.run(["bash", str(DEPLOY / "tls" / "make-certs.sh"), str(folder),
                    "localhost,127.0.0.1", *common_names], check=True, capture_output=True)


def tls_twin(pki: Path, folder: Path) -> str:
    """deploy/tls/twin.json5 with the certificates of `pki`, written to `folder`."""
    return materialise(config(DEPLOY / "tls" / "twin.json5",
                              transport__link__tls__root_ca_certificate=str(pki / "ca.pem"),
                              transport__link__tls__listen_certificate=str(pki / "twin.pem"),
                              transport__link__tls__listen_private_key=str(pki / "twin.key")),
                       folder / "twin.json5")


def tls_client(pki: Path, cn: str, folder: Path) -> str:
    """deploy/tls/client.json5 with the certificate of `cn`, written to `folder`."""
    return materialise(config(
        DEPLOY / "tls" / "client.json5",
        transport__link__tls__root_ca_certificate=str(pki / "ca.pem"),
        transport__link__tls__connect_certificate=str(pki / f"{cn}.pem"),
        transport__link__tls__connect_private_key=str(pki / f"{cn}.key")),
        folder / f"{cn}.json5")


def _have_cryptography() -> bool:
    try:
        import cryptography  # noqa: F401
    except ImportError:
        return False
    return True


MAKERS = {"cryptography": (_pki_cryptography, _have_cryptography()),
          "openssl": (_pki_openssl, shutil.which("openssl") is not None)}


@pytest.mark.parametrize("maker", sorted(MAKERS))
def test_tls_with_client_certificates_and_acl(tmp_path: Path, maker: str) -> None:
    make, available = MAKERS[maker]
    if not available:
        pytest.skip(f"{maker} is not installed")
    pki, other = tmp_path / "pki", tmp_path / "other"
    pki.mkdir()
    other.mkdir()
    make(pki, ("operator", "viewer"))
    make(other, ("operator",))  # a CA the twin does not trust
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    twin_conf = config(DEPLOY / "tls" / "twin.json5", mode="peer", listen__endpoints=[endpoint],
                       scouting__multicast__enabled=False,
                       transport__link__tls__root_ca_certificate=str(pki / "ca.pem"),
                       transport__link__tls__listen_certificate=str(pki / "twin.pem"),
                       transport__link__tls__listen_private_key=str(pki / "twin.key"))

    def client(folder: Path, cn: str | None) -> zenoh.Config:
        keys = {"transport__link__tls__root_ca_certificate": str(folder / "ca.pem")}
        if cn:
            keys |= {"transport__link__tls__connect_certificate": str(folder / f"{cn}.pem"),
                     "transport__link__tls__connect_private_key": str(folder / f"{cn}.key")}
        conf = config(DEPLOY / "tls" / "client.json5", **keys)
        if not cn:
            conf.insert_json5("transport/link/tls/enable_mtls", "false")
        return conf

    with standin(twin_conf) as twin:
        operator = materialise(client(pki, "operator"), tmp_path / "operator.json5")
        viewer = materialise(client(pki, "viewer"), tmp_path / "viewer.json5")
        check_rights(endpoint, operator, viewer, twin)
        assert cannot_connect(f"tcp/127.0.0.1:{port}", config(None))  # plain TCP
        assert cannot_connect(endpoint, client(pki, None))  # no client certificate
        assert cannot_connect(endpoint, client(other, "operator"))  # another CA


@pytest.mark.slow
def test_the_recorder_logs_in_to_the_acl_router_as_the_recorder(tmp_path: Path) -> None:
    """deploy/twind-recorder.service's command behind the ACL router, with the "recorder"
    user's credentials: the twin's blocks reach the file."""
    dictionary = f"transport/auth/usrpwd/dictionary_file:{json.dumps(str(CREDENTIALS))}"
    out = tmp_path / "acl.mcap"
    with router(DEPLOY / "acl" / "router.json5", free_port(), dictionary) as endpoint, \
            serving("--mode", "client", "--connect", endpoint,
                    "--zenoh-config", str(DEPLOY / "acl" / "twin-client.json5")) as proc:
        wait_until_answering(endpoint, str(DEPLOY / "acl" / "operator.json5"), proc)
        recorded = subprocess.run(
            [sys.executable, "-m", "twind", "record", "-o", str(out), "--mode", "client",
             "--connect", endpoint, "--zenoh-config", str(DEPLOY / "acl" / "recorder.json5"),
             "--duration", "3"], capture_output=True, text=True, timeout=60)
    assert recorded.returncode == 0, recorded.stderr[-2000:]
    session = read_session(out)
    assert CHANNEL in session.channels and session.config["status"]["optics"] == ["ETMX"]


def test_serve_record_logs_its_recorder_in_behind_the_acl_router(tmp_path: Path) -> None:
    """``serve --record`` behind the ACL router: the twin logs in as "twin", its recorder as
    "recorder" (--record-zenoh-config), and the session reaches the files."""
    dictionary = f"transport/auth/usrpwd/dictionary_file:{json.dumps(str(CREDENTIALS))}"
    with router(DEPLOY / "acl" / "router.json5", free_port(), dictionary) as endpoint, \
            serving("--mode", "client", "--connect", endpoint,
                    "--zenoh-config", str(DEPLOY / "acl" / "twin-client.json5"),
                    "--record", str(tmp_path),
                    "--record-zenoh-config", str(DEPLOY / "acl" / "recorder.json5")) as proc:
        wait_until_answering(endpoint, str(DEPLOY / "acl" / "operator.json5"), proc)
        watcher = Watcher(endpoint, str(DEPLOY / "acl" / "viewer.json5"))
        try:
            watcher.wait_for_data()
            recorded(tmp_path)
        finally:
            watcher.close()
    session = read_session(sorted(tmp_path.glob("*.mcap")))
    assert CHANNEL in session.channels and len(session[CHANNEL].sequences) > 0


@pytest.mark.slow
def test_serve_record_over_tls_with_the_recorders_certificate(tmp_path: Path) -> None:
    """tls/: ``serve --record`` on a TLS-only twin, its recorder logged in with the
    "recorder" client certificate (--record-zenoh-config): the session reaches the files."""
    make = next((m for m, available in MAKERS.values() if available), None)
    if make is None:
        pytest.skip("neither cryptography nor openssl is installed")
    pki = tmp_path / "pki"
    pki.mkdir()
    make(pki, ("operator", "recorder"))
    endpoint = f"tls/localhost:{free_port()}"
    twin = tls_twin(pki, tmp_path)

    def client(cn: str) -> str:
        return tls_client(pki, cn, tmp_path)

    recordings = tmp_path / "recordings"
    with serving("--zenoh-config", twin, "--listen", endpoint, "--record", str(recordings),
                 "--record-zenoh-config", client("recorder")) as proc:
        wait_until_answering(endpoint, client("operator"), proc)
        recorded(recordings)
    session = read_session(sorted(recordings.glob("*.mcap")))
    assert CHANNEL in session.channels and len(session[CHANNEL].sequences) > 0
