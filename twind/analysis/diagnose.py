"""``twind diagnose``: is the nominal model enough, where does it miss, which physics left out
explains the miss, and how much better the augmented model fits.

1. The nominal parameters are refitted (:func:`~twind.analysis.fit.fit`); the residuals are
   searched band by band with the false alarms of the whole search controlled
   (:func:`~twind.analysis.locate.locate`).
2. Every catalogue effect (:data:`~twind.model.effects.CATALOGUE`) is fitted
   together with the nominal parameters.  Its evidence is the drop in residual power,
   normalised by the residuals' own noise level (robust scale, F-distributed tails, bin
   correlation, as ``locate`` uses): a likelihood ratio with ``k`` parameters, its p-value
   (Bonferroni over the catalogue) and ``delta_bic = LR - k ln(N)``.
   Consistent: nothing located and no effect claimed.
3. The best effect (highest delta BIC) is reported with its parameters; claimed effects that
   fit the data about as well (likelihood ratio within :data:`EQUIVALENT_LR` of it, whatever
   their number of parameters) are named as not told apart by these data.  What the best
   augmented model still misses is reported as unexplained, where it lies.

``bounce_roll`` is fitted on more bins: its modes' bands, every bin whatever its coherence
(the BounceRoll notches leave little there), and from where a search over the modes'
frequencies put it (:mod:`twind.analysis.narrow`), which its p-value pays for.
The claims are scored on a corpus of concealed effects by ``twind bench --suite diagnose``
(:mod:`twind.analysis.corpus`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from scipy import stats

from twind.analysis import narrow
from twind.analysis.fit import (
    FIT_PARAMS,
    FitData,
    FitError,
    FitResult,
    fit,
    with_params,
)
from twind.analysis.locate import Located, _null_moments, locate
from twind.analysis.tf import TFSet
from twind.config import OpticConfig
from twind.errors import TwindError
from twind.model.effects import CATALOGUE, NARROW, model_names

ALPHA = 0.01
"""False-alarm probability of claiming an effect (over the whole catalogue): an effect is
claimed on its likelihood ratio's calibrated p-value (Bonferroni over the catalogue). BIC's
ln(n) per parameter (~9 for the ~5000 residuals of a 0.05 Hz measurement) would ask a
concealed coil imbalance for far more evidence than its p-value needs; delta BIC still ranks
the claimed effects."""
EQUIVALENT_LR = 6.0
"""Claimed effects whose likelihood ratio (``2 ln L``) is within this of the best one's are
not told apart by the data: less than "strong" evidence (a likelihood ratio of 20) against
them. Parameters are not charged here: an OSEM imbalance (three gain directions) that fits
as well as a one-parameter wire asymmetry is a rival the data leave standing, however BIC
ranks the two."""


class DiagnoseError(TwindError):
    """A diagnosis cannot be made or written."""


@dataclass
class EffectFit:
    """The nominal parameters refitted with one catalogue effect."""

    effect: str
    result: FitResult
    lr: float
    k: int
    p_value: float
    delta_bic: float
    equivalent: list[str] = field(default_factory=list)

    def to_json(self) -> dict:
        """One entry of ``effects`` in ``twind diagnose --json``."""
        names = CATALOGUE[self.effect].params
        got = dict(zip(self.result.names, zip(self.result.values, self.result.sigma,
                                              strict=True), strict=True))
        params, sigma = model_names(
            self.effect, {n: float(got[n][0]) for n in names},
            {n: None if math.isnan(got[n][1]) else float(got[n][1]) for n in names})
        return {"effect": self.effect, "params": params, "sigma": sigma,
                "delta_bic": self.delta_bic, "p_value": self.p_value,
                "equivalent": self.equivalent}


@dataclass
class Diagnosis:
    """What ``twind diagnose`` found."""

    nominal: FitResult
    located: list[Located]
    effects: list[EffectFit]
    final: FitResult
    unexplained: list[Located]
    separations: dict[tuple[str, str], tuple[str, str, float]] = field(default_factory=dict)
    p_values: dict[str, float] = field(default_factory=dict)
    """Every hypothesis fitted and its p-value, claimed or not: how near the data came to
    each explanation."""

    @property
    def consistent(self) -> bool:
        """True when the refitted nominal model explains the data: no band stands out and
        no catalogue effect earns its parameters."""
        return not self.located and not self.effects

    def to_json(self) -> dict:
        """The object of the issue, exactly."""
        nominal = {n: {"value": p["value"], "sigma": p["sigma"]}
                   for n, p in self.nominal.to_json()["params"].items()}
        return {"consistent": self.consistent,
                "chi2_nu_nominal": self.nominal.chi2_nu,
                "chi2_nu_final": self.final.chi2_nu,
                "located": [x.to_json() for x in self.located],
                "effects": [e.to_json() for e in self.effects],
                "unexplained": [{"element": x.element, "band_hz": list(x.band_hz)}
                                for x in self.unexplained],
                "nominal_params": nominal}

    def lines(self) -> list[str]:
        """A summary for a person."""
        out = [f"{self.nominal.optic}: nominal model refitted, chi2/nu "
               f"{self.nominal.chi2_nu:.3f}: "
               + ("consistent with the data" if self.consistent else
                  f"misses in {len(self.located)} band(s)")]
        for x in self.located[:8]:
            out.append(f"  {x.element:9s} {x.band_hz[0]:7.3g}-{x.band_hz[1]:<7.3g} Hz  "
                       f"{x.significance:5.1f} sigma, residual power x{x.excess:.2f}")
        for e in self.effects:
            params = ", ".join(
                f"{n} {{{', '.join(f'{k} {x:.3g}' for k, x in v.items())}}}"
                if isinstance(v, dict) else f"{n} {v:.4g}"
                for n, v in e.to_json()["params"].items())
            out.append(f"  effect {e.effect}: delta BIC {e.delta_bic:.1f}, p {e.p_value:.2g}"
                       f" ({params})" + (f"; not told apart from {', '.join(e.equivalent)}"
                                         if e.equivalent else ""))
        for (a, b), (dof, response, f) in self.separations.items():
            out.append(f"  to tell {a} from {b}: excite {dof} around {f:.3g} Hz and measure "
                       f"{response}/{dof} (where their predictions differ most against "
                       "the noise)")
        if not self.consistent and not self.effects:
            out.append("  no catalogue effect explains it")
        shown = {e.effect for e in self.effects}
        rest = sorted((p, e) for e, p in self.p_values.items() if e not in shown and p < 1)[:3]
        if rest:
            out.append("  nearest unclaimed: " + ", ".join(f"{e} p {p:.2g}" for p, e in rest))
        for x in self.unexplained[:8]:
            out.append(f"  unexplained: {x.element} {x.band_hz[0]:.3g}-{x.band_hz[1]:.3g} Hz")
        if not self.consistent:
            out.append(f"  chi2/nu {self.nominal.chi2_nu:.3f} -> {self.final.chi2_nu:.3f}")
        return out


MIN_COHERENCE = 0.0
"""Of the bins ``diagnose`` fits (:func:`diagnose`)."""


def diagnose(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig,
             params: Sequence[str] = FIT_PARAMS,
             min_coherence: float = MIN_COHERENCE) -> Diagnosis:
    """Diagnose measured TFs of `cfg`'s optic against its nominal model.

    Parameters
    ----------
    tfs : TFSet or sequence of TFSet
    cfg : OpticConfig
    params : sequence of str
        The nominal parameters refitted alongside every hypothesis.
    min_coherence : float
        Bins fitted (see :meth:`~twind.analysis.fit.FitData.from_tfset`): by default every
        response wherever the excitation reached the optic, coherent or not. An effect
        that couples one DOF into another lifts that element out of the noise only where
        it is large; spread thinly, it is plain only in the many incoherent bins together,
        whose errors are the noise's.

    Returns
    -------
    Diagnosis
    """
    nominal = fit(tfs, cfg, params, min_coherence)
    located = locate(tfs, cfg, nominal)
    # every hypothesis is tried even when no band stands out: an effect spread thinly over
    # many bands can be plain in its own fit and invisible band by band
    candidates = [c for c in (_try(tfs, cfg, params, e, nominal) for e in CATALOGUE) if c]
    claimed = sorted((c for c in candidates
                      if c.p_value < ALPHA),
                     key=lambda c: -c.delta_bic)
    p_values = {c.effect: c.p_value for c in candidates}
    if not claimed:
        return Diagnosis(nominal, located, [], nominal, located, p_values=p_values)
    best = claimed[0]
    best.equivalent = [c.effect for c in claimed[1:] if best.lr - c.lr < EQUIVALENT_LR]
    shown = [best] + [c for c in claimed[1:] if c.effect in best.equivalent]
    separations = {(best.effect, c.effect): separating_measurement(cfg, best.result, c.result)
                   for c in shown[1:]}
    return Diagnosis(nominal, located, shown, best.result, locate(tfs, cfg, best.result),
                     separations, p_values)


def separating_measurement(cfg: OpticConfig, a: FitResult, b: FitResult
                           ) -> tuple[str, str, float]:
    """The excitation (DOF, response, frequency) where two fitted hypotheses differ most
    relative to the IN1 noise: what to measure next to tell them apart."""
    import numpy as np

    from twind import DOFS
    from twind.analysis.fit import ClosedLoopModel
    from twind.excitation.coherence import in1_noise_asd

    f = np.logspace(-1, 2, 400)
    noise = in1_noise_asd(cfg, f)  # [f, response]
    ta, tb = (ClosedLoopModel(cfg, f, 0.0, r.effect)(r.as_dict()) for r in (a, b))
    contrast = np.abs(ta - tb) / np.maximum(noise[:, :, None], 1e-300)
    k, i, j = np.unravel_index(np.argmax(contrast), contrast.shape)
    return DOFS[j], DOFS[i], float(f[k])


def _try(tfs: TFSet | Sequence[TFSet], cfg: OpticConfig, params: Sequence[str], effect: str,
         nominal: FitResult) -> EffectFit | None:
    # from the refitted nominal parameters, holding those the data left free (a Q without
    # its resonance): a hypothesis fit would chase them again to its evaluation limit
    start = replace(cfg, sus=with_params(cfg.sus, nominal.identified()))
    free = [p for p in params if p not in nominal.unidentifiable]
    path = None  # a search's look-elsewhere measure
    try:
        if effect in NARROW:
            nominal, result, path = _try_narrow(tfs, start, free, nominal)
        else:
            result = fit(tfs, start, free, nominal.min_coherence, effect=effect)
    except FitError:
        return None
    # directions the effect adds that the data determine (a coil imbalance's common mode
    # is the coil strength's, its butterfly mode moves nothing: two of four gains count)
    k = result.rank - nominal.rank
    if k <= 0:
        return None
    lr = max(nominal.chi2 - result.chi2, 0.0) / _unit(nominal, tfs)
    n = 2 * nominal.bins
    if path is None:
        p = float(stats.chi2.sf(lr, k))
    else:  # the searched frequencies are paid for by the path, not as parameters
        searched = sum(math.isfinite(s) for n_, s in zip(result.names, result.sigma,
                                                         strict=True) if n_ in NARROW[effect])
        p = narrow.p_value(lr, k - searched, path)
    p = min(1.0, p * len(CATALOGUE))
    return EffectFit(effect, result, lr, k, p, lr - k * math.log(max(n, 1)))


def _try_narrow(tfs: TFSet | Sequence[TFSet], start: OpticConfig, free: list[str],
                nominal: FitResult) -> tuple[FitResult, FitResult, float]:
    """``bounce_roll``: the modes' bands join the data, every bin of them whatever its
    coherence, the nominal model is refitted on the same bins to compare against, and the
    fit starts where :func:`~twind.analysis.narrow.search` found the modes (searched on the
    first measurement). Returns the nominal fit, the effect's and the search's path."""
    first = tfs if isinstance(tfs, TFSet) else tfs[0]
    res = FitData.from_tfset(first, nominal.min_coherence).resolution_hz
    whole = narrow.bands(start, res)
    nominal = fit(tfs, start, free, nominal.min_coherence, whole=whole)
    data = FitData.from_tfset(first, nominal.min_coherence, whole=whole).span()
    found, path = narrow.search(data, start, nominal.as_dict(), free, _unit(nominal, tfs))
    result = fit(tfs, start, free, nominal.min_coherence, effect="bounce_roll",
                 effect_start=found, whole=whole)
    return nominal, result, path


def _unit(nominal: FitResult, tfs: TFSet | Sequence[TFSet]) -> float:
    """The drop in chi^2 one fitted parameter makes in pure noise: the null's per-bin power
    (robust scale, F tails of coherence-based errors) over independent bins (Hann
    neighbours are correlated)."""
    mu, _ = _null_moments(_averages(tfs))
    inflation = 1.0 + 2.0 * sum(r * r for r in nominal.bin_correlation)
    return 2 * nominal.noise_scale**2 * mu * inflation


def _averages(tfs: TFSet | Sequence[TFSet]) -> int:
    sets = [tfs] if isinstance(tfs, TFSet) else list(tfs)
    return min(t.averages for t in sets)


def write_report(diagnosis: Diagnosis, tfs: TFSet, cfg: OpticConfig, out: str | Path) -> Path:
    """Bode matrices before and after (measured, model, residual/sigma per bin), the JSON,
    and an HTML page with both, in directory `out` (created; existing files are refused)."""
    import html
    import json

    from twind.analysis.fit import plot_fit

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = ["nominal.png", "augmented.png", "diagnosis.json", "index.html", "diagnosis.rrd"]
    taken = [n for n in names if (out / n).exists()]
    if taken:
        msg = f"{out} already holds {', '.join(taken)}; twind does not overwrite reports"
        raise DiagnoseError(msg)
    plot_fit(tfs, cfg, diagnosis.nominal, str(out / "nominal.png"))
    if diagnosis.effects:
        plot_fit(tfs, cfg, diagnosis.final, str(out / "augmented.png"))
    (out / "diagnosis.json").write_text(json.dumps(diagnosis.to_json(), indent=1))
    _write_rrd(diagnosis, tfs, cfg, out / "diagnosis.rrd")
    images = "".join(f'<h2>{n[:-4]}</h2><img src="{n}" style="max-width:100%">'
                     for n in names[:2] if (out / n).exists())
    page = (f"<html><head><title>twind diagnose: {html.escape(diagnosis.nominal.optic)}"
            f"</title></head><body><h1>twind diagnose: {html.escape(diagnosis.nominal.optic)}"
            f"</h1><pre>{html.escape(chr(10).join(diagnosis.lines()))}</pre>{images}"
            '<p><a href="diagnosis.json">diagnosis.json</a>; <code>rerun diagnosis.rrd</code>'
            " (timeline frequency_hz)</p></body></html>")
    (out / "index.html").write_text(page)
    return out / "index.html"


def _write_rrd(diagnosis: Diagnosis, tfs: TFSet, cfg: OpticConfig, path: Path) -> None:
    """Per element: measured, nominal and augmented |IN1/EXC| (dB) and residuals / sigma."""
    import numpy as np

    from twind.analysis.fit import ClosedLoopModel, FitData
    from twind.viz.spectra import write_spectra_rrd

    data = FitData.from_tfset(tfs)
    f = data.frequency_hz
    fits = {"nominal": diagnosis.nominal}
    if diagnosis.effects:
        fits["augmented"] = diagnosis.final
    series = {}
    for label, result in fits.items():
        model = ClosedLoopModel.of(cfg, data, result.effect).for_data(data)
        pred = model(result.as_dict())
        for i, r in enumerate(data.responses):
            for j, e in enumerate(data.excited):
                used = data.mask[:, i, j]
                if not used.any():
                    continue
                base = f"diagnose/{r}_{e}"
                resid = np.abs(data.H[:, i, j] - pred[:, i, j]) / data.sigma[:, i, j]
                series[f"{base}/{label}_db"] = (f[used], 20 * np.log10(np.abs(pred[used, i, j])))
                series[f"{base}/{label}_residual_sigma"] = (f[used], resid[used])
                series[f"{base}/measured_db"] = (f[used], 20 * np.log10(np.abs(data.H[used, i, j])))
    write_spectra_rrd(path, f"twind diagnose {diagnosis.nominal.optic}", series)


def push(diagnosis: Diagnosis, connect: Sequence[str], ifo: str = "C1") -> str:
    """Give a running twin the diagnosis' final model: the refitted nominal parameters and,
    when one was claimed, the best effect; returns what was sent, for a person."""
    from twind.client import TwinClient

    final = diagnosis.final
    nominal = {n: v for n, v in final.identified().items() if n in FIT_PARAMS}
    q = {n[2:]: v for n, v in nominal.items() if n.startswith("Q_")}
    changes = {n: v for n, v in nominal.items() if not n.startswith("Q_")}
    effect = None
    if diagnosis.effects:
        best = diagnosis.effects[0]
        effect = {"id": best.effect, "values": {n: v for n, v in final.as_dict().items()
                                                if n in CATALOGUE[best.effect].params}}
    client = TwinClient(list(connect), ifo=ifo)
    try:
        client.params(final.optic, effect=effect, **changes, **({"Q": q} if q else {}))
    finally:
        client.close()
    return f"{len(changes) + len(q)} nominal parameter(s)" + (
        f" and {effect['id']}" if effect else "")
