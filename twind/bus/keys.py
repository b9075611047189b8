"""Zenoh key expressions of the twin.

Every channel lives under a root of its own (``twin/C1:SUS-ETMX_SUSPOS_IN1``) so that a twin
is never mistaken for the real CDS. Control lives under a verbatim ``@`` chunk, which
wildcards such as ``twin/**`` do not match, so data subscribers never see it.
"""

from __future__ import annotations

ROOT = "twin"


def data_key(channel: str, root: str = ROOT) -> str:
    """The Zenoh key a channel's blocks are published under.

    Parameters
    ----------
    channel : str
        The channel, e.g. ``C1:SUS-ETMX_SUSPOS_IN1``.
    root : str
        The key root of the twin (``twin``).

    Returns
    -------
    str

    Examples
    --------
    >>> data_key("C1:SUS-ETMX_SUSPOS_IN1")
    'twin/C1:SUS-ETMX_SUSPOS_IN1'
    """
    return f"{root}/{channel}"


def channel_of(key: str, root: str = ROOT) -> str:
    """The channel name of a data key.

    Parameters
    ----------
    key : str
        A data key, as :func:`data_key` makes it.
    root : str
        The key root of the twin (``twin``).

    Returns
    -------
    str

    Raises
    ------
    ValueError
        If `key` does not lie under `root`.

    Examples
    --------
    >>> channel_of("twin/C1:SUS-ETMX_SUSPOS_IN1")
    'C1:SUS-ETMX_SUSPOS_IN1'
    """
    prefix = f"{root}/"
    if not key.startswith(prefix):
        msg = f"{key!r} is not a twin data key (root {root!r})"
        raise ValueError(msg)
    return key[len(prefix):]


def all_data(root: str = ROOT) -> str:
    """Every channel of every twin under `root`."""
    return f"{root}/**"


def control_key(ifo: str, verb: str, root: str = ROOT) -> str:
    """The key of a service queryable (``status``, ``inject``, ``stop``, ``params``,
    ``filter``) or of the ``events`` publication of injection events.

    Parameters
    ----------
    ifo : str
        The twin's interferometer prefix, e.g. ``C1``.
    verb : str
        ``status``, ``inject``, ``stop``, ``params``, ``filter`` or ``events``.
    root : str
        The key root of the twin (``twin``).

    Returns
    -------
    str

    Examples
    --------
    >>> control_key("C1", "status")
    'twin/@/C1/status'
    """
    return f"{root}/@/{ifo}/{verb}"
