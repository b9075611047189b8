"""``twind serve``: run the twin on Zenoh until stopped (SIGINT/SIGTERM end it cleanly)."""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from twind.config import TwinConfig
from twind.service.twin import TwinService


def main(conf: zenoh.Config, twin: TwinConfig, optics: list, *, block_s: float = 1 / 16,
         speed: float = 1.0, seed: int = 0, duration: float | None = None,
         record_dir: str | None = None, endpoints: Sequence[str] = ()) -> int:
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
    """
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with zenoh.open(conf) as session:
        # the recorder subscribes before the service answers anything, so that no block and
        # no injection event escapes the recording
        recorder = _recorder(record_dir, endpoints, twin.ifo) if record_dir else None
        service = TwinService(session, twin, optics, block_s=block_s, speed=speed, seed=seed)
        print(f"twind serve: {', '.join(o.name for o in optics)} at {service.rate:g} Hz in "
              f"{service.block_s:g} s blocks, {speed:g} x real time, GPS {service.gps0:.3f}, "
              f"on {' '.join(endpoints)}; Ctrl-C stops", flush=True)
        try:
            service.run(duration=duration, stop=stop)
        finally:
            status = service.status()
            if recorder is not None:
                time.sleep(0.2)  # let the last blocks reach the recorder before it closes
                recorder.stop()
            service.close()
    print(f"twind serve: stopped after {status['blocks']} blocks, {status['late_blocks']} late, "
          f"max lag {status['max_lag_s'] * 1e3:.1f} ms, busy {100 * status['cpu_fraction']:.1f} %",
          file=sys.stderr)
    return 0


def _recorder(folder: str, endpoints: Sequence[str], ifo: str):  # noqa: ANN202
    from twind.bus.session import zenoh_config
    from twind.recording.recorder import Recorder
    from twind.timeutil import now_gps

    Path(folder).mkdir(parents=True, exist_ok=True)
    conf = zenoh_config(connect=[e.replace("0.0.0.0", "127.0.0.1") for e in endpoints],
                        mode="client")
    recorder = Recorder(conf, Path(folder) / f"{ifo}-twin-{int(now_gps())}.mcap", ifo=ifo,
                        rotate_seconds=3600.0, status_timeout=0.1)
    recorder.start()
    return recorder
