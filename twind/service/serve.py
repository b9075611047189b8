"""``twind serve``: run the twin on Zenoh until stopped (SIGINT/SIGTERM end it cleanly)."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh
from threadpoolctl import threadpool_limits

from twind.bus.keys import control_key
from twind.client import twin_reply
from twind.config import TwinConfig
from twind.errors import TwindError
from twind.limits import ServiceLimits
from twind.service.plant_twin import PlantTwinService
from twind.service.twin import TwinService
from twind.timeutil import now_gps


def main(conf: zenoh.Config, twin: TwinConfig, optics: list, *, block_s: float = 1 / 16,
         speed: float = 1.0, seed: int = 0, duration: float | None = None,
         record_dir: str | None = None, endpoints: Sequence[str] = (),
         record_config: str | None = None) -> int:
    """Serve `optics` on a session opened with `conf`.

    Parameters
    ----------
    conf : zenoh.Config
        Session configuration (embedded peer listening on loopback by default).
    twin, optics
        Configuration and the optics to run.
    block_s, speed, seed
        See :class:`TwinService`.
    duration : float, optional
        Stop after this many twin seconds (forever when None).
    record_dir : str, optional
        Record every block and event to MCAP files rotating hourly in this folder.
    endpoints : sequence of str
        Where the service can be reached (for the recorder's session and the log).
    record_config : str, optional
        The recorder's Zenoh configuration file (its credentials behind an ACL router).
    """
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if not (speed > 0 and block_s > 0):
        msg = f"--speed and --block must be positive, got {speed} and {block_s}"
        raise TwindError(msg)
    kinds = {o.kind for o in optics}
    if len(kinds) > 1:
        msg = "a twin serves SOSs or one state-space optic, not both: choose --optics"
        raise TwindError(msg)
    priority = _raise_priority()  # before any thread starts: they all inherit it
    limit_zenoh(conf, twin.service)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    # the checks of a params/filter change run LAPACK; OpenBLAS's threads, spinning on the
    # two cores beside the engine's, made each check 46 ms instead of 7 and the loop late
    threadpool_limits(limits=1, user_api="blas")
    recorder = None
    try:
        with zenoh.open(conf) as session:
            served = already_served(session, twin.ifo, [o.name for o in optics])
            if served:
                raise TwindError(served)
            # the recorder subscribes before the service answers anything, so that no block
            # and no injection event escapes the recording
            recorder = (Recording(record_dir, endpoints, twin.ifo, record_config)
                        if record_dir else None)
            kind = PlantTwinService if kinds == {"statespace"} else TwinService
            service = kind(session, twin, optics, block_s=block_s, speed=speed, seed=seed,
                           recorder_status=recorder.state if recorder else None)
            if recorder is not None:
                threading.Thread(target=recorder.watch, args=(stop,), daemon=True).start()
            print(f"twind serve: {', '.join(o.name for o in optics)} at {service.rate:g} Hz in "
                  f"{service.block_s:g} s blocks, {speed:g} x real time, GPS "
                  f"{service.gps0:.3f}, on {' '.join(endpoints) or 'the configured endpoints'}"
                  f", {priority}; ready for clients (twind status --wait S waits for this); "
                  "Ctrl-C stops", flush=True)
            reporter = threading.Thread(target=_report, args=(service, stop), daemon=True)
            reporter.start()
            try:
                service.run(duration=duration, stop=stop)
            finally:
                status = service.status()
                service.close()
    finally:
        if recorder is not None:
            recorder.stop()
    print(f"twind serve: stopped after {status['blocks']} blocks, {status['late_blocks']} late, "
          f"max lag {status['max_lag_s'] * 1e3:.1f} ms, busy {100 * status['cpu_fraction']:.1f} %",
          file=sys.stderr)
    return 0


def already_served(session: zenoh.Session, ifo: str, optics: Sequence[str],
                   timeout: float = 2.0) -> str:
    """Why a twin of `optics` must not start on this bus: another twin serves one of them
    ("" if none does). Two twins of one optic would both start every excitation of it.

    Parameters
    ----------
    session : zenoh.Session
        The new twin's session, open.
    ifo : str
        Its interferometer prefix.
    optics : sequence of str
        The optics it is to serve.
    timeout : float
        Seconds the twins on the bus have to answer their status.

    Returns
    -------
    str
    """
    for reply in session.get(control_key(ifo, "status"), timeout=timeout,
                             consolidation=zenoh.ConsolidationMode.NONE):
        status = twin_reply(reply)
        both = sorted(set(optics) & set(status.get("optics", []) if isinstance(status, dict)
                                        else []))
        if both:
            return (f"{', '.join(both)} already served on this bus by twin {status['twin']}; "
                    "two twins of one optic would both run its excitations: stop that twin, "
                    "or serve other optics (--optics)")
    return ""


SWITCH_INTERVAL_S = 0.001
"""How long a thread busy with a request (a stability check, a long stream's JSON) may keep
the interpreter from the pacing thread before it must hand it over (Python's default: 5 ms)."""

ZENOH_DEFAULTS = {"transport/link/rx/max_message_size": 1 << 30,
                  "transport/link/tx/queue/congestion_control/block/wait_before_close": 5_000_000}
"""Zenoh's own defaults of the settings :func:`limit_zenoh` bounds (bytes, microseconds)."""


def limit_zenoh(conf: zenoh.Config, service: ServiceLimits) -> None:
    """Bound what a client can cost the twin through Zenoh itself, where the configuration
    file left Zenoh's default:

    - a message beyond twice ``service.request_bytes`` is dropped before it is assembled,
      so a 500 MB request never reaches the twin's memory (its sender is not answered);
    - a subscriber that reads nothing for ``service.subscriber_wait_s`` has its session
      closed, instead of holding every block for Zenoh's 5 s.

    Parameters
    ----------
    conf : zenoh.Config
        The service's Zenoh configuration, changed in place.
    service : ServiceLimits
        The ``[service]`` table of the twin's configuration.
    """
    wanted = {"transport/link/rx/max_message_size": int(2 * service.request_bytes),
              "transport/link/tx/queue/congestion_control/block/wait_before_close":
                  int(1e6 * service.subscriber_wait_s)}
    for key, value in wanted.items():
        if json.loads(conf.get_json(key)) == ZENOH_DEFAULTS[key]:
            conf.insert_json5(key, str(value))


NICE = -10
"""The service's scheduling priority where the OS allows it: a twin paced to the wall clock
must not wait behind batch work on its cores."""


def _raise_priority() -> str:
    """Raise this thread's priority (and so that of every thread it starts) to :data:`NICE`;
    what was done, in words."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, min(NICE, os.getpriority(os.PRIO_PROCESS, 0)))
    except OSError:
        return "at normal priority (a raised one needs CAP_SYS_NICE)"
    return f"at nice {os.getpriority(os.PRIO_PROCESS, 0)}"


def _report(service: TwinService, stop: threading.Event, every: float = 10.0) -> None:
    """A status line every `every` seconds, so a terminal shows the twin is alive."""
    while not stop.wait(every):
        s = service.status()
        print(f"twind serve: GPS {s['gps']:.1f}, {s['blocks']} blocks, {s['real_time_factor']:.3f} "
              f"x real time, lag {1e3 * s['lag_s']:.1f} ms (max {1e3 * s['max_lag_s']:.1f}), "
              f"{s['late_blocks']} late, {len(s['excitations'])} excitation(s)", flush=True)


def _recorder(folder: str, endpoints: Sequence[str], ifo: str,
              zenoh_config_file: str | None = None) -> subprocess.Popen:
    """``twind record`` in a process of its own: it cannot slow the twin's pacing thread
    (Python threads share one interpreter lock) nor take the twin down if it fails."""

    Path(folder).mkdir(parents=True, exist_ok=True)
    out = Path(folder) / f"{ifo}-twin-{int(now_gps())}.mcap"
    for k in itertools.count(2):  # a recorder started again within the same second
        if not out.with_name(f"{out.stem}-0001.mcap").exists():
            break
        out = Path(folder) / f"{ifo}-twin-{int(now_gps())}r{k}.mcap"
    connect = [a for e in endpoints for a in ("--connect", e.replace("0.0.0.0", "127.0.0.1"))]
    proc = subprocess.Popen([sys.executable, "-m", "twind", "record", "-o", str(out),
                             "--mode", "client", "--rotate-s", "3600", "--ifo", ifo,
                             "--parent", str(os.getpid()), *connect,
                             *(["--zenoh-config", zenoh_config_file] if zenoh_config_file
                               else [])])
    first = out.with_name(f"{out.stem}-0001.mcap")
    deadline = time.monotonic() + 60
    while not first.exists():  # the recorder subscribes before it creates its first file
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            msg = f"the recorder for {folder} did not start"
            raise TwindError(msg)
        time.sleep(0.05)
    return proc


class Recording:
    """The recorder ``serve --record`` runs beside the twin, watched: one that ends while the
    twin serves (killed, its disk full) is said so on the terminal and in the twin's status,
    and started again in a file of its own, :data:`RESTARTS` times at most; one started again
    that ends within :data:`QUICK_S` (a full disk, a refused login) is not started again.

    Parameters
    ----------
    folder : str
        Where it records.
    endpoints : sequence of str
        Where the twin listens.
    ifo : str
        The interferometer prefix.
    zenoh_config_file : str, optional
        The recorder's own Zenoh configuration.
    """

    RESTARTS = 5
    QUICK_S = 10.0

    def __init__(self, folder: str, endpoints: Sequence[str], ifo: str,
                 zenoh_config_file: str | None = None) -> None:
        self.folder = folder
        self._args = (folder, endpoints, ifo, zenoh_config_file)
        self.proc: subprocess.Popen | None = _recorder(*self._args)
        self._started = time.monotonic()
        self.restarts = 0
        self.last_exit: int | None = None

    def watch(self, stop: threading.Event, every_s: float = 1.0) -> None:
        """Look at the recorder every `every_s` until `stop` is set."""
        while not stop.wait(every_s):
            proc = self.proc
            if proc is None or proc.poll() is None:
                continue
            self.last_exit, self.proc = proc.returncode, None
            if stop.is_set():
                return
            quick = self.restarts and time.monotonic() - self._started < self.QUICK_S
            why = ("it ended again at once (its error above)" if quick else
                   f"{self.RESTARTS} restarts" if self.restarts >= self.RESTARTS else "")
            print(f"twind serve: the recorder for {self.folder} ended (exit "
                  f"{proc.returncode}) at {time.strftime('%H:%M:%S')}; "
                  + (f"not started again, {why}: NOT RECORDING" if why else
                     "starting another: the recording has a gap"), file=sys.stderr, flush=True)
            if not why:
                self.restarts += 1
                try:
                    self.proc, self._started = _recorder(*self._args), time.monotonic()
                except TwindError as err:
                    print(f"twind serve: {err}: NOT RECORDING", file=sys.stderr, flush=True)

    def state(self) -> dict:
        """For the twin's status: the folder, whether it records, its restarts."""
        proc = self.proc
        return {"folder": self.folder, "recording": proc is not None and proc.poll() is None,
                "restarts": self.restarts, "last_exit": self.last_exit}

    def stop(self) -> None:
        """End the recording (its file complete)."""
        if self.proc is not None:
            _stop_recorder(self.proc)


def _stop_recorder(proc: subprocess.Popen) -> None:
    time.sleep(0.3)  # let the last blocks reach it
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
