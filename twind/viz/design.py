"""Figures of excitation designs: ``twind excite --output``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure


def plot_coherence(design: Any, path: str | Path) -> Path:
    """One column per DOF: required and designed ASD (top), predicted coherence (bottom).

    Parameters
    ----------
    design : CoherenceDesign
    path : str or Path
        PNG to write.

    Returns
    -------
    Path
        The file written.
    """
    lo, hi = design.band
    n = len(design.dofs)
    fig = Figure(figsize=(5.0 * n, 6.5))
    axes = fig.subplots(2, n, sharex="col", squeeze=False)
    f = np.geomspace(lo / 10, hi * 10, 800)
    for j, d in enumerate(design.dofs.values()):
        top, bottom = axes[0, j], axes[1, j]
        top.loglog(d.f_hz, d.required_asd, ".", ms=3, label="required (bins)")
        top.loglog(f, d.asd(f), label=f"designed (RMS {d.rms:.3g})")
        top.axvspan(lo, hi, color="0.9", zorder=0)
        top.set_title(f"{design.optic} {d.dof}_EXC -> IN1 {', '.join(d.responses)}", fontsize=9)
        top.set_ylabel("EXC ASD / rtHz")
        top.legend(fontsize=8)
        top.grid(True, which="both", alpha=0.3)
        bottom.semilogx(d.f_hz, d.coherence, ".", ms=3, label="predicted (Hann bins, true)")
        bottom.axhline(design.target, color="C3", ls="--", label=f"target {design.target:g}")
        bottom.axhline(design.design_coherence, color="C2", ls=":",
                       label=f"designed for {design.design_coherence:.3f}")
        bottom.set_ylim(0, 1.02)
        bottom.set_xlabel("frequency (Hz)")
        bottom.set_ylabel("coherence")
        bottom.legend(fontsize=8, loc="lower left")
        bottom.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path


def plot_information(design: Any, path: str | Path) -> Path:
    """Tone amplitudes per DOF, and the predicted uncertainties against white noise's.

    Parameters
    ----------
    design : InformationDesign
        As :func:`~twind.analysis.design.information.design_information` returns it.
    path : path
        The image file to write (its suffix picks the format, e.g. ``.png``).

    Returns
    -------
    Path
        `path`.
    """
    fig = Figure(figsize=(8, 7))
    top, bottom = fig.subplots(2, 1)
    for i, dof in enumerate(design.tones):
        top.stem(design.tones[dof], design.amps[dof], label=dof, linefmt=f"C{i}-",
                 markerfmt=f"C{i}o", basefmt=" ").markerline.set_markersize(4)
    top.set_xscale("log")
    top.set_xlabel("frequency [Hz]")
    top.set_ylabel("tone amplitude (peak)")
    top.legend()
    top.set_title(f"{design.optic}: D-optimal multisines, det(Cov) {design.gain:.1f}x smaller "
                  "than white noise")
    x = np.arange(len(design.params))
    white = np.sqrt(np.diag(design.covariance_white))
    bottom.bar(x - 0.2, 100 * white, 0.4, label="white noise, equal RMS")
    bottom.bar(x + 0.2, 100 * design.sigma, 0.4, label="this design")
    bottom.set_yscale("log")
    bottom.set_xticks(x, design.params, rotation=30, fontsize=8)
    bottom.set_ylabel(f"predicted sigma [%] in {design.duration_s:g} s")
    bottom.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    return Path(path)
