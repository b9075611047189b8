"""Helpers for tests that run a twin service on loopback."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

from twind.bus.session import free_port  # noqa: F401 - the tests take it from here
from twind.client import TwinClient


@contextmanager
def running(cmd: list[str], timeout: float = 20) -> Iterator[subprocess.Popen]:
    """A subprocess with piped output, terminated (killed if it must be) on exit."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()


@contextmanager
def serving(*args: str, port: int | None = None, ifo: str = "C1") -> Iterator[str]:
    """Run ``twind serve`` on a loopback port in a subprocess; yields its endpoint once the
    twin of `ifo` answers."""
    endpoint = f"tcp/127.0.0.1:{port or free_port()}"
    with running([sys.executable, "-m", "twind", "serve", "--listen", endpoint, *args]) as proc:
        TwinClient.wait([endpoint], alive=lambda: proc.poll() is None, ifo=ifo).close()
        yield endpoint
