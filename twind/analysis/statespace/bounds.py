"""Where a change of a state-space model may go in a fit, and when it has gone to an edge.

A fit refines a place, it does not wander to another mode's: a moved mode stays within the
stretch of the peak it was found at, a mode in no model away from where a moved mode lies,
each inside the coherent band (:func:`limits`). A change that ends at such an edge, or at the
most amplitude or the broadest Q a mode may take, has found another mode's place or a slope
of the band, not its own (:func:`pinned`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from twind.analysis.identification.data import FitData
from twind.analysis.statespace.fit import RANGES, PlantFit
from twind.analysis.statespace.model import Effect, PlantModel
from twind.analysis.statespace.moves import reach
from twind.analysis.statespace.search import MOST_AMPLITUDE, SHIFT


MOST_SHARE = 1.0
"""A coupling's share either way: a drive's share of another input of its stage, in any
readback (``drive_coupling``), and a readback's share of another readback
(``cross_coupling``). A drive that drives another input more than its own is not that
drive, a readback that reads another more than its own DOF is not that readback, and a
share past it is a free calibration's trade (the BS's TM_LOCK_P b file: shares of 1e8
against a calibration of 1e-8, which wrecked the final fit). The real files' shares are
0.002-5 %."""
MODE_Q = (3.0, 1e7)
"""A moved mode's Q: below 3 a peak is wider than a third of its frequency, a slope of the
band no data resolve as that mode."""


def band(data: FitData) -> tuple[float, float]:
    """The coherent band: the lowest and highest frequency of a bin used."""
    f = data.frequency_hz[data.mask.any(axis=(1, 2))]
    return max(float(f[0]), 1e-3), float(f[-1])


def moved_to(model: PlantModel, effects: Sequence[tuple[Effect, dict]]
             ) -> list[tuple[float, float]]:
    """Where the modes that `effects` move now lie, each widened to three widths or
    :data:`~twind.analysis.identification.model.NARROW_REACH_BINS` bins, whichever is more:
    a mode in no model found there would be the moved one again. Likewise each mode in no
    model already found, widened to one width: a second there would split the first."""
    out = []
    for effect, own in effects:
        if effect.family == "resonance":
            r = max(own["f_hz"] / own["q"], model.res)
            out.append((own["f_hz"] - r, own["f_hz"] + r))
        if effect.family == "mode_frequency":
            k = effect.target[0]
            f = model.modal.modes[k].f_hz * math.exp(own["log_f"])
            q = model.modal.q[k] * math.exp(own["log_q"])
            r = reach(f, q, model.res)
            out.append((f - r, f + r))
    return out


def limits(model: PlantModel, data: FitData, effects: Sequence[tuple[Effect, dict]]
           ) -> dict[str, tuple[float, float]]:
    """Where each change may go in a fit. A resonance's frequency: inside the coherent band,
    less where a moved mode lies (:func:`moved_to`), the stretch that holds it. A moved
    mode: within its anchor (the stretch of the peak it was found at: a fit refines a place,
    it does not wander to another mode's), :data:`~twind.analysis.statespace.search.SHIFT`
    and the band; its Q within :data:`MODE_Q`; its amplitude within
    :data:`~twind.analysis.statespace.search.MOST_AMPLITUDE` of the model's either way (a
    mode that needs more is not that mode, or trades against a calibration). A coupling's
    shares: within :data:`MOST_SHARE` either way."""
    lo, hi = band(data)
    avoid = moved_to(model, effects)
    out = {}
    for effect, own in effects:
        key = effect.key()
        if effect.family == "mode_frequency":
            k = effect.target[0]
            f0 = model.modal.modes[k].f_hz
            a, b = effect.anchor or (f0 / SHIFT, f0 * SHIFT)
            a, b = max(a, lo, f0 / SHIFT), min(b, hi, f0 * SHIFT)
            if a < b:
                out[f"{key}.log_f"] = (math.log(a / f0), math.log(b / f0))
            out[f"{key}.log_q"] = (math.log(MODE_Q[0] / model.modal.q[k]),
                                   math.log(MODE_Q[1] / model.modal.q[k]))
            out[f"{key}.amplitude"] = (1 / MOST_AMPLITUDE, MOST_AMPLITUDE)
        if effect.family in ("drive_coupling", "cross_coupling"):
            out.update({f"{key}.{name}": (-MOST_SHARE, MOST_SHARE) for name in own})
        if effect.family != "resonance":
            continue
        at, a, b = own["f_hz"], lo, hi
        for x, y in avoid:
            if y <= at:
                a = max(a, y)
            elif x >= at:
                b = min(b, x)
        out[f"{key}.f_hz"] = (a, b)
    return out


def pinned(fit: PlantFit, effect: Effect, model: PlantModel,
           within: dict[str, tuple[float, float]] | None = None) -> bool:
    """Whether a moved mode ends at a bound of :func:`limits`: its amplitude at one or
    within a sigma of it (the data want more, or less, of it there than the model's shape
    of that mode gives), its Q at the lowest, or its frequency within half a bin of its
    anchor's edge (it left the peak it was found at for a flank). Either way the place is
    another mode's. A mode's amplitude within two sigmas of the model's is no change.
    Likewise a mode in no model at its lowest Q (``RANGES["q"]``: a slope of the band), or
    within a bin of the edge of its stretch (`within`, from :func:`limits`): the coherent
    band's edge, where a slope of the band is no mode, or a moved mode's place."""
    if effect.family == "mode_amplitude":  # the model's own amplitude is no reading
        a, sa = fit.own(effect)["amplitude"], fit.error(f"{effect.key()}.amplitude")
        return sa is None or abs(a - 1.0) < 2 * sa
    if effect.family == "resonance":
        own = fit.own(effect)
        a, b = (within or {}).get(f"{effect.key()}.f_hz", (-math.inf, math.inf))
        at_edge = min(own["f_hz"] - a, b - own["f_hz"]) < model.res
        return at_edge or own["q"] < 1.05 * RANGES["q"][0]  # or as broad as it may be
    if effect.family != "mode_frequency":
        return False
    own, key = fit.own(effect), effect.key()
    a, sa = own["amplitude"], fit.error(f"{key}.amplitude") or 0.0
    if not (1.01 / MOST_AMPLITUDE < a - sa and a + sa < MOST_AMPLITUDE / 1.01):
        return True  # at its bound, or within a sigma of it
    if model.modal.q[effect.target[0]] * math.exp(own["log_q"]) < 1.05 * MODE_Q[0]:
        return True  # as broad as a mode may be: a slope of the band, not this mode
    if effect.anchor is None:
        return False
    f = model.modal.modes[effect.target[0]].f_hz * math.exp(own["log_f"])
    return min(abs(f - x) for x in effect.anchor) < 0.5 * model.res
