"""``twind record``, ``replay``, ``export`` and ``recover``: recordings on the bus and on disk."""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import warnings
from types import FrameType
from typing import Any

from twind.bus.keys import all_data
from twind.bus.session import DEFAULT_ENDPOINT, zenoh_config
from twind.recording.export import export
from twind.recording.recorder import Recorder
from twind.recording.recover import recover
from twind.recording.replay import check_rate, replay
from twind.recording.session import RecordingError, session_files


def cmd_record(args: argparse.Namespace) -> int:
    """``twind record``: record until --duration, SIGINT or SIGTERM; print a summary."""

    for name in ("duration", "rotate_mb", "rotate_s"):
        value = getattr(args, name)
        if value is not None and not (value > 0 and math.isfinite(value)):
            msg = f"--{name.replace('_', '-')} must be positive, got {value}"
            raise RecordingError(msg)
    connect = args.connect or ([] if args.listen or args.zenoh_config else [DEFAULT_ENDPOINT])
    conf = zenoh_config(listen=args.listen or (), connect=connect, mode=args.mode,
                        config_file=args.zenoh_config)
    recorder = Recorder(conf, args.output, args.keyexprs or (all_data(),), ifo=args.ifo,
                        rotate_bytes=int(args.rotate_mb * 1e6) if args.rotate_mb else None,
                        rotate_seconds=args.rotate_s, events=not args.no_events)
    stats = recorder.run(args.duration, parent=args.parent)
    print(stats.summary(), flush=True)
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    """``twind replay``: until the end (or, with --loop, SIGINT/SIGTERM)."""

    rate = check_rate(args.rate)
    files = session_files(args.files)
    connect = args.connect or ([] if args.listen else [DEFAULT_ENDPOINT])
    conf = zenoh_config(listen=args.listen or (), connect=connect, mode=args.mode)
    stop = threading.Event()
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        def on_signal(signum: int, frame: FrameType | None) -> None:
            stop.set()

        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    speed = "as fast as possible" if rate == 0 else f"at {rate:g}x"
    print(f"twind replay: {files[0]}{f' and {len(files) - 1} more' if len(files) > 1 else ''}"
          f" {speed}{', looping' if args.loop else ''}", file=sys.stderr, flush=True)
    try:
        stats = replay(files, conf, rate, args.loop, ifo=args.ifo, events=not args.no_events,
                       stop=stop,
                       log=lambda line: print(line, file=sys.stderr, flush=True))
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(f"replayed {stats.messages} messages ({stats.bytes / 1e6:.1f} MB) on "
          f"{len(stats.keys)} keys in {stats.elapsed_s:.2f} s ({stats.loops} pass(es); "
          f"recorded span {stats.recorded_span_s:.2f} s)")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """``twind export``: write the file, print what it holds, report gaps on stderr."""

    channels = None
    if args.channels:
        channels = [c for item in args.channels for c in item.split(",") if c]
    with warnings.catch_warnings():
        # reported below, once, without a Python source line
        warnings.simplefilter("ignore")
        result = export(args.inputs if len(args.inputs) > 1 else args.inputs[0], args.output,
                        channels)
    for problem in result.problems:
        print(f"twind export: warning: {problem}", file=sys.stderr)
    n_gaps = sum(len(g) for g in result.gaps.values())
    print(f"wrote {result.path} ({result.format}): {len(result.channels)} channel(s)"
          + (f", {n_gaps} gap(s) NaN-filled" if n_gaps else ""))
    return 0


def cmd_recover(args: argparse.Namespace) -> int:
    """``twind recover``: write the file, say what was lost."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the loss is reported below, once
        n, problems = recover(args.input, args.output)
    for problem in problems:
        print(f"twind recover: {problem}", file=sys.stderr)
    print(f"wrote {args.output}: {n} message(s)"
          + ("" if problems else f" ({args.input} was complete)"))
    return 0
