"""Talk to a running twin over Zenoh, as scripts talk to CDS.

>>> with TwinClient(connect=["tcp/127.0.0.1:7447"]) as twin:          # doctest: +SKIP
...     exc = twin.inject("C1:SUS-ETMX_SUSPOS_EXC", "sine", freq=3.0, amp=0.1, duration=20)
...     print(twin.status().excitations)
...     twin.stop(exc)
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from types import TracebackType

import zenoh

from twind.bus.keys import ROOT, control_key
from twind.bus.session import DEFAULT_ENDPOINT, zenoh_config, zenoh_message
from twind.errors import TwindError
from twind.excitation.request import ExcitationError, ExcitationRequest, channel_match
from twind.protocol import (
    FilterRequest,
    ParamsReply,
    ParamsRequest,
    StatusReply,
    StopRequest,
)


class InjectionRefused(TwindError):
    """The twin refused an excitation; the message is its reason."""


class TwinUnreachable(TwindError):
    """No twin answered on the bus."""


class SeveralTwins(TwindError):
    """More than one twin did what one request asked: two twins serve the same optic.

    Attributes
    ----------
    replies : list of dict
        Each twin's reply (its ``twin`` and, for an injection, its excitation ``id``).
    """

    def __init__(self, msg: str, replies: list[dict]) -> None:
        super().__init__(msg)
        self.replies = replies


class AccessRefused(TwinUnreachable):
    """A twin answers ``status`` but not this request: Zenoh's access control dropped it.

    Zenoh's access control drops a denied query without telling the client or the twin, so
    the client infers the refusal from the twin answering the status query everyone may ask
    (deploy/README.md, "Passwords and access rights").
    """


class TwinClient:
    """A Zenoh client session to one twin service.

    Parameters
    ----------
    connect : sequence of str
        Endpoints of the twin (or of a router in front of it).
    ifo : str
        The twin's interferometer prefix.
    timeout : float
        Seconds to wait for a reply.
    root : str
        The key root the twin publishes under (``twin``).
    config_file : str, optional
        A Zenoh JSON5 configuration (credentials, TLS) to start from.

    Raises
    ------
    TwinUnreachable
        If no session can be opened to `connect`.

    Examples
    --------
    >>> with TwinClient(["tcp/127.0.0.1:7447"]) as twin:  # doctest: +SKIP
    ...     exc = twin.inject("C1:SUS-ETMX_SUSPOS_EXC", "sine", freq=3.0, amp=1.0,
    ...                       duration=10)
    ...     twin.params("ETMX", Q_POS=450)
    """

    def __init__(self, connect: Sequence[str] = (DEFAULT_ENDPOINT,), ifo: str = "C1",
                 timeout: float = 5.0, root: str = ROOT, config_file: str | None = None) -> None:
        self.ifo, self.timeout, self.root = ifo, timeout, root
        self.last_reply: dict = {}  # the reply :meth:`query` returned last (its twin)
        try:
            self._session = zenoh.open(zenoh_config(connect=connect, mode="client",
                                                    config_file=config_file))
        except zenoh.ZError as err:
            msg = (f"cannot reach a twin at {', '.join(connect)} ({zenoh_message(err)}): is "
                   "`twind serve` running there? Start one, or give its endpoint with --connect")
            raise TwinUnreachable(msg) from None

    @classmethod
    def wait(cls, connect: Sequence[str], timeout: float = 60.0,
             alive: Callable[[], bool] = lambda: True, **kwargs: object) -> TwinClient:
        """A client to a twin that may still be starting: retries until its status answers.

        Parameters
        ----------
        connect : sequence of str
            Endpoints of the twin.
        timeout : float
            Seconds to keep trying.
        alive : callable
            Asked between tries (e.g. ``lambda: proc.poll() is None`` for a service started
            as a process), so that a twin that died ends the wait at once.
        **kwargs
            As :class:`TwinClient` takes them.

        Returns
        -------
        TwinClient

        Raises
        ------
        TwinUnreachable
            If the twin has not answered within `timeout`, or `alive` says it died.
        """
        deadline = time.monotonic() + timeout
        while True:
            try:
                client = cls(connect=connect, **kwargs)
                try:
                    client.status()
                    return client
                except TwinUnreachable:
                    client.close()
                    raise
            except TwinUnreachable:
                if not alive() or time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    def replies(self, verb: str, request: dict | None = None) -> list[dict]:
        """Send one control request and return every twin's reply.

        A reply counts when it is a JSON object naming the twin that sent it (``twin``);
        anything else that answers on the key (an error, bytes that are not JSON, a process
        that is not a twin) is left out, and said so when no twin answered.

        Parameters
        ----------
        verb : str
            ``status``, ``inject``, ``stop``, ``params`` or ``filter``.
        request : dict, optional
            The request's JSON object.

        Returns
        -------
        list of dict
            The twins' replies, one per twin.

        Raises
        ------
        TwinUnreachable
            If no twin answers within the timeout.
        AccessRefused
            If the twin answers ``status`` but not `verb` (the session's rights).
        """
        key = control_key(self.ifo, verb, self.root)
        replies, others = [], []
        # no consolidation: every twin's reply, not only the last one per key
        for reply in self._session.get(key, payload=json.dumps(request or {}), timeout=self.timeout,
                                       consolidation=zenoh.ConsolidationMode.NONE):
            answer = twin_reply(reply)
            (replies if isinstance(answer, dict) else others).append(answer)
        if replies:
            return replies
        if others:
            msg = f"no twin answered on {key}; {len(others)} other answer(s): {others[0]}"
            raise TwinUnreachable(msg)
        if verb != "status" and self._answers_status():
            msg = (f"the twin answers status but not {verb} ({key}): most likely the "
                   f"access rights of this session do not allow {verb}; log in as a user "
                   "who may (an operator, --zenoh-config), see deploy/README.md")
            raise AccessRefused(msg)
        msg = (f"no twin answered on {key} within {self.timeout} s: is `twind serve` "
               "running and reachable at the endpoint given (--connect)?")
        raise TwinUnreachable(msg)

    def query(self, verb: str, request: dict | None = None) -> dict:
        """Send one control request and return the reply of the twin it concerns.

        Every twin on the bus answers; the one that did what was asked (its reply ``ok``)
        answers for all, otherwise the first refusal with its reason. Where several twins
        did it (two twins serving one optic), that is an error naming them: their replies
        are not merged.

        Parameters
        ----------
        verb, request
            As :meth:`replies`.

        Returns
        -------
        dict
            The reply's JSON object; ``twin`` names the twin.

        Raises
        ------
        TwinUnreachable, AccessRefused
            As :meth:`replies`.
        SeveralTwins
            If more than one twin did what was asked.
        """
        replies = self.replies(verb, request)
        done = [r for r in replies if r.get("ok") and r.get("accepted", True)]
        if verb != "status" and len(done) > 1:
            ids = "; ".join(f"twin {r['twin']}" + (f" (id {r['id']})" if "id" in r else "")
                            for r in done)
            msg = (f"{len(done)} twins did this {verb}, where one serves each optic: {ids}; "
                   "twind status lists them, twind stop all stops every excitation")
            raise SeveralTwins(msg, done)
        self.last_reply = (done or replies)[0]
        return self.last_reply

    def _answers_status(self) -> bool:
        key = control_key(self.ifo, "status", self.root)
        return any(r.ok is not None for r in self._session.get(key, timeout=self.timeout))

    def status(self) -> StatusReply:
        """The service status: real-time factor, lag, late blocks, excitations, uptime."""
        return StatusReply.from_json(self.query("status"))

    def inject(self, channel: str, waveform: str, **settings: object) -> str:
        """Start an excitation at a test point, as awg does.

        Parameters
        ----------
        channel : str
            The test point, e.g. ``C1:SUS-ETMX_SUSPOS_EXC``.
        waveform : str
            ``sine``, ``sweep``, ``noise``, ``multisine`` or ``stream``.
        **settings
            Those of :class:`twind.excitation.ExcitationRequest` (``freq``, ``amp``,
            ``duration``, ``ramp``, ``start_gps``, ``f_stop``, ``shape``, ``samples``...).

        Returns
        -------
        str
            The excitation's id (for :meth:`stop`).

        Raises
        ------
        InjectionRefused
            With the reason: a field of the wrong type or unknown, found before sending, or
            the twin's (over a limit, a test point it does not serve...); never clipped.
        """
        if "samples" in settings and settings["samples"] is not None:
            settings["samples"] = [float(x) for x in settings["samples"]]  # type: ignore[union-attr]
        try:  # typed and its fields checked here; its limits are the twin's to judge
            request = ExcitationRequest.from_json({"channel": channel, "waveform": waveform,
                                                   **settings})
            channel_match(request.channel)
        except ExcitationError as err:
            raise InjectionRefused(str(err)) from None
        reply = self.query("inject", request.to_json())
        if not reply.get("accepted"):
            raise InjectionRefused(reply.get("reason", "refused"))
        return reply["id"]

    def stop(self, exc_id: str | None = None) -> list[str]:
        """Stop one excitation by id, or all of them, on every twin, when `exc_id` is None."""
        request = StopRequest(all=True) if exc_id is None else StopRequest(id=exc_id)
        replies = self.replies("stop", request.to_json())
        done = [r for r in replies if r.get("ok")]
        if not done:
            raise TwindError(replies[0].get("reason", "stop failed"))
        return [x for r in done for x in r.get("stopped", [])]

    def params(self, optic: str, effect: dict | None = None, **changes: float) -> ParamsReply:
        """An optic's parameters and filter modules, set live first if asked.

        Parameters
        ----------
        optic : str
            E.g. ``ETMX``.
        effect : dict, optional
            Physics left out to run from now on, ``{"id": "coil_imbalance", "values":
            {...}}`` (the catalogue of docs/model.md); ``{"id": None}`` removes it.
        **changes
            Nominal parameters under the names ``twind fit`` reports (``wire_length_m``,
            ``Q_POS``...).

        Returns
        -------
        ParamsReply
            The optic's parameters, filter modules and effect after the change.

        Raises
        ------
        TwindError
            A :class:`twind.protocol.RequestError` naming a field at fault, found before
            sending; or the twin's reason for a refused change.
        """
        body = {"optic": optic, **({"set": changes} if changes else {}),
                **({"effect": effect} if effect is not None else {})}
        return self._changed("params", ParamsRequest.from_json(body).to_json())

    def rearm(self, optic: str) -> ParamsReply:
        """Re-arm a tripped watchdog: the optic's damping outputs come back (from rest)."""
        return self._changed("params", ParamsRequest(optic, rearm=True).to_json())

    def switch(self, optic: str, dof: str, fm: int, on: bool) -> ParamsReply:
        """Switch stage FM`fm` of `optic`'s `dof` damping filter module on or off.

        The twin refuses the change, with the reason, unless the damping loop stays stable.

        Parameters
        ----------
        optic : str
            E.g. ``ETMX``.
        dof : str
            ``POS``, ``PIT``, ``YAW`` or ``SIDE``.
        fm : int
            The stage, 1-10.
        on : bool
            True to switch it on, False off.

        Returns
        -------
        ParamsReply
            The optic's parameters and filter modules after the change.

        Raises
        ------
        TwindError
            A field at fault, found before sending; or the twin's reason for a refusal.
        """
        body = {"optic": optic, "dof": dof, "fm": fm, "on": on}
        return self._changed("filter", FilterRequest.from_json(body).to_json())

    def set_gain(self, optic: str, dof: str, gain: float,
                 ramp: float | None = None) -> ParamsReply:
        """Ramp `optic`'s `dof` damping gain to `gain`.

        The twin refuses the change, with the reason, unless the damping loop stays stable.

        Parameters
        ----------
        optic : str
            E.g. ``ETMX``.
        dof : str
            ``POS``, ``PIT``, ``YAW`` or ``SIDE``.
        gain : float
            The new gain of the module.
        ramp : float, optional
            Seconds to ramp over (0-3600); by default the module's own ramp time.

        Returns
        -------
        ParamsReply
            The optic's parameters and filter modules after the change.

        Raises
        ------
        TwindError
            A field at fault, found before sending; or the twin's reason for a refusal.
        """
        body = {"optic": optic, "dof": dof, "gain": gain, "ramp": ramp}
        return self._changed("filter", FilterRequest.from_json(body).to_json())

    def _changed(self, verb: str, request: dict) -> ParamsReply:
        reply = self.query(verb, request)
        if not reply.get("ok"):
            raise TwindError(reply.get("reason", f"{verb} failed"))
        return ParamsReply.from_json(reply)

    def close(self) -> None:
        """Close the session."""
        self._session.close()

    def __enter__(self) -> TwinClient:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def twin_reply(reply: zenoh.Reply) -> dict | str:
    """A twin's reply as its JSON object, or what else answered, in words.

    Parameters
    ----------
    reply : zenoh.Reply
        One answer to a query on a twin's control key.

    Returns
    -------
    dict or str
        The JSON object when it names its twin (``twin``), else a description.
    """
    if reply.ok is None:
        return f"an error: {reply.err.payload.to_bytes().decode(errors='replace')[:200]}"
    raw = reply.ok.payload.to_bytes()
    try:
        answer = json.loads(raw)
    except ValueError:  # UnicodeDecodeError is one
        return f"{len(raw)} bytes that are not JSON"
    if not (isinstance(answer, dict) and isinstance(answer.get("twin"), str)):
        return f"a reply that names no twin: {raw[:120].decode(errors='replace')}"
    return answer
