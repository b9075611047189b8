"""How long the commands a person waits on take, from process start to their answer:
``twind --help``, a refused input, and ``twind inject`` against a served twin on loopback.

Each is run as a new process, as a person runs it, several times; the figures are wall
times, printed beside their targets (docs/benchmarks.md).
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence

from twind.bus.session import free_port

TARGETS_S = {"twind --help": 1.0, "twind tf missing.xml": 1.0, "twind inject": 1.5}
"""The longest a person should wait for each (issue 42's)."""


def _timed(argv: Sequence[str]) -> tuple[float, int]:
    """Wall seconds of one ``python -m twind`` process, and its exit status."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "twind", *argv], capture_output=True,
                          check=False)
    return time.perf_counter() - start, done.returncode


def command_latency(runs: int = 5, say: Callable[[str], None] = print) -> list[str]:
    """Time each command `runs` times; the lines of the table.

    Parameters
    ----------
    runs : int
        Processes per command.
    say : callable
        Told what is being done, as it is.

    Returns
    -------
    list of str
        One line per command: median and largest seconds, and the target.
    """
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    serve = subprocess.Popen([sys.executable, "-m", "twind", "serve", "--optics", "ETMX",
                              "--listen", endpoint, "--duration", "600"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        say("waiting for the twin to answer ...")
        _, status = _timed(["status", "--wait", "60", "--connect", endpoint])
        if status != 0:
            return [f"the twin at {endpoint} did not answer within 60 s"]
        commands = {"twind --help": ["--help"], "twind tf missing.xml": ["tf", "missing.xml"],
                    "twind inject": ["inject", "C1:SUS-ETMX_SUSPOS_EXC", "sine", "--freq", "3",
                                     "--amp", "1", "--duration", "1", "--connect", endpoint]}
        lines = [f"{'command':22s} {'median s':>9s} {'max s':>7s} {'target s':>9s}"]
        for name, argv in commands.items():
            say(f"{name}: {runs} processes ...")
            times = [_timed(argv)[0] for _ in range(runs)]
            lines.append(f"{name:22s} {statistics.median(times):9.2f} {max(times):7.2f} "
                         f"{TARGETS_S[name]:9.1f}")
        return lines
    finally:
        serve.terminate()
        serve.wait(timeout=30)
