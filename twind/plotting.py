"""Bode-matrix figures (matplotlib, Agg backend, imported only when a plot is asked for)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from twind.model.compare import ModelComparison


def bode_matrix(f_hz: NDArray[np.float64], curves: Mapping[str, NDArray[np.complex128]],
                path: str | Path, labels: Sequence[str], title: str = "") -> Path:
    """Write a grid of magnitude and phase panels, one per matrix element.

    Parameters
    ----------
    f_hz : ndarray
        Frequencies (Hz).
    curves : mapping of str to ndarray, shape (nf, n, n)
        Named responses drawn over each other.
    path : str or Path
        PNG to write.
    labels : sequence of str
        Row and column names (response / excitation).
    title : str
        Figure title.

    Returns
    -------
    Path
        The file written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(labels)
    fig, axes = plt.subplots(2 * n, n, figsize=(3.2 * n, 4.2 * n), sharex=True, squeeze=False)
    drawn = np.zeros((n, n), dtype=bool)
    for name, h in curves.items():
        for i in range(n):
            for j in range(n):
                mag = np.abs(h[:, i, j])
                if not np.any(mag > 1e-12 * np.abs(h).max()):
                    continue  # zero by symmetry; round-off is not worth a curve
                drawn[i, j] = True
                axes[2 * i, j].loglog(f_hz, mag, label=name)
                axes[2 * i + 1, j].semilogx(f_hz, np.degrees(np.angle(h[:, i, j])), label=name)
    for i in range(n):
        for j in range(n):
            axes[2 * i, j].set_title(f"{labels[i]} / {labels[j]}", fontsize=9)
            if not drawn[i, j]:
                axes[2 * i, j].text(0.5, 0.5, "zero", ha="center", va="center",
                                    transform=axes[2 * i, j].transAxes, color="gray")
            axes[2 * i + 1, j].set_ylim(-180, 180)
            axes[2 * i + 1, j].set_yticks([-180, -90, 0, 90, 180])
            for ax in axes[2 * i : 2 * i + 2, j]:
                ax.grid(True, which="both", alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("frequency [Hz]")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


MIN_COHERENCE = 0.5
"""Points below this coherence are drawn faded: their phase is mostly noise."""


def bode_transfers(transfers: Sequence, path: str | Path, title: str = "") -> Path:
    """Measured transfer functions (:class:`twind.analysis.diaggui.Transfer`) as a Bode plot.

    Magnitude with its standard error, phase and coherence share the frequency axis; points
    below :data:`MIN_COHERENCE` are faded.

    Returns
    -------
    Path
        The PNG written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (mag, phase, coh) = plt.subplots(3, 1, figsize=(8, 8), sharex=True,
                                          gridspec_kw={"height_ratios": [3, 2, 1]})
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
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_freeswing(result, sen: NDArray[np.float64], rate_hz: float,  # noqa: ANN001
                   path: str | Path) -> Path:
    """A free-swinging check (:class:`twind.analysis.freeswing.FreeSwing`) as a figure: the
    OSEM spectra with the modes found and the model's, and both input matrices as maps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import signal

    from twind import DOFS
    from twind.model.osem import OSEMS

    fig = plt.figure(figsize=(11, 7))
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
    plt.close(fig)
    return path


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
    # Agg canvas directly: no pyplot global state, no display needed
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(14, 11))
    FigureCanvasAgg(fig)
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
