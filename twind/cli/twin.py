"""``twind serve`` and the commands that talk to a running twin: ``inject``, ``stop``,
``status``."""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import fields

import numpy as np

from twind import strictjson
from twind.bus.session import DEFAULT_ENDPOINT, zenoh_config
from twind.client import TwinClient
from twind.errors import TwindError
from twind.excitation.request import ExcitationRequest
from twind.protocol import StatusReply


def _endpoints(args: argparse.Namespace) -> tuple[list[str], list[str]]:
    # a Zenoh configuration file brings its own endpoints
    default = [] if args.connect or getattr(args, "zenoh_config", None) else [DEFAULT_ENDPOINT]
    return args.listen or default, args.connect or []


def cmd_serve(args: argparse.Namespace) -> int:
    """The twin as a Zenoh service."""
    # OpenMP threads that spin between blocks cost a whole core while serving in real time;
    # set before the engine loads its compiled kernel (the runtime reads it once)
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    # here, not at the top: the configuration (scipy.signal, python-control) takes a second
    # to import, which inject, stop and status, the commands a person waits on, do without
    from twind.config import load_config
    from twind.service.serve import main as serve_main  # after the environment: see there

    twin = load_config(args.config, args.optics)
    optics = twin.select(args.optics)
    listen, connect = _endpoints(args)
    conf = zenoh_config(listen, connect, mode=args.mode, config_file=args.zenoh_config)
    return serve_main(conf, twin, optics, block_s=args.block, speed=args.speed, seed=args.seed,
                      duration=args.duration, record_dir=args.record, endpoints=listen + connect,
                      record_config=args.record_zenoh_config)


def client(args: argparse.Namespace, channel: str = "") -> TwinClient:
    """A client of the twin the command's bus arguments name; its interferometer is
    ``--ifo``, else `channel`'s prefix (``K1`` of ``K1:VIS-SRM_TM_TEST_P_EXC``), else C1;
    with ``--wait``, once the twin answers."""
    ifo = args.ifo or (channel.partition(":")[0] if ":" in channel else "C1")
    connect = args.connect or [DEFAULT_ENDPOINT]
    if not args.wait:
        return TwinClient(connect=connect, ifo=ifo, timeout=args.timeout,
                          config_file=args.zenoh_config)
    twin = TwinClient.wait(connect, timeout=args.wait, ifo=ifo, config_file=args.zenoh_config)
    twin.timeout = args.timeout
    return twin


def cmd_inject(args: argparse.Namespace) -> int:
    """Start an excitation on a running twin; prints its id, or the reason it was refused."""
    settings = {f.name: getattr(args, f.name) for f in fields(ExcitationRequest)
                if f.name not in ("channel", "waveform") and getattr(args, f.name, None)
                is not None}  # the options are named as the request's fields
    if args.file:
        try:
            settings["samples"] = np.loadtxt(args.file, ndmin=1)
        except ValueError as err:
            msg = f"{args.file}: not a column of numbers ({err})"
            raise TwindError(msg) from None
    with client(args, args.channel) as twin:
        exc_id = twin.inject(args.channel, args.waveform, **settings)
    print(exc_id)
    print(f"twind inject: {args.channel} started by twin {twin.last_reply['twin']}",
          file=sys.stderr)
    return 0


def cmd_stop(args: argparse.Namespace) -> int:
    """Stop an excitation by id (or all)."""
    with client(args) as twin:
        stopped = twin.stop(None if args.id == "all" else args.id)
    print(" ".join(stopped) if stopped else "no excitation was running")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    """Print the status of every twin that answers."""
    with client(args) as twin:
        replies = twin.replies("status")
    if args.json:
        print(strictjson.dumps(replies[0] if len(replies) == 1 else {"twins": replies}))
        return 0
    if len(replies) > 1:
        print(f"{len(replies)} twins answer:")
    for reply in replies:
        try:
            status = StatusReply.from_json(reply)
        except (KeyError, TypeError, ValueError) as err:
            print(f"twin {reply['twin']}: a status twind cannot read ({err!r} missing or "
                  "not as twind writes it)")
            continue
        print_status(status)
    return 0


def print_status(status: StatusReply) -> None:
    """One twin's status as ``twind status`` prints it."""
    print(f"{status.ifo} twin of {', '.join(status.optics)} ({status.twin}): GPS "
          f"{status.gps:.3f}, up {status.uptime_s:.1f} s, "
          f"{status.real_time_factor:.3f} x real time (speed {status.speed:g}), lag "
          f"{1e3 * status.lag_s:.1f} ms (max {1e3 * status.max_lag_s:.1f}), "
          f"{status.late_blocks} late blocks, busy {100 * status.cpu_fraction:.1f} %")
    tripped = [o for o, w in status.watchdogs.items() if w != "armed"]
    if tripped:
        print(f"  watchdog TRIPPED: {', '.join(tripped)} (outputs zeroed until re-armed)")
    rec = status.recorder
    if rec:
        again = f", restarted {rec['restarts']} time(s)" if rec["restarts"] else ""
        print(f"  recorder: {'recording' if rec['recording'] else 'NOT RECORDING'} to "
              f"{rec['folder']}{again}")
    for exc in status.excitations:
        when = "waits for" if exc.scheduled else "since"
        print(f"  {exc.id}: {exc.waveform} on {exc.channel}, {when} GPS {exc.start_gps:.3f}")
