"""Who published a recorded channel: the twins asked which optics they serve.

Every block names the twin that published it (``host/pid/tag``). A recorder asks the twins on
the bus for their status (``twin/@/<IFO>/status``), which lists each twin's identity and
optics, the first time a twin's name appears and again while the answer is missing; a block
whose twin does not answer (while others do: the bus works), does not serve the block's
optic, or that names no twin, is from no twin that serves it (a forgery, a replay, a
script). The recorder keeps such blocks and
marks the channel with an ``unserved`` event; readers warn of it.
"""

from __future__ import annotations

import json
import queue
import threading
import time
import warnings
from collections.abc import Callable
from typing import Any

import zenoh

from twind.bus.keys import control_key
from twind.channels import POINT_NAME
from twind.errors import TwindWarning
from twind.recording.session import caller_level

__all__ = ["Roster", "UnservedWarning", "warn_unserved"]

ASKS = 3
"""Times a twin that has not answered is asked before its blocks are called unserved."""
PACE_S = 2.0
"""Least seconds between two queries: a twin just started, busy, is given time."""
MOST_TWINS = 64
"""Twin names asked after at most; beyond them (a forger's many names) blocks are unserved."""


class UnservedWarning(TwindWarning):
    """A recorded channel came from no twin that serves its optic."""


class Roster:
    """The optics each twin on the bus serves, by its own status reply.

    Parameters
    ----------
    session : zenoh.Session
        The recorder's session.
    ifo : str
        Interferometer prefix of the status key.
    timeout : float
        Seconds each status query waits for replies.
    pace_s : float
        Least seconds between two queries.
    """

    def __init__(self, session: zenoh.Session, ifo: str, timeout: float = 2.0,
                 pace_s: float = PACE_S) -> None:
        self.session, self.key, self.timeout = session, control_key(ifo, "status"), timeout
        self.pace_s = max(pace_s, timeout)
        self._serves: dict[str, frozenset[str]] = {}  # twin -> optics, from its replies
        self._asked: dict[str, int] = {}  # twin -> queries it was missing from
        self._pending: set[str] = set()
        self._lock = threading.Lock()
        self._wanted: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._ask_loop, name="twind-roster",
                                        daemon=True)
        self._thread.start()

    def verdict(self, twin: str, channel: str) -> tuple[bool, str | None]:
        """Whether the twins have told, and why the block of `channel` named `twin` is from
        no twin that serves it (None when it is, or while the twins are asked).

        Parameters
        ----------
        twin : str
            The twin the block names.
        channel : str
            The block's channel.

        Returns
        -------
        known : bool
            False while the twins are being asked.
        why : str or None
        """
        if not twin:
            return True, "its blocks name no twin"
        match = POINT_NAME.match(channel)
        optic = match["optic"] if match else None
        with self._lock:
            serves = self._serves.get(twin)
            if serves is None:
                if self._asked.get(twin, 0) >= ASKS:
                    return True, f"twin {twin} does not answer {self.key}"
                if len(self._asked) + len(self._pending) >= MOST_TWINS:
                    return True, f"twin {twin} is one of more than {MOST_TWINS} names"
                if twin not in self._pending:
                    self._pending.add(twin)
                    self._wanted.put(twin)
                return False, None
        if optic not in serves:
            return True, f"twin {twin} serves {', '.join(sorted(serves)) or 'nothing'}, not {optic}"
        return True, None

    def close(self) -> None:
        """End the asking thread (a query under way ends by its timeout)."""
        self._closed.set()
        self._wanted.put(None)
        self._thread.join(timeout=self.timeout + 1.0)

    def _ask_loop(self) -> None:
        while (twin := self._wanted.get()) is not None and not self._closed.is_set():
            with self._lock:
                known = twin in self._serves  # an answer to an earlier query named it
            answers = {} if known else self._ask()
            with self._lock:
                self._serves.update(answers)
                if answers and twin not in self._serves:  # others answered: the bus works
                    self._asked[twin] = self._asked.get(twin, 0) + 1
                self._pending.discard(twin)

    def _ask(self) -> dict[str, frozenset[str]]:
        answers: dict[str, frozenset[str]] = {}
        started = time.monotonic()
        try:
            for reply in self.session.get(self.key, timeout=self.timeout):
                status = _status(reply)
                if status is not None:
                    answers[status["twin"]] = frozenset(status["optics"])
        except zenoh.ZError:
            pass  # the session is closing, or the router is away: asked again
        self._closed.wait(max(0.0, self.pace_s - (time.monotonic() - started)))
        return answers


def _status(reply: Any) -> dict | None:
    """A twin's status from a reply, or None for anything else."""
    if reply.ok is None:
        return None
    try:
        status = json.loads(reply.ok.payload.to_bytes())
    except ValueError:
        return None
    if not (isinstance(status, dict) and isinstance(status.get("twin"), str)
            and isinstance(status.get("optics"), list)):
        return None
    return status


def warn_unserved(events: list[dict], channels: Callable[[str], bool],
                  problems: list[str]) -> None:
    """One :class:`UnservedWarning` for the ``unserved`` events of the channels read.

    Parameters
    ----------
    events : list of dict
        The recording's events.
    channels : callable
        Whether a channel was read.
    problems : list of str
        Receives the warning's text; nothing when every channel read came from its twin.

    Warns
    -----
    UnservedWarning
    """
    marks = [e for e in events if e.get("event") == "unserved" and channels(e.get("channel", ""))]
    if not marks:
        return
    listed = "; ".join(f"{e['channel']}: {e.get('why', '')}" for e in marks[:5])
    more = f"; and {len(marks) - 5} more" if len(marks) > 5 else ""
    text = (f"{len(marks)} channel(s) came from no twin that serves them (a forgery, a "
            f"replay or a script): {listed}{more}")
    problems.append(text)
    warnings.warn(text, UnservedWarning, stacklevel=caller_level())
