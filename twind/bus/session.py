"""Zenoh configuration for twin services and clients."""

from __future__ import annotations

import json
import re
import socket
from collections.abc import Sequence

import zenoh

from twind.errors import BusError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def free_port() -> int:
    """A TCP port on loopback that nothing listens on now (for a twin, a router or a
    recorder a benchmark or test starts; another process may take it before they do)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def zenoh_config(listen: Sequence[str] = (), connect: Sequence[str] = (),
                 mode: str | None = None, config_file: str | None = None,
                 scouting: bool | None = None) -> zenoh.Config:
    """A Zenoh configuration.

    Parameters
    ----------
    listen, connect : sequence of str
        Endpoints such as ``tcp/127.0.0.1:7447``.
    mode : {"peer", "client", "router"}, optional
        Default: the configuration file's, else ``"peer"``.
    config_file : str, optional
        A Zenoh JSON5 configuration file (e.g. ``deploy/zenoh-router.json5``) to start from.
    scouting : bool, optional
        Multicast scouting. Default: the configuration file's, else off, so that tests and
        twins stay on the endpoints they are given and never find each other by accident.

    Returns
    -------
    zenoh.Config
        With Zenoh's shared memory off, whatever the file says. Zenoh 1.x passes a message
        of more than 3 kB to a process on the same host through a shared-memory pool; when
        the receiver is descheduled for a moment (a loaded machine, a suspended client), the
        sender reuses buffers not yet read, and a subscriber got blocks undecodable, of
        another channel or out of sequence (zenoh 1.10.2; upstream eclipse-zenoh/zenoh#2628).
        Blocks are 8 kB: copying them costs little. Routers need the same setting (deploy/).
    """
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    conf.insert_json5("transport/shared_memory/enabled", "false")
    if mode is not None or not config_file:
        conf.insert_json5("mode", json.dumps(mode or "peer"))
    for endpoint in (*listen, *connect):
        _check_endpoint(endpoint)
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if scouting is not None or not config_file:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(scouting)))
    return conf


ENDPOINT = re.compile(r"^[a-z][a-z0-9-]*/[^\s/]\S*$")
"""A Zenoh endpoint: ``<protocol>/<address>[?<metadata>][#<config>]``."""


def _check_endpoint(endpoint: str) -> None:
    """Refuse what is not a Zenoh endpoint, in words (Zenoh's own message is a JSON5 error
    with a Rust source path)."""
    if not ENDPOINT.match(endpoint):
        msg = (f"{endpoint!r} is not a Zenoh endpoint: <protocol>/<address>, e.g. "
               f"{DEFAULT_ENDPOINT}")
        raise BusError(msg)


def zenoh_message(err: BaseException) -> str:
    """Zenoh's error text for a person: without the Rust source location it ends with and
    the JSON5 wrapper around a configuration error."""
    text = str(err)
    wrapped = re.search(r'msg: "(.*?)"', text)
    if wrapped:
        text = wrapped.group(1)
    return re.sub(r"\s*at \S+\.rs:\d+\.?", "", text).strip()
