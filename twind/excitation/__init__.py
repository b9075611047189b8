"""awg-style excitations of the twin's ``_EXC`` test points (like LIGO's awg / awgstream).

Pure signal generation: a client's :class:`ExcitationRequest` (sine, log sweep, Schroeder
multisine, foton-shaped Gaussian noise or a stream of samples) is refused with a reason by
:func:`check` or turned into a :class:`Waveform` by :func:`make_waveform`, which hands out
the samples block by block.  Nothing here touches the bus or the physics.

Modules: :mod:`.request` (the request and its JSON form), :mod:`.checks` (limits and
refusals), :mod:`.design` (tapers, multisine periods, noise shaping), :mod:`.waveforms`
(the generators).
"""

import importlib
from typing import Any

from twind.excitation.request import WAVEFORMS, ExcitationError, ExcitationRequest

_LATER = {"Limits": "checks", "check": "checks", "Waveform": "waveforms",
          "make_waveform": "waveforms"}
"""Names imported when first asked for: the generators need scipy, which a client that only
builds and sends a request (``twind inject``, ``twind status``) should not wait for."""


def __getattr__(name: str) -> Any:  # noqa: ANN401 - whichever the name is
    if name in _LATER:
        return getattr(importlib.import_module(f"twind.excitation.{_LATER[name]}"), name)
    msg = f"module 'twind.excitation' has no attribute {name!r}"
    raise AttributeError(msg)


__all__ = ["WAVEFORMS", "ExcitationError", "ExcitationRequest", "Limits", "Waveform", "check",
           "make_waveform"]
