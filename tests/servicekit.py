"""Helpers for tests that run a twin service on loopback."""

from __future__ import annotations

import socket
import subprocess
import sys
from contextlib import contextmanager
from collections.abc import Iterator

from twind.client import TwinClient


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def serving(*args: str, port: int | None = None) -> Iterator[str]:
    """Run ``twind serve`` on a loopback port in a subprocess; yields its endpoint."""
    port = port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "twind", "serve", "--listen", endpoint, *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        TwinClient.wait([endpoint], alive=lambda: proc.poll() is None).close()
        yield endpoint
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
