"""Bode-matrix figures (matplotlib, Agg backend, imported only when a plot is asked for)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray


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
