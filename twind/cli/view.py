"""``twind view`` (live channels in a Rerun viewer) and ``twind rrd`` (MCAP session to .rrd).

Neither imports rerun until it runs, so building the command line stays fast.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

import rerun as rr

from twind.bus.session import DEFAULT_ENDPOINT
from twind.errors import TwindError
from twind.viz.live import stream
from twind.viz.rerun_export import mcap_to_rrd


def _viewer_executable() -> str | None:
    """The ``rerun`` viewer that rerun-sdk installs next to this Python, or one on PATH."""
    beside = Path(sys.executable).with_name("rerun")
    return str(beside) if beside.exists() else shutil.which("rerun")


def _can_open_window() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def cmd_view(args: argparse.Namespace) -> int:
    """Stream the live twin to a Rerun viewer (spawned, given by --viewer, --web or --save)."""

    if not (args.rate > 0):
        msg = f"--rate must be positive, got {args.rate}"
        raise TwindError(msg)
    rec = rr.RecordingStream("twind")
    if args.save:
        if Path(args.save).exists():
            msg = f"{args.save} exists; twind does not overwrite files"
            raise TwindError(msg)
        rec.save(args.save)
        where = f"writing {args.save}"
    elif args.viewer:
        rec.connect_grpc(args.viewer)
        where = f"sending to the viewer at {args.viewer}"
    elif args.web:
        url = rec.serve_grpc(grpc_port=args.port)
        rr.serve_web_viewer(open_browser=False, connect_to=url)
        where = f"serving {url}; web viewer on http://localhost:9090 (open it in a browser)"
    else:
        exe = _viewer_executable()
        if exe is None or not _can_open_window():
            msg = ("cannot start a Rerun viewer here (" + ("no display" if exe else
                   "no 'rerun' executable") + "); use --viewer URL of a running viewer, "
                   "--web to serve the web viewer, or --save FILE.rrd")
            raise TwindError(msg)
        rr.spawn(port=args.port, recording=rec, executable_path=exe)
        where = f"spawned the Rerun viewer (gRPC port {args.port})"
    connect = args.connect or [DEFAULT_ENDPOINT]
    print(f"twind view: {', '.join(connect)} -> {where}; Ctrl-C stops", flush=True)
    stats = stream(rec, connect, config_file=args.zenoh_config, ifo=args.ifo,
                   channels=args.channels, rate_hz=args.rate, duration=args.duration)
    rec.disconnect()
    print(f"twind view: {stats.blocks} blocks, {len(stats.rows)} channels, "
          f"{sum(stats.rows.values())} points, {stats.events} events"
          + (f", {stats.dropped} dropped (too far behind, or not twind blocks)"
             if stats.dropped else ""), file=sys.stderr)
    if stats.blocks == 0:
        print("twind view: no data arrived: is the twin running, and may these credentials "
              "subscribe?", file=sys.stderr)
    return 0


def cmd_rrd(args: argparse.Namespace) -> int:
    """Convert an MCAP session into a Rerun .rrd; prints what it holds."""

    out = Path(args.output) if args.output else Path(args.mcap).with_suffix(".rrd")
    summary = mcap_to_rrd(args.mcap, out, channels=args.channels, decimate_to_hz=args.rate,
                          bode=not args.no_bode)
    rows = sum(summary.series.values())
    print(f"wrote {out}: {len(summary.series)} channels at {summary.rate_hz:g} Hz "
          f"({rows} points), {summary.events} events, {len(summary.bode)} transfer functions")
    for base in summary.bode:
        print(f"  {base}")
    print(f"open it with: rerun {out}")
    return 0
