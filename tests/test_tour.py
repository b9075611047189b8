"""The README's five-minute tour as written, shortened and at high speed: serve recording,
wait for the twin, excite POS, PIT and YAW in turn, and measure the transfer functions; an
excitation that would outlast the service is refused, saying why."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from servicekit import free_port, running

SPEED = 8.0


def twind(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twind", *args], capture_output=True,
                          text=True, timeout=120)


@pytest.mark.slow
def test_the_tour_as_written(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rec = tmp_path / "rec"
    with running([sys.executable, "-m", "twind", "serve", "--optics", "ETMX", "--record",
                  str(rec), "--speed", str(SPEED), "--duration", "240", "--listen", endpoint],
                 timeout=60) as serve:
        # at once, as a newcomer types it: the client waits for the twin to answer
        status = twind("status", "--wait", "60", "--connect", endpoint, "--json")
        assert status.returncode == 0, status.stderr
        assert json.loads(status.stdout)["optics"] == ["ETMX"]
        for dof in ("POS", "PIT", "YAW"):
            started = time.monotonic()
            got = twind("inject", f"C1:SUS-ETMX_SUS{dof}_EXC", "noise", "--amp", "10",
                        "--duration", "24", "--ramp", "1", "--connect", endpoint)
            assert got.returncode == 0, got.stderr
            assert got.stdout.startswith("exc-")
            time.sleep(max(0.0, 28 / SPEED - (time.monotonic() - started)))
        late = twind("inject", "C1:SUS-ETMX_SUSPOS_EXC", "sine", "--freq", "3", "--amp", "1",
                     "--duration", "1000", "--connect", endpoint)
        assert late.returncode == 2
        assert "past the end of this service" in late.stderr and "serve --duration" in late.stderr
        stopped = twind("stop", "all", "--connect", endpoint)  # the last one has ended
        assert stopped.stdout.strip() == "no excitation was running", stopped.stdout
        assert serve.wait(timeout=120) == 0, serve.stderr.read()
    tf = twind("tf", *map(str, sorted(rec.glob("*.mcap"))), "--bw", "0.5", "--json")
    assert tf.returncode == 0, tf.stderr
    assert json.loads(tf.stdout)["excited"] == ["POS", "PIT", "YAW"]
