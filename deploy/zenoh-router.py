#!/usr/bin/env python3
"""A Zenoh router from the Python binding that twind already depends on (eclipse-zenoh), for
hosts without ``zenohd``:

    /opt/twind/venv/bin/python zenoh-router.py -c /etc/twind/zenoh-router.json5

It opens one session in router mode with the given configuration (``--listen`` replaces the
file's endpoints; ``--cfg KEY:VALUE`` sets any key, as zenohd's option of that name does) and
routes until SIGINT or SIGTERM. zenohd adds plugins (REST, storages) that twind does not need.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

import zenoh


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="zenoh-router", description=__doc__.splitlines()[0])
    p.add_argument("-c", "--config", help="Zenoh JSON5 configuration file")
    p.add_argument("-l", "--listen", action="append", help="endpoint, e.g. tcp/0.0.0.0:7447")
    p.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                   help="set a key to a JSON5 value, "
                        "e.g. 'transport/auth/usrpwd/dictionary_file:\"/x\"'")
    args = p.parse_args(argv)
    conf = zenoh.Config.from_file(args.config) if args.config else zenoh.Config()
    conf.insert_json5("mode", '"router"')
    # never through shared memory, whatever the file says: see zenoh-router.json5
    conf.insert_json5("transport/shared_memory/enabled", "false")
    if args.listen:
        conf.insert_json5("listen/endpoints", json.dumps(args.listen))
    for item in args.cfg:
        key, sep, value = item.partition(":")
        if not sep:
            p.error(f"--cfg {item!r}: expected KEY:VALUE")
        conf.insert_json5(key, value)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with zenoh.open(conf) as session:
        listen = conf.get_json("listen/endpoints")
        print(f"zenoh router {session.info.zid()} listening on {listen}", flush=True)
        while not stop.wait(1.0):
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
