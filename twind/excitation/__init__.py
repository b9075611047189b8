"""awg-style excitations of the twin's ``_EXC`` test points (like LIGO's awg / awgstream).

Pure signal generation: a client's :class:`ExcitationRequest` (sine, log sweep, Schroeder
multisine, foton-shaped Gaussian noise or a stream of samples) is refused with a reason by
:func:`check` or turned into a :class:`Waveform` by :func:`make_waveform`, which hands out
the samples block by block.  Nothing here touches the bus or the physics.

Modules: :mod:`.request` (the request and its JSON form), :mod:`.checks` (limits and
refusals), :mod:`.design` (tapers, multisine periods, noise shaping), :mod:`.waveforms`
(the generators).
"""

from twind.excitation.checks import Limits, check
from twind.excitation.request import WAVEFORMS, ExcitationError, ExcitationRequest
from twind.excitation.waveforms import Waveform, make_waveform

__all__ = ["WAVEFORMS", "ExcitationError", "ExcitationRequest", "Limits", "Waveform", "check",
           "make_waveform"]
