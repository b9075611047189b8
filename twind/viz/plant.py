"""Figures and the report of a plant given as a state-space model: each measured element as
diaggui draws it (magnitude with its errors, phase, coherence), the model and the refitted
model beside it, and the page ``twind diagnose -o`` writes."""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from twind import __version__, strictjson
from twind.analysis.statespace.diagnose import PlantDiagnosis
from twind.analysis.statespace.measurement import PlantSet
from twind.errors import TwindError
from twind.viz.plotting import MIN_COHERENCE, phase
from twind.viz.report import bands, html_page, number, report_dir, table

COLUMNS = 3
"""Elements side by side in a figure."""
FONT = 10


def plot_elements(f: NDArray[np.float64], H: NDArray[np.complex128],
                  sigma: NDArray[np.float64], coherence: NDArray[np.float64],
                  good: NDArray[np.bool_], rows: Sequence[str], cols: Sequence[str],
                  path: str | Path, models: Mapping[str, NDArray[np.complex128]] | None = None,
                  title: str = "", notes: Sequence[str] = (),
                  marks: Sequence[tuple[float, str]] = ()) -> Path:
    """Each element with trusted bins: magnitude (errors on the trusted bins), phase and
    coherence, with the `models` as lines.

    Parameters
    ----------
    f : ndarray
        Frequencies (Hz).
    H, sigma, coherence : ndarray, shape (nf, rows, cols)
        The measurement, its standard error and coherence.
    good : ndarray of bool, shape (nf, rows, cols)
        The bins trusted (coherent); the others are drawn faded.
    rows, cols : sequence of str
        The readbacks and drives.
    path : path
        The PNG.
    models : mapping of str to ndarray, optional
        Named model curves at `f`.
    title : str
    notes : sequence of str
        Lines printed under the title: what the figure shows (files, resolution,
        averages).
    marks : sequence of (float, str)
        Vertical lines (frequency, label): a mode moved, from where to where.

    Returns
    -------
    Path
    """
    models = models or {}
    cells = [(i, j) for i in range(len(rows)) for j in range(len(cols)) if good[:, i, j].any()]
    if not cells:
        msg = "no element has a coherent bin to draw"
        raise TwindError(msg)
    used = good.any(axis=(1, 2))
    lo, hi = f[used].min(), f[used].max()
    view = (f >= lo / 1.5) & (f <= hi * 1.5) & (f > 0)
    ncol = min(COLUMNS, len(cells))
    nrow = math.ceil(len(cells) / ncol)
    head = 0.9 + 0.2 * len(notes)
    width, height = 5.2 * ncol, 6.4 * nrow + head
    fig = Figure(figsize=(width, height))
    grid = fig.add_gridspec(nrow, ncol, top=1 - head / height, bottom=0.5 / height,
                            left=0.9 / width, right=1 - 0.2 / width, hspace=0.3, wspace=0.32)
    for n, (i, j) in enumerate(cells):
        inner = grid[divmod(n, ncol)].subgridspec(3, 1, height_ratios=[3, 2, 1.2], hspace=0.08)
        mag = fig.add_subplot(inner[0])
        ph = fig.add_subplot(inner[1], sharex=mag)
        co = fig.add_subplot(inner[2], sharex=mag)
        _element(mag, ph, co, f[view], H[view, i, j], sigma[view, i, j],
                 coherence[view, i, j], good[view, i, j],
                 {k: v[view, i, j] for k, v in models.items()})
        mag.set_title(f"{rows[i]} / {cols[j]}", fontsize=FONT)
        for x, label in marks:
            for ax in (mag, ph, co):
                ax.axvline(x, color="C3", lw=0.6, ls=":")
            mag.text(x, 1.0, label, transform=mag.get_xaxis_transform(), fontsize=FONT - 1,
                     color="C3", rotation=90, va="top", ha="right")
        for ax in (mag, ph):
            ax.tick_params(labelbottom=False)
        co.set_xlabel("frequency [Hz]", fontsize=FONT)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper right", fontsize=FONT, frameon=False,
               bbox_to_anchor=(1 - 0.2 / width, 1 - 0.45 / height), ncol=2)
    fig.suptitle(title, x=0.9 / width, y=1 - 0.15 / height, ha="left", fontsize=FONT + 2)
    for k, line in enumerate(notes):
        fig.text(0.9 / width, 1 - (0.55 + 0.2 * k) / height, line, fontsize=FONT - 1)
    path = Path(path)
    fig.savefig(path, dpi=90)
    return path


def _element(mag, ph, co, f, h, s, g2, good, models) -> None:  # noqa: ANN001 - axes
    """One element's three panels."""
    mag.errorbar(f[good], np.abs(h[good]), yerr=s[good], fmt=".", ms=2.5, elinewidth=0.5,
                 color="0.1", label="measured (coherent)")
    mag.plot(f[~good], np.abs(h[~good]), ".", ms=2, color="0.6", alpha=0.35,
             label="measured (not coherent)")
    ph.plot(f[good], np.degrees(np.angle(h[good])), ".", ms=2.5, color="0.1")
    ph.plot(f[~good], np.degrees(np.angle(h[~good])), ".", ms=2, color="0.6", alpha=0.35)
    top = max((np.abs(m).max() for m in models.values()), default=0.0)
    for k, (name, m) in enumerate(models.items()):
        there = np.abs(m) > 1e-12 * max(top, 1e-300)
        if not there.any():
            continue
        mag.plot(f, np.where(there, np.abs(m), np.nan), color=f"C{k}", lw=1.1, label=name)
        ph.plot(f, phase(np.where(there, m, np.nan)), color=f"C{k}", lw=1.1)
        if not np.abs(m).max() > 1e-9 * max(top, 1e-300):
            mag.text(0.5, 0.05, f"{name}: zero here", transform=mag.transAxes, fontsize=FONT - 1,
                     color=f"C{k}", ha="center")
    co.plot(f, g2, ".", ms=2, color="0.3")
    mag.set(xscale="log", yscale="log")
    seen = np.abs(h[np.isfinite(h) & (np.abs(h) > 0)])
    if seen.size:  # the data's range: a model far below it is drawn to the panel's foot
        mag.set_ylim(np.percentile(seen, 0.5) / 30, seen.max() * 3)
    mag.set_ylabel("magnitude", fontsize=FONT)
    ph.set(ylim=(-180, 180), yticks=[-180, -90, 0, 90, 180])
    ph.set_ylabel("phase [deg]", fontsize=FONT)
    co.set(ylim=(0, 1.05))
    co.set_ylabel("coherence", fontsize=FONT)
    for ax in (mag, ph, co):
        ax.grid(True, which="both", alpha=0.3)
        ax.tick_params(labelsize=FONT - 1)


def measurement_notes(plant: PlantSet) -> list[str]:
    """What a figure of `plant` shows: its channels, files, resolution and averages, and
    which twind drew it."""
    drives = ", ".join(plant.channels.get(d, d) for d in plant.drives)
    return [f"excited {drives}; {len(plant.readbacks)} readbacks; "
            f"{plant.resolution_hz:.4g} Hz bins, {plant.averages} averages (Hann)",
            f"{', '.join(Path(s).name for s in plant.sources)}; "
            + (f"GPS from {plant.gps:.0f}; " if plant.gps else "") + f"twind {__version__}"]


def plot_plant(plant: PlantSet, path: str | Path) -> list[Path]:
    """``twind tf -o`` of a state-space optic: the measured plant, and each closed loop's
    controller (OUT/IN2) beside it (``_controller``).

    Returns
    -------
    list of Path
    """
    good = plant.coherent()
    title = f"{plant.optic}: measured plant (readback per drive" + (
        "; a closed loop's per unit of its OUT" if plant.loops else "") + ")"
    out = [plot_elements(plant.frequency_hz, plant.H, plant.sigma, plant.coherence, good,
                         plant.readbacks, plant.drives, path, title=title,
                         notes=measurement_notes(plant))]
    loops = [(m, c) for m, lp in plant.loops.items() if (c := lp.controller()) is not None]
    if loops:
        k = np.stack([c[0] for _, c in loops], axis=1)[:, :, None]
        s = np.stack([c[1] for _, c in loops], axis=1)[:, :, None]
        g2 = np.stack([np.minimum(plant.loops[m].coherence["OUT"],
                                  plant.loops[m].coherence["IN2"]) for m, _ in loops],
                      axis=1)[:, :, None]
        ok = np.isfinite(k) & (g2 >= MIN_COHERENCE)
        path = Path(path)
        to = path.with_name(f"{path.stem}_controller{path.suffix}")
        out.append(plot_elements(plant.frequency_hz, k, s, g2, ok, [m for m, _ in loops],
                                 ["OUT/IN2"], to,
                                 title=f"{plant.optic}: the controller as measured (OUT/IN2)",
                                 notes=measurement_notes(plant)))
    return out


def plot_diagnosis(d: PlantDiagnosis, path: str | Path) -> Path:
    """Measured, the model (its calibrations, delay and low-pass fitted) and the refitted
    model (with the changes claimed), element by element, each moved mode marked."""
    data = d.data
    lo = int(np.searchsorted(d.plant.frequency_hz, data.frequency_hz[0]))
    g2 = d.plant.coherence[lo:lo + data.frequency_hz.size]
    models = {"model (calibrations, delay, low-pass fitted)":
              d.model(d.nominal.nuisance, d.nominal.effects)}
    if d.effects:
        models["refitted (changes claimed)"] = d.model(d.final.nuisance, d.final.effects)
    marks = []
    for c in d.chosen:
        if c.effect.family == "mode_frequency":
            m = d.modal.modes[c.effect.target[0]]
            f = m.f_hz * math.exp(d.final.own(c.effect)["log_f"])
            marks.append((f, f"{m.f_hz:.3g} -> {f:.4g} Hz"))
    return plot_elements(data.frequency_hz, data.H, data.sigma, g2, data.mask,
                         data.responses, data.excited, path, models,
                         title=f"{d.optic.name}: measured, the model and the model refitted",
                         notes=measurement_notes(d.plant), marks=marks)


def write_plant_report(d: PlantDiagnosis, out: str | Path) -> Path:
    """``twind diagnose -o DIR`` of a state-space optic: ``diagnosis.png``,
    ``diagnosis.json`` and ``index.html`` (the verdict, the changes, the modes, what the
    measurement adds, the bands), never over an earlier report.

    Returns
    -------
    Path
        The page.
    """
    out = report_dir(out, ["diagnosis.png", "diagnosis.json", "index.html"], TwindError)
    plot_diagnosis(d, out / "diagnosis.png")
    (out / "diagnosis.json").write_text(strictjson.dumps(d.to_json(), indent=1))
    (out / "index.html").write_text(_page(d))
    return out / "index.html"


def _page(d: PlantDiagnosis) -> str:
    """The report's HTML."""
    optic = html.escape(d.optic.name)
    changes = [(c.effect.key(), c.rival_of and f"rival of {c.rival_of}" or
                ("chosen" + (" (partial)" if c.partial else "")), number(c.p_value, 2),
                number(c.delta_bic, 4), d.describe(c)) for c in d.effects]
    modes = [(f"{m['f_hz']:.4g}", f"{m['q']:.3g}", f"{m['label']} ({m['share']:.2f})",
              _measured(m["measured"])) for m in d.modes_table()]
    nuisance = [(k, number(v["value"], 4), number(v["sigma"], 2)) for k, v in d.nuisance().items()]
    parts = [f"<h1>twind diagnose: {optic} (state-space model)</h1>",
             f'<p class="verdict" id="verdict">{html.escape(d.summary())}</p>',
             f"<p>{html.escape(' '.join(measurement_notes(d.plant)))}</p>",
             f"<p>The model: {html.escape(d.optic.model_source or d.optic.source)}</p>",
             "<h2>Changes</h2>",
             table("changes", ("change", "verdict", "p-value", "delta BIC", "reading"), changes)
             if changes else "<p>none claimed</p>",
             "<h2>The model's modes in the measured band</h2>",
             table("modes", ("model f (Hz)", "model Q", "label (share)", "measured"), modes),
             "<h2>What the measurement adds to the model</h2>",
             table("nuisance", ("parameter", "value", "sigma"), nuisance),
             "<h2>Where the model misses</h2>", bands("located", d.located, "nowhere"),
             "<h2>Unexplained by the final model</h2>",
             bands("unexplained", d.unexplained, "nothing"),
             '<h2>Measured, model and refitted</h2><img src="diagnosis.png" alt="figure">',
             '<p><a href="diagnosis.json">diagnosis.json</a></p>']
    return html_page(f"twind diagnose: {optic}", parts)


def _measured(m: dict | None) -> str:
    if m is None:
        return "as modelled (no change claimed)"
    if "f_hz" in m:
        q = number(m["q"], 3) if m.get("q_resolved") else "not resolved (narrower than a bin)"
        return f"{number(m['f_hz'], 5)} ± {number(m['f_hz_sigma'], 2)} Hz, Q {q}"
    return f"amplitude {number(m['amplitude'], 3)} ± {number(m['amplitude_sigma'], 2)}"
