"""Where a measurement shows a model's modes: each mode tried at the data's own peaks, and one
place given to each.

A model's mode found elsewhere in a measurement is found where the data show a peak, in the
elements the mode answers in, with a width the data allow: a screen of the mode against the
residuals (:meth:`~twind.analysis.statespace.search.Residuals.profile`) also rises where
moving it merely fills some other misfit (a neighbouring mode's, a coupling's, a broad
stretch a calibration left), so the places tried are the peaks
(:func:`~twind.analysis.statespace.peaks.measured_peaks`), as a commissioner reads a transfer
function before comparing it with the model. The places are then given out best first, each
mode one and each place one mode (:func:`assign`): a suspension's modes seldom cross, and
two modes never sit on one peak.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from twind.analysis.identification.model import NARROW_REACH_BINS
from twind.analysis.statespace.model import Effect, PlantModel
from twind.analysis.statespace.peaks import Peak
from twind.analysis.statespace.search import FINE_Q, MOST_AMPLITUDE, SHIFT, Residuals, grid

SHARE = 0.05
"""An element shows a mode when it holds at least this share of the mode's whitened power."""
RESOLVED_BINS = 3.0
"""A peak wider than this many bins has its width resolved: its Q is read from it."""
Q_SPREAD = 3.0
"""A trial's Q lies within this factor of the Q a peak's width gives (above it alone for a
peak the bins do not resolve)."""


@dataclass(frozen=True)
class Candidate:
    """A model mode at one of the data's peaks, as its screen found it.

    Attributes
    ----------
    mode : int
    f_hz, q, amplitude : float
        Where, how narrow, and how large (of the model's) the screen puts it.
    drop : float
        The drop in chi^2 (noise units).
    paths : tuple of float
        Its sweeps' look-elsewhere paths (rad), for the whole reach the mode was looked for
        in.
    peak_hz : float, optional
        Where the peak it was found at stands: the screen's best trial may lie on the
        peak's flank, where a mode whose shape or amplitude the model has wrong fills the
        residuals best.
    """

    mode: int
    f_hz: float
    q: float
    amplitude: float
    drop: float
    paths: tuple[float, ...]
    peak_hz: float | None = None

    def effect(self, model: PlantModel, res_hz: float) -> tuple[Effect, dict[str, float]]:
        """The move: the effect, anchored within its reach (:func:`reach`) of the place, and
        where its fit starts."""
        r = reach(self.f_hz, self.q, res_hz)
        k = self.mode
        return (Effect("mode_frequency", (k,), (self.f_hz - r, self.f_hz + r)),
                {"log_f": math.log(2 * math.pi * self.f_hz / model.modal.w[k]),
                 "log_q": math.log(self.q / model.modal.q[k]), "amplitude": self.amplitude})


def reach(f_hz: float, q: float, res_hz: float) -> float:
    """How far a mode at `f_hz` of quality `q` lies from another place the data tell apart:
    three widths, or :data:`~twind.analysis.identification.model.NARROW_REACH_BINS` bins."""
    return max(3 * f_hz / q, NARROW_REACH_BINS * res_hz)


def candidates(res: Residuals, model: PlantModel, k: int, peaks: Sequence[Peak],
               unit: float, least: float) -> list[Candidate]:
    """Mode `k` at each of the data's `peaks` in the elements that show it (:data:`SHARE`),
    within :data:`~twind.analysis.statespace.search.SHIFT` of its frequency, inside the band
    and more than a bin from where the model has it: the best trial near each peak (within
    two widths and two bins) at a Q its width allows (:data:`Q_SPREAD`), with an amplitude
    below :data:`~twind.analysis.statespace.search.MOST_AMPLITUDE` either way (at the bound,
    the data want more of it there than its shape gives: another mode's peak) and a drop
    of at least `least`. A mode broader than a bin is also tried anywhere in that reach,
    at a Q near its own: a damped mode moved may raise no peak that stands out of any
    element."""
    data, res_hz = res.data, res.data.resolution_hz
    f0 = model.modal.modes[k].f_hz
    used = data.frequency_hz[data.mask.any(axis=(1, 2))]
    lo, hi = max(f0 / SHIFT, float(used[0])), min(f0 * SHIFT, float(used[-1]))
    shows = _elements(res, model, k)
    own = [p for p in peaks if shows[p.element] and lo <= p.f_hz <= hi
           and abs(p.f_hz - f0) > res_hz]
    every = grid(lo, hi, FINE_Q, model.res) if lo < hi else np.zeros(0)
    near = {id(p): np.abs(every - p.f_hz) <= 2 * p.width_hz + 2 * res_hz for p in own}
    tried = np.any(list(near.values()), axis=0) if near else np.zeros(every.size, bool)
    q0 = float(model.modal.q[k])
    broad = f0 / q0 > res_hz  # its peak may stand out of no element
    tried |= broad
    if not tried.any():
        return []
    profile = res.profile(k, unit, every[tried])
    scale = every.size / int(tried.sum())
    out = []
    for p in own:
        j, i = profile.best(near[id(p)][tried], _qs(profile.q, p, res_hz))
        f, a, drop = profile.f_hz[i], profile.amplitude[j, i], profile.drop[j, i]
        if (drop >= least and abs(f - f0) > res_hz
                and 1 / MOST_AMPLITUDE <= a < MOST_AMPLITUDE):
            out.append(Candidate(k, float(f), float(profile.q[j]), float(a), float(drop),
                                 tuple(x * scale for x in profile.paths), p.f_hz))
    if broad:  # anywhere in its reach, about as broad as the model has it
        ok_q = (profile.q >= q0 / Q_SPREAD) & (profile.q <= q0 * Q_SPREAD)
        j, i = profile.best(np.ones(profile.f_hz.size, dtype=bool),
                            ok_q if ok_q.any() else np.ones(profile.q.size, dtype=bool))
        f, a, drop = profile.f_hz[i], profile.amplitude[j, i], profile.drop[j, i]
        if (drop >= least and abs(f - f0) > res_hz
                and 1 / MOST_AMPLITUDE <= a < MOST_AMPLITUDE):
            out.append(Candidate(k, float(f), float(profile.q[j]), float(a), float(drop),
                                 tuple(profile.paths)))
    return out


def _elements(res: Residuals, model: PlantModel, k: int) -> NDArray[np.bool_]:
    """The elements (readbacks, drives) holding at least :data:`SHARE` of mode `k`'s
    whitened power at the measured bins."""
    power = np.sum(np.abs(res.G * model.closed_term(k)) ** 2, axis=0)
    total = float(power.sum())
    return power >= SHARE * total if total > 0 else np.zeros(power.shape, dtype=bool)


def _qs(qs: NDArray[np.float64], peak: Peak, res_hz: float) -> NDArray[np.bool_]:
    """The trial Qs a peak's width allows (:data:`Q_SPREAD`); every Q when none does."""
    q_peak = peak.f_hz / peak.width_hz
    ok = qs >= q_peak / Q_SPREAD
    if peak.width_hz > RESOLVED_BINS * res_hz:
        ok &= qs <= q_peak * Q_SPREAD
    return ok if ok.any() else np.ones(qs.size, dtype=bool)


HELD_BINS = 1.5
"""A peak within this many bins of a model mode that shows in its element is that mode where
the model has it: no other mode is moved onto it."""


def holders(res: Residuals, model: PlantModel, modes: Sequence[int], peaks: Sequence[Peak]
            ) -> list[tuple[float, int]]:
    """The modes of `modes` the data show where the model has them, each with its
    frequency: a peak within :data:`HELD_BINS` of it is in an element that shows it."""
    within = HELD_BINS * res.data.resolution_hz
    out = []
    for k in modes:
        f, shows = model.modal.modes[k].f_hz, _elements(res, model, k)
        if any(shows[p.element] and abs(p.f_hz - f) <= within for p in peaks):
            out.append((f, k))
    return out


def unheld(peaks: Sequence[Peak], held: Sequence[tuple[float, int]], k: int, res_hz: float
           ) -> list[Peak]:
    """The `peaks` mode `k` may be moved onto: all but those within :data:`HELD_BINS` of
    another mode `held` (:func:`holders`), in any element (one resonance seen in several
    readbacks). A model mode moved onto a peak its neighbour already explains would fit
    that peak's flank, not its own."""
    within = HELD_BINS * res_hz
    return [p for p in peaks if all(abs(p.f_hz - f) > within or j == k for f, j in held)]


def unshown(res: Residuals, model: PlantModel, modes: Sequence[int], peaks: Sequence[Peak],
            f_hz: float) -> list[int]:
    """Of `modes`, those within :data:`~twind.analysis.statespace.search.SHIFT` of `f_hz`
    that the data no longer show where the model has them (no peak within a bin of it in
    the elements that show it), nearest `f_hz` first: a mode in no model found there may be
    one of them moved."""
    out = []
    for k in modes:
        mode = model.modal.modes[k]
        if not mode.f_hz / SHIFT <= f_hz <= mode.f_hz * SHIFT:
            continue
        shows, r = _elements(res, model, k), res.data.resolution_hz
        if not any(shows[p.element] and abs(p.f_hz - mode.f_hz) <= r for p in peaks):
            out.append(k)
    return sorted(out, key=lambda k: abs(math.log(f_hz / model.modal.modes[k].f_hz)))


def assign(found: Sequence[Candidate], res_hz: float) -> list[Candidate]:
    """The candidates given out best first: each mode one place, each place (within its
    :func:`reach`) one mode."""
    taken: list[tuple[float, float]] = []
    out: dict[int, Candidate] = {}
    for c in sorted(found, key=lambda c: -c.drop):
        if c.mode in out or any(abs(c.f_hz - g) < r for g, r in taken):
            continue
        taken.append((c.f_hz, reach(c.f_hz, c.q, res_hz)))
        out[c.mode] = c
    return list(out.values())
