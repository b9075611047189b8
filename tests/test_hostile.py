"""The service against hostile and careless clients, in process: every control request is
answered with an id or a reason, and the loop goes on computing finite blocks."""

from __future__ import annotations

import io
import json
import math
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, redirect_stdout
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from servicekit import free_port, serving

from twind import DOFS
from twind.bus.keys import control_key
from twind.bus.session import zenoh_config
from twind.cli import main
from twind.cli.twin import print_status
from twind.client import InjectionRefused, SeveralTwins, TwinClient, TwinUnreachable
from twind.config import DEFAULT_CONFIG, ConfigError, TwinConfig, load_config
from twind.excitation import WAVEFORMS
from twind.limits import ServiceLimits
from twind.protocol import (
    LIVE_PARAMS,
    EffectChange,
    FilterRequest,
    ParamsReply,
    ParamsRequest,
    StatusReply,
    StopRequest,
)
from twind.service.serve import limit_zenoh
from twind.service.twin import TwinService

EXC = [f"C1:SUS-ETMX_SUS{d}_EXC" for d in DOFS]


@pytest.fixture(scope="module")
def service() -> Iterator[TwinService]:
    """One twin for the tests that leave it as they found it."""
    with _serving() as svc:
        yield svc


@pytest.fixture
def fresh() -> Iterator[TwinService]:
    """A twin of its own, for a test that counts what runs on it."""
    with _serving() as svc:
        yield svc


@contextmanager
def _serving(twin: TwinConfig | None = None) -> Iterator[TwinService]:
    twin = twin or load_config(None, ["ETMX"])
    with zenoh.open(zenoh_config()) as session:
        svc = TwinService(session, twin, list(twin.optics.values()))
        yield svc
        svc.close()


def _step_is_finite(svc: TwinService) -> None:
    svc.step()
    assert all(np.all(np.isfinite(v)) for v in vars(svc._buf).values()
               if isinstance(v, np.ndarray)), "a block holds NaN or inf"


def _ask(svc: TwinService, verb: str, request: object) -> dict:
    reply = svc.handle(verb, json.dumps(request).encode())
    assert isinstance(reply, dict) and isinstance(reply.get("ok"), bool)
    if not reply["ok"]:
        assert isinstance(reply["reason"], str) and reply["reason"]
    elif verb == "inject":
        assert reply["accepted"] and reply["id"].startswith("exc-")
    return reply


def test_a_ramp_too_long_to_stop_is_refused_and_a_stop_never_stalls_the_loop(
        service: TwinService) -> None:
    """An infinite excitation whose ramp no int64 holds was accepted, and stopping it
    raised in the pacing thread and killed the service."""
    for ramp in (1e300, 6e14):
        reply = _ask(service, "inject", {"channel": EXC[0], "waveform": "sine", "amp": 1.0,
                                         "freq": 3.0, "duration": "inf", "ramp": ramp})
        assert not reply["ok"] and reply["reason"].startswith("ramp:")
    reply = _ask(service, "inject", {"channel": EXC[0], "waveform": "sine", "amp": 1.0,
                                     "freq": 3.0, "duration": "inf", "ramp": 5e11})
    assert reply["ok"]
    _step_is_finite(service)
    assert _ask(service, "stop", {"id": reply["id"]})["stopped"] == [reply["id"]]
    for _ in range(3):
        _step_is_finite(service)
    _ask(service, "stop", {"all": True})


@pytest.mark.parametrize(("gain", "words"), [(-30.0, "unstable"), (1e300, "unstable"),
                                             (math.nan, "finite"), ("1", "finite")])
def test_a_gain_that_would_ring_up_or_poison_the_optic_is_refused(
        service: TwinService, gain: object, words: str) -> None:
    before = _ask(service, "params", {"optic": "ETMX"})["filters"]["POS"]["gain"]
    reply = _ask(service, "filter", {"optic": "ETMX", "dof": "POS", "gain": gain, "ramp": 0})
    assert not reply["ok"] and words in reply["reason"]
    assert _ask(service, "params", {"optic": "ETMX"})["filters"]["POS"]["gain"] == before
    _step_is_finite(service)


def test_a_stage_switch_is_checked_like_a_gain(service: TwinService) -> None:
    for bad, words in (({"fm": 11}, "fm must be"), ({"fm": True}, "fm must be"),
                       ({"fm": 1, "on": "yes"}, "on must be"), ({"dof": "ROLL", "fm": 1},
                                                               "dof must be"),
                       ({"fm": 9}, "holds no filter"), ({"gains": 1.0}, "unknown field")):
        reply = _ask(service, "filter", {"optic": "ETMX", "dof": "POS", **bad})
        assert not reply["ok"] and words in reply["reason"], (bad, reply["reason"])


def test_an_excitation_that_fails_while_running_ends_alone(service: TwinService) -> None:
    """A waveform that raises in the pacing thread is stopped, with an event; the loop and
    the other excitations go on."""
    keep = _ask(service, "inject", {"channel": EXC[1], "waveform": "sine", "amp": 0.5,
                                    "freq": 2.0, "duration": "inf"})["id"]
    bad = _ask(service, "inject", {"channel": EXC[2], "waveform": "sine", "amp": 0.5,
                                   "freq": 2.0, "duration": "inf"})["id"]

    def broken(n: int) -> np.ndarray:
        raise OverflowError("a waveform's fault")

    service._active[bad].waveform.next = broken
    _step_is_finite(service)
    running = {e["id"] for e in _ask(service, "status", {})["excitations"]}
    assert keep in running and bad not in running
    assert _ask(service, "stop", {"id": bad})["already_ended"] == [bad]
    _ask(service, "stop", {"all": True})


_NUMBER = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(),
                    st.floats(min_value=-1e3, max_value=1e3), st.just(1e300), st.booleans(),
                    st.none(), st.text(max_size=8))
_ANY = st.recursive(_NUMBER, lambda inner: st.lists(inner, max_size=3)
                    | st.dictionaries(st.text(max_size=6), inner, max_size=3), max_leaves=6)


def _optional(keys: dict[str, st.SearchStrategy], required: tuple[str, ...] = ()
              ) -> st.SearchStrategy[dict]:
    """Requests with any of `keys` or an unknown one, and twice as often with the
    `required` ones."""
    shaped = st.fixed_dictionaries({k: keys[k] for k in required}, optional={
        k: v for k, v in keys.items() if k not in required})
    return st.one_of(shaped, shaped, st.fixed_dictionaries({}, optional={**keys,
                                                                         "colour": _ANY}))


_REQUESTS = st.one_of(
    st.tuples(st.just("inject"), _optional({
        "channel": st.sampled_from([*EXC, "C1:SUS-ETMY_SUSPOS_EXC", "garbage"]),
        "waveform": st.sampled_from([*WAVEFORMS, "square"]),
        "amp": st.one_of(_NUMBER, st.floats(0, 10)),
        "freq": st.one_of(_NUMBER, st.floats(0.01, 100)), "f_stop": _NUMBER,
        "n_tones": _NUMBER, "freqs": st.lists(_NUMBER, max_size=4),
        "duration": st.one_of(_NUMBER, st.floats(0.01, 10), st.just("inf")),
        "ramp": st.one_of(_NUMBER, st.floats(0, 1e16)), "start_gps": _NUMBER,
        "samples": st.lists(_NUMBER, max_size=5),
        "seed": _NUMBER, "shape": st.one_of(st.text(max_size=12), st.just("zpk([1],[10],1)")),
        }, required=("channel", "waveform", "amp", "freq"))),
    st.tuples(st.just("inject"), st.fixed_dictionaries(  # mostly accepted, ended by later ones
        {"channel": st.sampled_from(EXC), "waveform": st.sampled_from(["sine", "noise"]),
         "amp": st.floats(0, 5), "freq": st.floats(0.05, 100)},
        optional={"duration": st.one_of(st.floats(0.01, 10), st.just("inf"), _NUMBER),
                  "ramp": st.one_of(st.floats(0, 5), st.sampled_from([1e12, 6e14, 1e300]),
                                    _NUMBER), "start_gps": _NUMBER})),
    st.tuples(st.just("stop"), _optional({"id": st.one_of(_ANY, st.just("exc-1")),
                                          "all": st.one_of(st.just(True), _ANY)})),
    st.tuples(st.just("params"), _optional({
        "optic": st.one_of(st.just("ETMX"), _ANY),
        "set": st.one_of(st.dictionaries(st.sampled_from(sorted(LIVE_PARAMS)), _NUMBER,
                                         max_size=2), _ANY),
        "effect": st.one_of(_ANY, st.fixed_dictionaries({"id": st.sampled_from(
            ["coil_imbalance", "loop_delay", "nonsense"]), "values": _ANY}))})),
    st.tuples(st.just("filter"), _optional({
        "optic": st.one_of(st.just("ETMX"), _ANY), "dof": st.sampled_from([*DOFS, "ROLL"]),
        "fm": st.one_of(_NUMBER, st.integers(1, 10)), "on": st.one_of(st.booleans(), _ANY),
        "gain": st.one_of(_NUMBER, st.floats(-2, 2)), "ramp": st.one_of(_NUMBER, st.just(0))},
        required=("dof",))),
    st.tuples(st.just("status"), _ANY),
)


@pytest.fixture(scope="module")
def unhurried() -> Iterator[TwinService]:
    """A twin that takes any number of changes a minute, so that the fuzz reaches them."""
    nominal = load_config(None, ["ETMX"])
    with _serving(replace(nominal, service=replace(nominal.service,
                                                   changes_per_minute=10**9))) as svc:
        yield svc


@settings(max_examples=600, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(requests=st.lists(_REQUESTS, min_size=1, max_size=8))
@pytest.mark.slow
def test_every_generated_request_is_answered_and_the_loop_goes_on(
        unhurried: TwinService, requests: list) -> None:
    """Thousands of generated requests over the schemas of inject, stop, params and filter,
    valid and not: each gets an id or a reason, and every block after them is finite."""
    for verb, request in requests:
        _ask(unhurried, verb, request)
        _step_is_finite(unhurried)
    _ask(unhurried, "stop", {"all": True})
    _step_is_finite(unhurried)


def test_changes_beyond_the_configured_rate_are_refused() -> None:
    nominal = load_config(None, ["ETMX"])
    with _serving(replace(nominal, service=replace(nominal.service,
                                                   changes_per_minute=3))) as svc:
        for gain in (0.9, 1.0, 0.95):
            assert _ask(svc, "filter", {"dof": "POS", "gain": gain, "ramp": 0})["ok"]
        reply = _ask(svc, "params", {"optic": "ETMX", "set": {"wire_length_m": 0.25}})
        assert not reply["ok"] and "service.changes_per_minute" in reply["reason"]
        assert _ask(svc, "params", {"optic": "ETMX"})["ok"]  # reading is no change


def test_excitations_are_counted_scheduled_ones_listed_and_stopped_at_once(
        fresh: TwinService) -> None:
    """A test point takes ``service.excitations_per_channel`` excitations, running or
    waiting; one scheduled beyond ``schedule_ahead_s`` is refused; ``status`` lists the
    waiting ones and ``stop all`` removes them at once, freeing their budget."""
    limits = fresh.accepts
    gps = _ask(fresh, "status", {})["gps"]
    later = {"channel": EXC[3], "waveform": "sine", "amp": 1e-6, "freq": 1.0, "duration": 1.0,
             "start_gps": gps + 3600}
    ids = [_ask(fresh, "inject", later)["id"] for _ in range(limits.excitations_per_channel)]
    reply = _ask(fresh, "inject", later)
    assert not reply["ok"] and "service.excitations_per_channel" in reply["reason"]
    far = _ask(fresh, "inject", {**later, "channel": EXC[0],
                                 "start_gps": gps + limits.schedule_ahead_s + 10})
    assert not far["ok"] and "service.schedule_ahead_s" in far["reason"]
    waiting = [e for e in _ask(fresh, "status", {})["excitations"] if e["scheduled"]]
    assert sorted(e["id"] for e in waiting) == sorted(ids)
    assert sorted(_ask(fresh, "stop", {"all": True})["stopped"]) == sorted(ids)
    assert _ask(fresh, "status", {})["excitations"] == []
    assert _ask(fresh, "inject", later)["ok"]
    _ask(fresh, "stop", {"all": True})


def test_a_request_beyond_the_payload_limit_is_refused_over_the_bus() -> None:
    nominal = load_config(None, ["ETMX"])
    with _serving(replace(nominal, service=replace(nominal.service, request_bytes=1000))) as svc:
        big = json.dumps({"channel": EXC[0], "waveform": "stream", "samples": [0.0] * 500})
        replies = list(svc._session.get(control_key("C1", "inject"), payload=big, timeout=5.0))
        reply = json.loads(replies[0].ok.payload.to_bytes())
        assert not reply["ok"] and f"request of {len(big)} bytes" in reply["reason"]
        assert "service.request_bytes" in reply["reason"]
        assert _ask(svc, "status", {})["excitations"] == []


def test_zenoh_drops_a_message_far_beyond_the_payload_limit_before_the_twin_sees_it() -> None:
    """serve's session limits Zenoh's messages to twice ``service.request_bytes`` (a file's
    own limit is kept): a larger query never reaches the queryable, later ones still do."""
    kept = zenoh.Config()
    kept.insert_json5("transport/link/rx/max_message_size", "5000000")
    limit_zenoh(kept, ServiceLimits(request_bytes=1000))
    assert json.loads(kept.get_json("transport/link/rx/max_message_size")) == 5000000
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh_config(listen=[endpoint])
    limit_zenoh(conf, ServiceLimits(request_bytes=1000))
    sizes: list[int] = []
    with zenoh.open(conf) as twin, \
            zenoh.open(zenoh_config(connect=[endpoint], mode="client")) as client:
        twin.declare_queryable("twin/q", lambda q: (sizes.append(len(q.payload)),
                                                     q.reply(q.key_expr, b"ok")))
        time.sleep(0.3)
        for size in (100, 100_000, 100):
            list(client.get("twin/q", payload=b"x" * size, timeout=1.0))
    assert sizes == [100, 100]


DEPLOY = Path(__file__).resolve().parent.parent / "deploy"


def test_no_session_of_twind_and_no_shipped_router_passes_blocks_through_shared_memory(
        tmp_path: Path) -> None:
    """Zenoh's shared memory hands a subscriber that was descheduled buffers already reused
    (blocks undecodable or of another channel): twind's sessions turn it off even when a
    configuration file turns it on, and the shipped routers have it off and let a client
    that reads nothing go after the twin's ``service.subscriber_wait_s``."""
    on = tmp_path / "shm.json5"
    on.write_text("{transport: {shared_memory: {enabled: true}}}")
    for conf in (zenoh_config(), zenoh_config(config_file=str(on), mode="client")):
        assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False
    wait = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    for router in (DEPLOY / "zenoh-router.json5", DEPLOY / "acl" / "router.json5"):
        conf = zenoh.Config.from_file(str(router))
        assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False, router
        assert json.loads(conf.get_json(wait)) == 1e6 * ServiceLimits().subscriber_wait_s


SUBSCRIBER = """
import json, sys, time, zenoh
from twind.bus.codec import SampleBlock
conf = zenoh.Config()  # Zenoh's defaults (shared memory on), as a commissioner's script has
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
last, report = {}, {"blocks": 0, "damaged": [], "gaps": 0}
def on(sample):
    key = str(sample.key_expr)
    try:
        block = SampleBlock.decode(sample.payload.to_bytes())
    except Exception as err:
        report["damaged"].append(f"{key}: {type(err).__name__}")
        return
    before = last.get(key, -1)
    if not key.endswith(block.channel) or block.sequence <= before:
        report["damaged"].append(f"{key}: block {block.sequence} of {block.channel} after {before}")
    report["gaps"] += before >= 0 and block.sequence > before + 1
    report["blocks"] += 1
    last[key] = block.sequence
with zenoh.open(conf) as s, s.declare_subscriber("twin/**", on):
    print("ready", flush=True)
    sys.stdin.readline()
report["last"] = max(last.values(), default=-1)
print(json.dumps(report), flush=True)
"""


@pytest.mark.slow
def test_a_suspended_subscriber_holds_the_twin_briefly_and_no_one_gets_a_damaged_block() -> None:
    """Two subscribers with Zenoh's defaults; one is descheduled 16 times for 0.1-0.4 s
    (through Zenoh's shared memory, such pauses damage blocks), then suspended for
    6 s (SIGSTOP, as Ctrl-Z): the twin waits for it at most ``service.subscriber_wait_s``
    (0.5 s; Zenoh alone waits 5 s), then closes its session and goes on. The other gets
    every block in sequence; the suspended one, resumed, reconnects and gets intact blocks
    again."""
    pauses = np.random.default_rng(18).uniform(0.1, 0.4, 16)
    with serving("--optics", "all") as endpoint:
        readers = [subprocess.Popen([sys.executable, "-c", SUBSCRIBER, endpoint], text=True,
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE)
                   for _ in range(2)]
        assert [r.stdout.readline().strip() for r in readers] == ["ready", "ready"]
        time.sleep(1.0)
        for pause in [*pauses, 6.0]:
            readers[1].send_signal(signal.SIGSTOP)
            time.sleep(pause)
            readers[1].send_signal(signal.SIGCONT)
            time.sleep(0.4)
        time.sleep(4.0)
        with TwinClient([endpoint]) as client:
            status = client.status()
        steady, resumed = (json.loads(r.communicate("\n", timeout=30)[0]) for r in readers)
    assert status.max_lag_s < 2.5, f"the twin waited {status.max_lag_s:.2f} s for a reader"
    assert steady["damaged"] == [] and steady["gaps"] == 0
    assert resumed["damaged"] == [] and resumed["gaps"] > 0  # its session was closed
    assert resumed["last"] >= status.blocks - 32  # and it reads again


def test_the_twin_s_replies_are_what_the_client_reads(fresh: TwinService) -> None:
    """status and params replies, an excitation and an effect running, read as typed
    replies and written back field for field: nothing the twin says is dropped or renamed;
    the requests the client sends read back as themselves."""
    sine = {"channel": EXC[0], "waveform": "sine", "amp": 0.1, "freq": 1.0, "duration": 5.0}
    assert _ask(fresh, "inject", sine)["accepted"]
    effect = {"id": "coil_imbalance", "values": {"gain_UL": 0.01}}
    assert _ask(fresh, "params", {"optic": "ETMX", "effect": effect})["ok"]
    status = fresh.status()
    assert StatusReply.from_json(status).to_json() == status and status["excitations"]
    params = {**_ask(fresh, "filter", {"dof": "PIT", "fm": 3, "on": False}), "twin": "t"}
    read = ParamsReply.from_json(params)
    assert read.to_json() == params and read.effect == EffectChange(**effect)
    for request in (StopRequest(all=True, ramp=2.0), ParamsRequest("ETMX", {"Q_POS": 4.0},
                    EffectChange(**effect), rearm=True), FilterRequest("PIT", "ETMX", 3, False),
                    FilterRequest("POS", gain=0.5, ramp=1.0)):
        assert type(request).from_json(request.to_json()) == request


def test_status_reports_the_latency_of_injections_made_now_only(fresh: TwinService) -> None:
    """Request to the block with its first sample published, per injection asked for "now";
    one scheduled ahead (or stopped before it ran) is not a latency."""
    gps = _ask(fresh, "status", {})["gps"]
    sine = {"channel": EXC[0], "waveform": "sine", "amp": 0.1, "freq": 1.0, "duration": 0.5}
    later = _ask(fresh, "inject", {**sine, "channel": EXC[1], "start_gps": gps + 0.1})["id"]
    gone = _ask(fresh, "inject", {**sine, "channel": EXC[2], "start_gps": gps + 0.1})["id"]
    _ask(fresh, "stop", {"id": gone})
    before = time.monotonic()
    _ask(fresh, "inject", sine)
    assert _ask(fresh, "status", {})["injection_latency_s"]["n"] == 0  # not yet published
    for _ in range(4):
        fresh.step()
    waited = time.monotonic() - before
    latency = _ask(fresh, "status", {})["injection_latency_s"]
    assert latency["n"] == 1 and 0 < latency["max"] <= waited
    assert later in [e["id"] for e in _ask(fresh, "status", {})["excitations"]]


def test_the_service_limits_are_read_from_the_configuration(tmp_path) -> None:  # noqa: ANN001
    src = DEFAULT_CONFIG.read_text()
    (tmp_path / "optics").symlink_to(DEFAULT_CONFIG.parent / "optics")
    path = tmp_path / "c1.toml"
    path.write_text(src.replace("excitations_per_channel = 16", "excitations_per_channel = 2"))
    assert load_config(path, ["ETMX"]).service.excitations_per_channel == 2
    path.write_text(src.replace("excitations = 64", "excitations = 0.5"))
    with pytest.raises(ConfigError, match="service.excitations: expected a whole number"):
        load_config(path, ["ETMX"])


def test_the_watchdog_trips_on_an_osem_out_of_range_and_is_rearmed() -> None:
    """With the watchdog at 0.5 um, a 5 um drive at POS trips it: the damping outputs are
    zero from the next block on, ``status`` says so, an event says why, a gain change
    waits, and ``params`` re-arms it."""
    nominal = load_config(None, ["ETMX"])
    with _serving(replace(nominal, service=replace(nominal.service, watchdog_um=0.5))) as svc:
        _trip_and_rearm(svc)


def _event(events: list[dict], name: str, timeout_s: float = 10.0) -> dict:
    """The first event `name` published (Zenoh delivers on its own threads)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = [e for e in events if e["event"] == name]
        if found:
            return found[0]
        time.sleep(0.01)
    raise AssertionError(f"no {name!r} event in {timeout_s} s; got {events}")


def _trip_and_rearm(svc: TwinService) -> None:
    events: list[dict] = []
    svc._session.declare_subscriber(control_key("C1", "events"), lambda sample: events.append(
        json.loads(sample.payload.to_bytes())))
    _ask(svc, "inject", {"channel": EXC[0], "waveform": "sine", "amp": 5.0, "freq": 1.0,
                         "duration": 2.0})
    for _ in range(16):
        _step_is_finite(svc)
    assert _ask(svc, "status", {})["watchdogs"] == {"ETMX": "tripped"}
    out = io.StringIO()
    with redirect_stdout(out):  # what twind status prints of it
        print_status(StatusReply.from_json(svc.status()))
    assert "watchdog TRIPPED: ETMX" in out.getvalue()
    tripped = _event(events, "tripped")
    assert "service.watchdog_um" in tripped["reason"] and tripped["optic"] == "ETMX"
    _step_is_finite(svc)
    assert not np.any(svc._buf.out)
    assert _ask(svc, "filter", {"dof": "POS", "gain": 0.5, "ramp": 0})["ok"]
    _step_is_finite(svc)
    assert not np.any(svc._buf.out)
    _ask(svc, "stop", {"all": True})
    assert _ask(svc, "params", {"optic": "ETMX", "watchdog": "rearm"})["watchdog"] == "armed"
    assert _event(events, "rearmed")["optic"] == "ETMX"
    assert sum(e["event"] == "tripped" for e in events) == 1
    _step_is_finite(svc)
    assert np.any(svc._buf.out)
    assert _ask(svc, "params", {"optic": "ETMX"})["filters"]["POS"]["gain"] == 0.5
    bad = _ask(svc, "params", {"optic": "ETMX", "watchdog": "off"})
    assert not bad["ok"] and "rearm" in bad["reason"]


# -- a client cannot be fooled by what is not a twin, nor by two twins ------------------
@contextmanager
def _bus() -> Iterator[tuple[str, zenoh.Session]]:
    """A session listening on a port of its own, and its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config(listen=[endpoint])) as session:
        yield endpoint, session


def _impostor(session: zenoh.Session, verb: str, answer: bytes | None) -> zenoh.Queryable:
    """A process answering on a twin's key what it likes (an error when `answer` is None)."""
    def reply(query: zenoh.Query) -> None:
        if answer is None:
            query.reply_err(b"impostor says no")
        else:
            query.reply(query.key_expr, answer)
    return session.declare_queryable(control_key("C1", verb), reply)


def test_a_client_keeps_only_the_twins_replies() -> None:
    """An impostor answering inject "ok", an error or bytes that are not UTF-8 beside a twin
    that refuses: the client reports the twin's refusal; alone, the impostor is no twin."""
    twin = load_config(None, ["ETMX"])
    with _bus() as (endpoint, session):
        svc = TwinService(session, twin, list(twin.optics.values()))
        fakes = [_impostor(session, "inject", b'{"ok": true, "accepted": true, "id": "x"}'),
                 _impostor(session, "inject", None), _impostor(session, "inject", b"\xff\xfe"),
                 _impostor(session, "status", b'{"ok": true}')]
        try:
            with TwinClient([endpoint]) as client:
                time.sleep(0.3)
                with pytest.raises(InjectionRefused, match="5000"):
                    client.inject(EXC[0], "sine", freq=3.0, amp=5000.0, duration=1.0)
                assert client.last_reply["twin"] == svc.twin_id
                (status,) = client.replies("status")
                assert status["twin"] == svc.twin_id and "gps" in status
        finally:
            svc.close()
        with TwinClient([endpoint], timeout=1.0) as client:
            with pytest.raises(TwinUnreachable, match="no twin answered.*3 other answer"):
                client.inject(EXC[0], "sine", freq=3.0, amp=0.1, duration=1.0)
        for fake in fakes:
            fake.undeclare()


def test_two_twins_serving_one_optic_are_named_not_merged(capsys) -> None:  # noqa: ANN001
    """Two twins of ETMX on one bus: an injection both start is an error naming both twins
    and both ids; stop all stops it on both; status lists both."""
    twin = load_config(None, ["ETMX"])
    with _bus() as (endpoint, first), \
            zenoh.open(zenoh_config(connect=[endpoint])) as second:
        services = [TwinService(s, twin, list(twin.optics.values())) for s in (first, second)]
        try:
            with TwinClient([endpoint]) as client:
                time.sleep(0.3)
                with pytest.raises(SeveralTwins, match="2 twins did this inject") as info:
                    client.inject(EXC[0], "sine", freq=3.0, amp=0.1, duration=100.0)
                both = {r["twin"] for r in info.value.replies}
                assert both == {s.twin_id for s in services}
                ids = {r["id"] for r in info.value.replies}
                assert set(client.stop()) == ids
                assert all(not r["excitations"] for r in client.replies("status"))
            assert main(["status", "--connect", endpoint]) == 0
            out = capsys.readouterr().out
            assert out.startswith("2 twins answer:")
            assert all(s.twin_id in out for s in services)
        finally:
            for s in services:
                s.close()


def test_a_wildcard_runs_no_verb_a_refusal_echoes_little_and_zero_amplitude_is_refused(
        fresh: TwinService) -> None:
    """``twin/@/**`` used to run every verb (a stop among them); a 200 kB shape came back in
    the reason and went into every recording; 64 excitations of amplitude 0 filled the slots."""
    running = _ask(fresh, "inject", {"channel": EXC[0], "waveform": "sine", "amp": 0.1,
                                     "freq": 3.0, "duration": 100.0})["id"]
    replies = list(fresh._session.get("twin/@/**", payload=json.dumps({"all": True}),
                                      timeout=2.0))
    assert replies and all(r.ok is None for r in replies)
    assert "on its own key" in replies[0].err.payload.to_string()
    assert [e["id"] for e in _ask(fresh, "status", {})["excitations"]] == [running]
    events: list[dict] = []
    sub = fresh._session.declare_subscriber(
        control_key("C1", "events"), lambda s: events.append(json.loads(s.payload.to_bytes())))
    huge = _ask(fresh, "inject", {"channel": EXC[1], "waveform": "noise", "amp": 0.1,
                                  "duration": 1.0, "shape": "gain(" * 50_000})
    zero = _ask(fresh, "inject", {"channel": EXC[1], "waveform": "sine", "amp": 0.0,
                                  "freq": 1.0, "duration": 1.0})
    time.sleep(0.3)
    sub.undeclare()
    assert not huge["ok"] and len(huge["reason"]) < 1000
    assert not zero["ok"] and "excites nothing" in zero["reason"]
    assert events and all(len(json.dumps(e)) < 2000 for e in events)
    _ask(fresh, "stop", {"all": True})


def test_a_misspelt_or_mistyped_field_is_refused_and_a_stop_is_taken_once(
        fresh: TwinService) -> None:
    """``{"sett": ...}`` answered ok and changed nothing; ``{"set": {"mass_kg": true}}`` stored
    True; a Q not of a DOF, or Q as a whole, is not a live parameter; ``stop`` with ``"ramp": 0`` ramped over the request's 30 s; a second stop of an
    excitation still ramping down published a second stop."""
    for request, words in (({"sett": {"mass_kg": 0.25}}, "unknown field(s): 'sett'"),
                           ({"set": {"mass_kg": True}}, "'set' takes numbers"),
                           ({"set": {"mass_kg": "heavy"}}, "'set' takes numbers"),
                           ({"set": {"Q.BOGUS": 5.0}}, "cannot change Q.BOGUS"),
                           ({"set": {"Q_BOGUS": 5.0}}, "cannot change Q_BOGUS"),
                           ({"set": {"Q": {"BOGUS": 5.0}}}, "cannot change Q live"),
                           ({"set": {"Q": 5.0}}, "cannot change Q live")):
        reply = _ask(fresh, "params", request)
        assert not reply["ok"] and words in reply["reason"], reply
    assert _ask(fresh, "params", {})["params"]["mass_kg"] != 0.25
    act = _ask(fresh, "inject", {"channel": EXC[0], "waveform": "sine", "amp": 0.1,
                                 "freq": 3.0, "duration": 100.0, "ramp": 30.0})["id"]
    for _ in range(2):
        fresh.step()
    assert not _ask(fresh, "stop", {"id": act, "rampp": 0})["ok"]
    assert _ask(fresh, "stop", {"id": act, "ramp": 0})["stopped"] == [act]
    assert _ask(fresh, "stop", {"id": act})["stopped"] == []  # stopping already: no second
    fresh.step()
    fresh.step()
    assert _ask(fresh, "status", {})["excitations"] == []  # gone at once, not in 30 s


def test_the_memory_excitations_hold_is_bounded() -> None:
    """64 multisines of a few hundred bytes each held a 2^22-sample period (2 GB in all):
    past ``service.waveform_bytes`` an excitation is refused with the reason."""
    nominal = load_config(None, ["ETMX"])
    small = replace(nominal, service=replace(nominal.service, waveform_bytes=10_000_000))
    with _serving(small) as svc:
        # its period: 2^20 samples, 8 MB
        tone = {"waveform": "multisine", "amp": 0.1, "freqs": [1.0, 1.0625],
                "duration": 100.0}
        assert _ask(svc, "inject", {"channel": EXC[0], **tone})["ok"]
        reply = _ask(svc, "inject", {"channel": EXC[1], **tone})
        assert not reply["ok"] and "service.waveform_bytes" in reply["reason"]
        _ask(svc, "stop", {"all": True})
