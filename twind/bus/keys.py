"""Zenoh key expressions of the twin.

Every channel lives under a root of its own (``twin/C1:SUS-ETMX_SUSPOS_IN1``) so that a twin
is never mistaken for the real CDS. Control lives under a verbatim ``@`` chunk, which
wildcards such as ``twin/**`` do not match, so data subscribers never see it.
"""

from __future__ import annotations

ROOT = "twin"


def data_key(channel: str, root: str = ROOT) -> str:
    """``twin/C1:SUS-ETMX_SUSPOS_IN1``."""
    return f"{root}/{channel}"


def channel_of(key: str, root: str = ROOT) -> str:
    """The channel name of a data key."""
    prefix = f"{root}/"
    if not key.startswith(prefix):
        msg = f"{key!r} is not a twin data key (root {root!r})"
        raise ValueError(msg)
    return key[len(prefix):]


def all_data(root: str = ROOT) -> str:
    """Every channel of every twin under `root`."""
    return f"{root}/**"


def control_key(ifo: str, verb: str, root: str = ROOT) -> str:
    """``twin/@/C1/status``: queryables of the service (status, inject, stop, params, filter)
    and the ``events`` publication of injection events."""
    return f"{root}/@/{ifo}/{verb}"
