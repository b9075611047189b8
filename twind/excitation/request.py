"""What a client asks for: one excitation of one ``_EXC`` test point, and its JSON form.

This module only checks *types* (what :meth:`ExcitationRequest.from_json` needs to build a
request at all); whether the values make sense for a model rate and a channel's limits is
:func:`twind.excitation.checks.check`'s business.
"""

from __future__ import annotations

import math
import numbers
import re
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from twind.channels import EXC_POINT
from twind.errors import TwindError

WAVEFORMS: tuple[str, ...] = ("sine", "sweep", "noise", "multisine", "stream")
"""Waveform names a request may ask for."""

MAX_TONES = 1000
"""Most tones one multisine may have; more would make the design slow and the crest high."""

MAX_SAMPLES = 2**26
"""Default longest stream (samples): 4096 s at 16384 Hz, 512 MB as float64."""

MAX_FINITE_SAMPLES = 2**53
"""Longest finite excitation or ramp (samples, ~17000 years at 16384 Hz; every sample index
an int64 and a float64 hold exactly); beyond, use duration inf."""



class ExcitationError(TwindError):
    """An excitation request is refused; the message is the reason, in words.

    Parameters
    ----------
    reason : str
        What is wrong and, where it helps, what would be accepted.
    key : str, optional
        The request field at fault (``"freq"``, ``"samples"``...); prefixed to the message.
    """

    def __init__(self, reason: str, key: str | None = None) -> None:
        self.reason, self.key = reason, key
        super().__init__(f"{key}: {reason}" if key else reason)


def _show(x: object) -> str:
    """A value for a message: type and a short repr (never the repr of a huge list)."""
    if isinstance(x, (list, tuple, dict, np.ndarray)):
        return f"{type(x).__name__} of length {len(x)}"
    if isinstance(x, int) and abs(x) > 10**40:
        return "an integer of more than 40 digits"  # repr() itself refuses 4300+ digits
    return f"{type(x).__name__} {x!r:.40}"


def is_real(x: object) -> bool:
    """A real number a user meant (NaN and inf included): a bool is an int to Python but
    never a number a user meant; numpy bools are not Real."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def is_int(x: object) -> bool:
    """An integer a user meant: not a bool."""
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def _real(key: str, x: object, *, optional: bool = False) -> float | None:
    if x is None and optional:
        return None
    if not is_real(x):
        want = "a number or null" if optional else "a number"
        raise ExcitationError(f"must be {want}, got {_show(x)}", key)
    return _float(key, x)


def _float(key: str, x: numbers.Real) -> float:
    try:
        return float(x)
    except OverflowError:  # a Python int beyond 1.8e308
        raise ExcitationError("is too large a number", key) from None


def _duration(x: object) -> float:
    # JSON has no infinity; to_json writes "inf" and Python's json module may give inf.
    if isinstance(x, str) and x.strip().lower() in ("inf", "infinity", "+inf"):
        return math.inf
    if not is_real(x):
        raise ExcitationError(f'must be a number of seconds or "inf", got {_show(x)}',
                              "duration")
    return _float("duration", x)


def _integer(key: str, x: object, *, optional: bool = False) -> int | None:
    if x is None and optional:
        return None
    # JSON writers in other languages may send 3.0 for 3; a fractional count is an error.
    if isinstance(x, float) and x.is_integer():
        return int(x)
    if not is_int(x):
        raise ExcitationError(f"must be an integer, got {_show(x)}", key)
    return int(x)  # type: ignore[arg-type]


def _string(key: str, x: object, *, optional: bool = False) -> str | None:
    if x is None and optional:
        return None
    if not isinstance(x, str):
        raise ExcitationError(f"must be a string, got {_show(x)}", key)
    return x


def _freqs(x: object) -> tuple[float, ...] | None:
    if x is None:
        return None
    if not isinstance(x, (list, tuple)):
        raise ExcitationError(f"must be a list of numbers (Hz), got {type(x).__name__}",
                              "freqs")
    # Refuse before converting: a list of millions of tones would only waste time.
    if len(x) > MAX_TONES:
        raise ExcitationError(f"{len(x)} tones, more than the {MAX_TONES} a multisine may have",
                              "freqs")
    for j, f in enumerate(x):
        if not is_real(f):
            raise ExcitationError(f"element {j} must be a number, got {type(f).__name__}",
                                  "freqs")
    return tuple(_float("freqs", f) for f in x)


def _samples(x: object, max_samples: int) -> NDArray[np.float64] | None:
    """A JSON list (or an array) of numbers as a read-only float64 array.

    The length is checked before anything is converted, so that a hostile length costs
    nothing.
    """
    if x is None:
        return None
    if not isinstance(x, (list, tuple, np.ndarray)):
        raise ExcitationError(f"must be a list of numbers, got {type(x).__name__}", "samples")
    n = len(x)
    if n > max_samples:
        raise ExcitationError(f"{n} samples, more than the {max_samples} a stream may have",
                              "samples")
    if isinstance(x, np.ndarray):
        arr = x
    else:
        # No dtype=float: numpy would turn the string "1" into 1.0.  Booleans are refused
        # here because np.array([1, True]) silently makes them integers.
        if any(isinstance(v, (bool, np.bool_)) for v in x):
            raise ExcitationError("must hold numbers only, found a boolean", "samples")
        try:
            arr = np.array(x)
        except (ValueError, TypeError, OverflowError) as exc:
            raise ExcitationError(f"must be a flat list of numbers ({exc})", "samples") from None
    if arr.ndim != 1:
        raise ExcitationError(f"must be a flat list of numbers, got {arr.ndim} dimensions",
                              "samples")
    if arr.size and arr.dtype.kind not in "iuf":
        raise ExcitationError(f"must hold numbers only, got {arr.dtype.kind!r} values "
                              "(strings, objects or integers too large for a float?)",
                              "samples")
    out = np.asarray(arr, dtype=np.float64)
    if out is arr and isinstance(x, np.ndarray):
        return x  # a caller's array: not copied (it may be a zero-stride view of 2**30)
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class ExcitationRequest:
    """One excitation of one ``_EXC`` test point, as a client asks for it.

    Parameters
    ----------
    channel : str
        ``IFO:SUS-OPTIC_SUSDOF_EXC`` with DOF one of POS, PIT, YAW, SIDE, e.g.
        ``C1:SUS-ETMX_SUSPOS_EXC``.
    waveform : str
        ``"sine"``, ``"sweep"``, ``"noise"``, ``"multisine"`` or ``"stream"``.
    amp : float
        Peak amplitude (sine, sweep, multisine) or RMS after shaping (noise), in the
        channel's units; unused by a stream, whose samples carry their amplitude.
    freq : float, optional
        Hz: the sine's frequency, the sweep's start, the multisine's lowest tone.
    f_stop : float, optional
        Hz: the sweep's end (logarithmic sweep), the multisine's highest tone.
    n_tones : int, optional
        Multisine: number of log-spaced tones from `freq` to `f_stop`.
    freqs : tuple of float, optional
        Multisine: explicit tones (Hz), instead of `freq`, `f_stop`, `n_tones`.
    shape : str, optional
        Noise: foton design string shaping white noise; None is white up to Nyquist.
    duration : float
        Seconds; ``math.inf`` runs a sine, noise or multisine until stopped.  Ignored by a
        stream, whose length is ``len(samples)`` samples.
    ramp : float
        Seconds of raised-cosine taper at the start and at the end.
    start_gps : float, optional
        GPS start time; None starts as soon as possible.
    samples : ndarray, optional
        Stream: the samples, at the model rate.
    seed : int
        Noise: seed of ``np.random.default_rng``.

    Notes
    -----
    Fields a waveform does not use are ignored, except where two ways of giving the same
    thing conflict (a multisine's `freqs` with `n_tones`, `freq` or `f_stop`).  Equality
    compares `samples` element by element.
    """

    channel: str
    waveform: str
    amp: float = 0.0
    freq: float | None = None
    f_stop: float | None = None
    n_tones: int | None = None
    freqs: tuple[float, ...] | None = None
    shape: str | None = None
    duration: float = 10.0
    ramp: float = 0.0
    start_gps: float | None = None
    samples: NDArray[np.float64] | None = None
    seed: int = 0

    # -- derived ------------------------------------------------------------------------------
    @property
    def optic(self) -> str:
        """The optic of `channel` (``ETMX``); the channel must be valid."""
        return channel_match(self.channel).group("optic")

    # -- equality (samples are arrays) ----------------------------------------------------------
    def _scalars(self) -> tuple[Any, ...]:
        return tuple(getattr(self, f.name) for f in fields(self) if f.name != "samples")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ExcitationRequest):
            return NotImplemented
        if self._scalars() != other._scalars():
            return False
        if self.samples is None or other.samples is None:
            return self.samples is None and other.samples is None
        return bool(np.array_equal(self.samples, other.samples))

    def __hash__(self) -> int:
        # Equal requests have equal scalars, so hashing only those is consistent with __eq__.
        return hash(self._scalars())

    # -- JSON ----------------------------------------------------------------------------------
    @classmethod
    def from_json(cls, obj: dict, max_samples: int = MAX_SAMPLES) -> ExcitationRequest:
        """Build a request from a decoded JSON object, checking every field's type.

        Parameters
        ----------
        obj : dict
            Keys are the field names; `samples` and `freqs` are lists of numbers;
            `duration` may be ``"inf"``.  `channel` and `waveform` are required.
        max_samples : int
            Longest stream accepted; checked before the samples are converted.

        Returns
        -------
        ExcitationRequest
            Typed, but not yet checked against a model rate or limits (see ``check``).

        Raises
        ------
        ExcitationError
            For an object that is not a dict, an unknown or missing key, or a value of the
            wrong type; the message names the key.
        """
        if not isinstance(obj, dict):
            raise ExcitationError(f"an excitation request must be a JSON object, got "
                                  f"{type(obj).__name__}")
        known = {f.name for f in fields(cls)}
        for key in obj:
            if not isinstance(key, str) or key not in known:
                raise ExcitationError(f"unknown key {str(key)[:40]!r}; known keys are "
                                      f"{', '.join(sorted(known))}", str(key)[:40])
        for key in ("channel", "waveform"):
            if key not in obj:
                raise ExcitationError("missing (required)", key)
        kw: dict[str, Any] = {}
        for key, value in obj.items():
            kw[key] = _COERCE[key](value) if key != "samples" else _samples(value, max_samples)
        return cls(**kw)

    def to_json(self) -> dict:
        """The request as a JSON-ready dict that :meth:`from_json` reads back equal.

        Returns
        -------
        dict
            Every field; `samples` and `freqs` as lists, infinite `duration` as ``"inf"``.
        """
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "samples" and v is not None:
                v = np.asarray(v, dtype=float).tolist()
            elif f.name == "freqs" and v is not None:
                v = [float(x) for x in v]
            elif f.name == "duration" and v == math.inf:
                v = "inf"
            out[f.name] = v
        return out


_COERCE = {
    "channel": lambda x: _string("channel", x),
    "waveform": lambda x: _string("waveform", x),
    "amp": lambda x: _real("amp", x),
    "freq": lambda x: _real("freq", x, optional=True),
    "f_stop": lambda x: _real("f_stop", x, optional=True),
    "n_tones": lambda x: _integer("n_tones", x, optional=True),
    "freqs": _freqs,
    "shape": lambda x: _string("shape", x, optional=True),
    "duration": _duration,
    "ramp": lambda x: _real("ramp", x),
    "start_gps": lambda x: _real("start_gps", x, optional=True),
    "seed": lambda x: _integer("seed", x),
}


def channel_match(channel: object) -> re.Match[str]:
    """`channel` parsed as an excitation test point (:data:`twind.channels.EXC_POINT`).

    Raises
    ------
    ExcitationError
        If it is not one, naming the field ``channel``.
    """
    m = EXC_POINT.fullmatch(channel) if isinstance(channel, str) else None
    if m is None:
        raise ExcitationError(f"{channel!r:.60} is not an excitation test point; expected "
                              "IFO:SYSTEM-OPTIC_<point>_EXC, e.g. C1:SUS-ETMX_SUSPOS_EXC or "
                              "K1:VIS-SRM_TM_TEST_P_EXC", "channel")
    return m


def typed(req: ExcitationRequest, max_samples: int = MAX_SAMPLES) -> ExcitationRequest:
    """Check the field types of a request built directly (not by :meth:`from_json`).

    Parameters
    ----------
    req : ExcitationRequest
        Any request; its fields may hold anything.
    max_samples : int
        Longest stream accepted.

    Returns
    -------
    ExcitationRequest
        The same request, with `freqs` as floats and `samples` as a float64 array.

    Raises
    ------
    ExcitationError
        For a field of the wrong type, naming it.
    """
    if not isinstance(req, ExcitationRequest):
        raise ExcitationError(f"expected an ExcitationRequest, got {type(req).__name__}")
    kw = {f.name: (_COERCE[f.name](getattr(req, f.name)) if f.name != "samples"
                   else _samples(req.samples, max_samples)) for f in fields(req)}
    return ExcitationRequest(**kw)
