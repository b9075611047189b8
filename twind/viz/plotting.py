"""Bode-matrix figures of models and measurements, a fit's before and after, a ringdown's
spectra (matplotlib, Agg backend, imported only when a plot is asked for)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray
from scipy import signal

from twind import DOFS, OSEMS, __version__
from twind.analysis.prediction import FitCurves
from twind.channels import UNITS

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from twind.model.compare import ModelComparison


MIN_COHERENCE = 0.5
"""Points of a diaggui transfer function below this coherence are drawn faded: their phase
is mostly noise."""


@dataclass(frozen=True)
class Measured:
    """Measured points of a transfer-function matrix, as a Bode matrix draws them.

    Attributes
    ----------
    h : ndarray, shape (nf, rows, cols)
    sigma : ndarray, optional
        Standard error of the real and imaginary parts (error bars; residuals in sigma).
    good : ndarray of bool, optional
        The points to trust (those driven by the excitation, or those a fit used); the
        others are faded, with no error bar and no residual. Default: all.
    """

    h: NDArray[np.complex128]
    sigma: NDArray[np.float64] | None = None
    good: NDArray[np.bool_] | None = None

    def trusted(self, i: int, j: int) -> NDArray[np.bool_]:
        """The trusted points of element (i, j): finite, and good if :attr:`good` is given.

        Parameters
        ----------
        i : int
            Row: the response DOF's index.
        j : int
            Column: the excitation DOF's index.

        Returns
        -------
        numpy.ndarray of bool
            One per frequency.
        """
        finite = np.isfinite(self.h[:, i, j])
        return finite if self.good is None else finite & self.good[:, i, j]


def dof_unit(dof: str) -> str:
    """The unit of a DOF's signals in the damping loop (:data:`twind.channels.UNITS`), as
    printed: µm, µrad; another model's signals are in its own units (a.u.)."""
    return UNITS[dof].replace("u", "µ") if dof in UNITS else "a.u."


FONT = {"title": 11, "label": 10, "tick": 9, "note": 9}
"""Font sizes (points) of the Bode figures: read at 100 dpi, as diaggui's are on a screen."""


def bode_matrix(f_hz: NDArray[np.float64], path: str | Path, rows: Sequence[str],
                cols: Sequence[str], models: Mapping[str, NDArray[np.complex128]] | None = None,
                measured: Mapping[str, Measured] | None = None, per: str | None = None,
                residuals: bool = False, title: str = "",
                coherence: NDArray[np.float64] | None = None, caption: str = "") -> Path:
    """Write a Bode matrix: per element (response row / excitation column) magnitude and
    phase, the coherence beneath them as diaggui draws it, and with `residuals` the
    measured minus each model over sigma.

    Parameters
    ----------
    f_hz : ndarray
        Frequencies (Hz); every axis spans these and no more.
    path : str or Path
        PNG to write.
    rows, cols : sequence of str
        The DOFs of the responses and of the excitations.
    models : mapping of str to ndarray, shape (nf, rows, cols), optional
        Named model curves. An element that is zero in a model (its largest magnitude below
        1e-9 of the model's largest: zero by symmetry, round-off left) is drawn as zero: a
        dashed line along the panel's floor, named.
    measured : mapping of str to Measured, optional
        Named measurements: points with error bars, faded where incoherent.
    per : str, optional
        The unit of the denominator ("ct" for a plant IN1/OUT); default the excited DOF's.
    residuals : bool
        A last panel per element: ``|measured - model| / sigma`` of the first measurement
        against every model.
    title : str
    coherence : ndarray, shape (nf, rows, cols), optional
        The first measurement's coherence: a panel under each magnitude and phase.
    caption : str
        A line under the panels: the channels, GPS span, estimator and the like.

    Returns
    -------
    Path
    """
    models, measured = models or {}, measured or {}
    kinds = ["mag", "phase"] + ["coh"] * (coherence is not None) + ["res"] * residuals
    ratios = {"mag": 3, "phase": 2, "coh": 1.2, "res": 1.6}
    width = 3.6 * len(cols)
    n_labels = len(models) + 2 * len(measured)
    legend = 0.3 * -(-n_labels // 3)  # inches: three entries a row
    height = (0.75 * sum(ratios[k] for k in kinds) + 0.5) * len(rows) + 0.9 + legend
    fig = Figure(figsize=(width, height))
    axes = fig.subplots(len(kinds) * len(rows), len(cols), sharex=True, squeeze=False,
                        gridspec_kw={"height_ratios": [ratios[k] for k in kinds] * len(rows)})
    for i, r in enumerate(rows):
        for j, c in enumerate(cols):
            cell = dict(zip(kinds, axes[len(kinds) * i: len(kinds) * (i + 1), j], strict=True))
            _element(cell, f_hz, models, measured, coherence, i, j)
            cell["mag"].set_title(f"{r} / {c}", fontsize=FONT["title"])
            cell["mag"].set_ylabel(f"|{r}/{c}| [{dof_unit(r)}/{per or dof_unit(c)}]",
                                   fontsize=FONT["label"])
    for ax in axes[-1]:
        ax.set_xlabel("frequency [Hz]", fontsize=FONT["label"])
    for ax in axes.flat:
        ax.tick_params(labelsize=FONT["tick"])
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].set_xlim(f_hz[f_hz > 0].min(), f_hz.max())  # shared by every panel
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=min(len(labels), 3) or 1,
               fontsize=FONT["label"], frameon=False,
               bbox_to_anchor=(0.5, 1 - 0.45 / height))  # above the panels
    fig.suptitle(title, y=1 - 0.2 / height, fontsize=FONT["title"] + 1)
    if caption:
        fig.text(0.01, 0.12 / height, caption, fontsize=FONT["note"], color="0.3")
    # fixed margins (inches): tight_layout measures every tick label, seconds for a matrix
    fig.subplots_adjust(left=1.0 / width, right=1 - 0.15 / width, bottom=0.75 / height,
                        top=1 - (0.75 + legend) / height, wspace=0.45, hspace=0.35)
    path = Path(path)
    fig.savefig(path, dpi=100)
    return path


def _element(cell: Mapping[str, Axes], f: NDArray, models: Mapping[str, NDArray],
             measured: Mapping[str, Measured], coherence: NDArray | None, i: int,
             j: int) -> None:
    """Element (i, j) of every model and measurement on its panels."""
    zero = _models(cell, f, models, i, j)
    drawn = _measured(cell, f, measured, i, j) or len(zero) < len(models)
    if "res" in cell and measured and next(iter(measured.values())).sigma is not None:
        _residuals(cell["res"], f, next(iter(measured.values())), models, i, j)
    if "coh" in cell:
        _coherence(cell["coh"], f, coherence[:, i, j], next(iter(measured.values()), None),
                   i, j)
    every = len(zero) == len(models)
    if zero and drawn:
        _zero(cell["mag"], zero, every)
    elif zero:
        cell["mag"].text(0.5, 0.5, f"{'model' if every else ', '.join(zero)}: 0",
                         ha="center", va="center", transform=cell["mag"].transAxes,
                         color="0.3", fontsize=FONT["note"])
        cell["mag"].set_yticks([])
    cell["phase"].set_ylabel("phase [deg]", fontsize=FONT["label"])
    cell["phase"].set(ylim=(-180, 180), yticks=[-180, -90, 0, 90, 180])


def _zero(ax: Axes, names: Sequence[str], every: bool) -> None:
    """Models that are zero in this element, drawn as zero: a dashed line just above the
    floor of the log-magnitude panel, named beside it."""
    ax.autoscale_view()
    lo, hi = ax.get_ylim()
    ax.set_ylim(lo / (hi / lo) ** 0.08, hi)
    ax.axhline(lo, color="0.3", ls="--", lw=1.2)
    ax.text(0.02, 0.07, f"{'model' if every else ', '.join(names)}: 0", color="0.3",
            transform=ax.transAxes, fontsize=FONT["note"], va="bottom")


def _coherence(ax: Axes, f: NDArray, g2: NDArray, m: Measured | None, i: int, j: int) -> None:
    """The coherence of element (i, j), faded where the measurement is not trusted."""
    good = np.isfinite(g2) if m is None else m.trusted(i, j)
    ax.semilogx(f[good], g2[good], ".", ms=2, color="0.15")
    ax.semilogx(f[~good], g2[~good], ".", ms=2, color="0.15", alpha=0.2)
    ax.set(ylim=(0, 1.05), yticks=[0, 0.5, 1])
    ax.set_ylabel("coherence", fontsize=FONT["label"])


def _models(cell: Mapping[str, Axes], f: NDArray, models: Mapping[str, NDArray], i: int,
            j: int) -> list[str]:
    """Each model's element (i, j) on the cell's magnitude and phase; the names of those
    that are zero there."""
    zero = []
    for k, (name, h) in enumerate(models.items()):
        mag, top = np.abs(h[:, i, j]), np.abs(h).max()
        if not mag.max() > 1e-9 * top:
            zero.append(name)  # zero by symmetry: round-off is not worth a curve
            continue
        there = mag > 1e-13 * top  # points where the model is exactly zero: not drawn
        cell["mag"].loglog(f, np.where(there, mag, np.nan), color=f"C{k}", lw=1.2, label=name)
        cell["phase"].semilogx(f, phase(np.where(there, h[:, i, j], np.nan)), color=f"C{k}",
                               lw=1.2)
    return zero


def phase(h: NDArray[np.complex128]) -> NDArray[np.float64]:
    """Phase in degrees, broken (NaN) where it wraps, so that no line crosses the panel."""
    deg = np.degrees(np.angle(h))
    deg[1:][np.abs(np.diff(deg)) > 180] = np.nan
    return deg


def _measured(cell: Mapping[str, Axes], f: NDArray, measured: Mapping[str, Measured], i: int,
              j: int) -> bool:
    """Each measurement's element (i, j): coherent points with error bars, the others
    faded; True if any drawn."""
    for k, (name, m) in enumerate(measured.items()):
        h, good = m.h[:, i, j], m.trusted(i, j)
        color = f"{0.15 + 0.25 * k:.2f}"
        err = None if m.sigma is None else m.sigma[good, i, j]
        cell["mag"].errorbar(f[good], np.abs(h[good]), yerr=err, fmt=".", ms=3,
                             elinewidth=0.5, color=color, label=name)
        cell["mag"].plot(f[~good], np.abs(h[~good]), ".", ms=3, color=color, alpha=0.2,
                         label=f"{name} where its EXC does not drive it (faded, no error bar)")
        cell["phase"].plot(f[good], np.degrees(np.angle(h[good])), ".", ms=3, color=color)
        cell["phase"].plot(f[~good], np.degrees(np.angle(h[~good])), ".", ms=3, color=color,
                           alpha=0.2)
        cell["mag"].set(xscale="log", yscale="log")
    return bool(measured)


def _residuals(ax: Axes, f: NDArray, m: Measured, models: Mapping[str, NDArray], i: int,
               j: int) -> None:
    """``|measured - model| / sigma`` of element (i, j) against every model, coherent
    points only, with the 3-sigma line."""
    good = m.trusted(i, j)
    if not good.any():
        ax.text(0.5, 0.5, "no bin fitted", ha="center", va="center", transform=ax.transAxes,
                color="gray", fontsize=FONT["note"])
    for k, h in enumerate(models.values()):
        z = np.abs(m.h[good, i, j] - h[good, i, j]) / m.sigma[good, i, j]
        ax.semilogx(f[good], z, ".", ms=2, color=f"C{k}")
    ax.axhline(3, color="k", lw=0.5, ls="--")
    ax.set_ylim(0, None if good.any() else 5)
    ax.set_ylabel("|res.| / sigma", fontsize=FONT["label"])


def bode_transfers(transfers: Sequence, path: str | Path, title: str = "") -> Path:
    """Measured transfer functions as a Bode plot.

    Magnitude with its standard error, phase and coherence share the frequency axis; points
    below :data:`MIN_COHERENCE` are faded.

    Parameters
    ----------
    transfers : sequence of Transfer
        As :mod:`twind.analysis.estimation.diaggui` reads them from a diaggui file.
    path : path
        The PNG to write.
    title : str
        The figure's title; by default the kinds of measurement and their averages.

    Returns
    -------
    Path
        The PNG written.
    """
    fig = Figure(figsize=(8, 8))
    mag, phase, coh = fig.subplots(3, 1, sharex=True, gridspec_kw={"height_ratios": [3, 2, 1]})
    for t in transfers:
        f, h, s = t.frequency_hz, t.tf, t.sigma()
        good = t.coherence >= MIN_COHERENCE
        line = mag.errorbar(f[good], np.abs(h[good]), yerr=s[good], fmt=".-", ms=3,
                            capsize=2, label=t.name)[0]
        color = line.get_color()
        mag.plot(f[~good], np.abs(h[~good]), ".", color=color, alpha=0.25)
        phase.plot(f[good], np.degrees(np.angle(h[good])), ".-", ms=3, color=color)
        phase.plot(f[~good], np.degrees(np.angle(h[~good])), ".", color=color, alpha=0.25)
        coh.plot(f, t.coherence, ".-", ms=3, color=color)
    mag.set(xscale="log", yscale="log", ylabel="magnitude [B/A]")
    phase.set(ylabel="phase [deg]", ylim=(-180, 180), yticks=[-180, -90, 0, 90, 180])
    coh.set(ylabel="coherence", ylim=(0, 1.05), xlabel="frequency [Hz]")
    coh.axhline(MIN_COHERENCE, color="gray", lw=0.8, ls="--")
    for ax in (mag, phase, coh):
        ax.grid(True, which="both", alpha=0.3)
    mag.legend(fontsize=8)
    kinds = sorted({f"{t.kind}, {t.averages} averages" for t in transfers})
    fig.suptitle(title or f"measured transfer functions ({'; '.join(kinds)})")
    starts = [t.gps for t in transfers if t.gps]
    files = sorted({Path(t.source).name for t in transfers})
    fig.text(0.01, 0.005, f"{', '.join(files)}; "
             + (f"GPS from {min(starts):.0f}; " if starts else "") + f"twind {__version__}",
             fontsize=FONT["note"], color="0.3")
    fig.tight_layout(rect=(0, 0.02, 1, 0.97))
    path = Path(path)
    fig.savefig(path, dpi=90)
    return path


def plot_freeswing(result, sen: NDArray[np.float64], rate_hz: float,  # noqa: ANN001
                   path: str | Path) -> Path:
    """A free-swinging check as a figure: the OSEM spectra (0.3-1.5 Hz) with the modes found
    and the model's, and both input matrices as maps.

    Parameters
    ----------
    result : FreeSwing
        As :mod:`twind.analysis.identification.freeswing` finds it.
    sen : numpy.ndarray, shape (5, n)
        The OSEM readings (um), UL, UR, LL, LR, SIDE.
    rate_hz : float
        Their sample rate (Hz).
    path : path
        The PNG to write.

    Returns
    -------
    Path
        The PNG written.
    """
    fig = Figure(figsize=(11, 7))
    spec = fig.add_subplot(2, 1, 1)
    q = max(1, int(rate_hz / 16))
    low = signal.decimate(sen - sen.mean(axis=1, keepdims=True), q, ftype="fir", axis=1) \
        if q > 1 else sen
    f, p = signal.welch(low, fs=rate_hz / q, nperseg=min(low.shape[1], int(400 * rate_hz / q)),
                        axis=1)
    keep = (f > 0.3) & (f < 1.5)
    for name, row in zip(OSEMS, p, strict=True):
        spec.semilogy(f[keep], np.sqrt(row[keep]), lw=0.8, label=name)
    for d in DOFS:
        spec.axvline(result.frequency_hz[d], color="k", lw=0.8)
        spec.axvline(result.model_hz[d], color="r", lw=0.8, ls=":")
        spec.text(result.frequency_hz[d], spec.get_ylim()[1], f" {d}", va="top", fontsize=8)
    spec.set(xlabel="frequency [Hz]", ylabel="OSEM ASD [um/rtHz]",
             title=f"{result.optic}: free-swinging OSEM spectra; modes found (black), the "
                   "model's (red, dotted)")
    spec.legend(fontsize=8, ncol=5)
    for k, (m, title) in enumerate(((result.input_matrix, "input matrix: diagonalising"),
                                    (result.configured, "configured"))):
        ax = fig.add_subplot(2, 2, 3 + k)
        scaled = m / np.abs(result.configured).max(axis=1, keepdims=True)
        im = ax.imshow(scaled, cmap="RdBu_r", vmin=-1.2, vmax=1.2)
        ax.set(xticks=range(len(OSEMS)), xticklabels=OSEMS, yticks=range(len(DOFS)),
               yticklabels=DOFS, title=title)
        for (i, j), x in np.ndenumerate(scaled):
            ax.text(j, i, f"{x:.2f}", ha="center", va="center", fontsize=7)
    fig.colorbar(im, ax=fig.axes[1:], shrink=0.8, label="over the configured row's largest")
    path = Path(path)
    fig.savefig(path, dpi=90)
    return path


def plot_violin_lines(report, path: str | Path,  # noqa: ANN001 - a LineReport
                      sen: NDArray[np.float64] | None = None, rate_hz: float | None = None,
                      most: int = 4) -> Path:
    """Each violin line as a commissioner looks at it: the spectrum of the OSEM that sees it
    best around the line (when the readings are given), and its ringdown, the amplitude of
    every segment against time with the fitted decay and the model's; the strongest `most`
    lines, one row each.

    Parameters
    ----------
    report : LineReport
        As :func:`twind.analysis.identification.lines.violin_lines` finds it.
    path : str or Path
        The figure to write.
    sen : ndarray, shape (5, n), optional
        The OSEM readings (um) the lines were found in, UL, UR, LL, LR, SIDE.
    rate_hz : float, optional
        Their rate.
    most : int
        Lines drawn at most.

    Returns
    -------
    Path
        The file written.
    """
    lines = report.found[:most]
    spectra = sen is not None and rate_hz is not None
    fig = Figure(figsize=(13 if spectra else 11, 1 + 3.2 * max(1, len(lines))),
                 layout="constrained")
    grid = fig.add_gridspec(max(1, len(lines)), 3 if spectra else 1)
    psd: dict[str, tuple[NDArray, NDArray]] = {}  # per reading, once
    for k, line in enumerate(lines):
        if spectra:
            if line.reading not in psd:
                psd[line.reading] = signal.welch(sen[OSEMS.index(line.reading)], fs=rate_hz,
                                                 nperseg=int(round(rate_hz)))
            _line_spectrum(fig.add_subplot(grid[k, 0]), line, *psd[line.reading])
        ax = fig.add_subplot(grid[k, 1:] if spectra else grid[k, 0])
        t = line.times_s
        ax.semilogy(t, np.abs(line.segments), ".", ms=2, label=f"|amplitude| in {line.reading}")
        ax.semilogy(t, line.amplitude * np.exp(-line.decay_per_s * t), "r",
                    label=f"fit: {line.text('um')}")
        near = report.nearest(line)
        model = ""
        if near is not None:
            model = f"; the model's nearest: segment {near[0]}'s n={near[1]}"
            ax.semilogy(t, line.amplitude * np.exp(-np.pi * near[2] / near[3] * t), "k--",
                        lw=0.8, label=f"the model's Q, {near[3]:.3g}")
        ax.set(xlabel="time from the first segment [s]", ylabel="um",
               title=f"line at {line.frequency_hz:.4f} Hz ringing down{model}")
        ax.legend(fontsize=8)
    if not lines:
        fig.text(0.5, 0.5, report.lines()[0], ha="center", va="center", wrap=True)
    fig.suptitle(f"{report.optic}: violin lines (twind {__version__})", fontsize=10)
    path = Path(path)
    fig.savefig(path, dpi=90)
    return path


def _line_spectrum(ax: Axes, line, f: NDArray, p: NDArray) -> None:  # noqa: ANN001
    """The ASD `p` (at frequencies `f`, 1 Hz bins as the lines were found) within 10 Hz of
    `line`."""
    keep = np.abs(f - line.frequency_hz) <= 10.0
    ax.semilogy(f[keep], np.sqrt(p[keep]), lw=0.8)
    ax.axvline(line.frequency_hz, color="r", lw=0.6, ls=":")
    ax.set(xlabel="frequency [Hz]", ylabel=f"{line.reading} ASD [um/rtHz]",
           title=f"{line.reading} spectrum, 1 Hz bins")


def plot_comparison(cmp: "ModelComparison", path: str | Path) -> Path:
    """Write a 4x4 Bode-magnitude matrix of both models' admittances to a PNG.

    Parameters
    ----------
    cmp : ModelComparison
    path : str or Path
        Output PNG file.

    Returns
    -------
    Path
        The file written.
    """
    fig = Figure(figsize=(14, 11))
    axes = fig.subplots(4, 4, sharex=True)
    zero = cmp.structurally_zero()
    worst = cmp.max_relative_difference()
    for i, row in enumerate(cmp.dofs):
        for j, col in enumerate(cmp.dofs):
            _panel(axes[i, j], cmp, i, j, zero[i, j], worst[i, j])
            axes[i, j].set_title(f"{row} / {col}", fontsize=9)
        axes[3, i].set_xlabel("frequency (Hz)")
    axes[0, 0].legend(fontsize=8, loc="lower left")
    fig.suptitle("Admittance |displacement / generalised force|: analytical (T000134) vs geometric "
                 "rigid body\n(max relative magnitude difference excluding ±10 % around resonances;"
                 " POS/PIT off-diagonal differs in sign only)", fontsize=10)
    # fixed margins: constrained layout costs seconds on a 4x4 grid
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.05, top=0.91, wspace=0.25, hspace=0.3)
    out = Path(path)
    fig.savefig(out, dpi=100)
    return out


def _panel(ax: "Axes", cmp: "ModelComparison", i: int, j: int, zero: bool, worst: float) -> None:
    ax.set_xscale("log")
    ax.set_xlim(0.1, 10)
    if zero:
        ax.text(0.5, 0.5, "0 in both models", ha="center", va="center", transform=ax.transAxes,
                color="0.5")
        ax.set_yticks([])
        return
    ax.loglog(cmp.f_hz, np.abs(cmp.admittance_analytical[:, i, j]), "C0-", lw=1.2, label="analytical")
    ax.loglog(cmp.f_hz, np.abs(cmp.admittance_geometric[:, i, j]), "C1--", lw=1.2, label="geometric")
    ax.text(0.97, 0.95, f"max |Δ| = {100 * worst:.2g} %", ha="right", va="top",
            transform=ax.transAxes, fontsize=8)
    ax.grid(True, which="both", alpha=0.3)


def plot_fit(fit: FitCurves, path: str) -> str:
    """A fit as a Bode matrix: per element, measured ``IN1/EXC`` (the bins the fit used with
    their errors, the others faded) with the model it started from and the fitted one, the
    coherence, and the residual of each in units of the measurement's sigma (what the fit
    minimised).

    Parameters
    ----------
    fit : FitCurves
        The measurement and the models, as :func:`twind.analysis.prediction.fit_curves`
        computes them.
    path : str
        The PNG to write.

    Returns
    -------
    str
        `path`.
    """
    title = f"{fit.optic} IN1/EXC, {fit.model} model: chi2/nu {fit.chi2_nu:.3g} after the fit"
    bode_matrix(fit.frequency_hz, path, fit.responses, fit.excited, fit.curves,
                {"measured": Measured(fit.H, fit.sigma, fit.used)}, residuals=True,
                title=title, coherence=fit.coherence,
                caption=f"{fit.caption}; twind {__version__}")
    return path
