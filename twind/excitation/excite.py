"""``twind excite``: design the excitation of one or more DOFs of an optic.

Modes (``--mode``):

- ``coherence``: the noise ASD that makes ``IN1`` coherent with ``EXC`` (>= ``--coherence``)
  in every bin of ``--band`` at ``--bw`` resolution and ``--averages`` averages, given the
  model and its noise, within the ``_EXC`` limits (:mod:`twind.excitation.coherence`).

- ``information``: D-optimal multisines (Pintelon-Schoukens) maximising det(Fisher) of
  ``--params`` at ``--rms`` per DOF over ``--duration`` seconds of measurement, with the
  uncertainty they predict next to white noise's (:mod:`twind.excitation.information`).

Each mode returns a design with ``summary()`` (lines for a person), ``to_json()`` and a plot;
a new mode is one more entry in :data:`MODES`.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from twind import strictjson
from twind.analysis.identification.params import FIT_PARAMS
from twind.config import load_config
from twind.errors import TwindError
from twind.excitation.checks import Limits
from twind.excitation.coherence import design_coherent
from twind.excitation.information import design_information


def excite_main(args: argparse.Namespace) -> int:
    """``twind excite``: print the design (or its JSON), optionally plot it."""

    for name in ("rms", "peak"):
        value = getattr(args, name)
        if value is not None and not (value > 0 and math.isfinite(value)):
            msg = f"--{name} must be a positive number, got {value}"
            raise TwindError(msg)
    twin = load_config(args.config, [args.optic])
    limits = Limits(peak=twin.service.exc_peak if args.peak is None else args.peak,
                    rms=twin.service.exc_rms if args.rms is None else args.rms)
    optic = twin.select([args.optic])[0]
    design = MODES[args.mode](args, optic, twin.ifo, limits)
    if args.output:
        path = PLOTS[args.mode](design, args.output)
    if args.json:
        print(strictjson.dumps(design.to_json()))
    else:
        print("\n".join(design.summary()))
        if args.output:
            print(f"wrote {path}")
    return 0


# -- coherence ------------------------------------------------------------------------------------
def _coherence(args: argparse.Namespace, optic: Any, ifo: str, limits: Any) -> Any:

    return design_coherent(optic, args.dof or ["POS"], tuple(args.band), target=args.coherence,
                           averages=args.averages, bw=args.bw, limits=limits,
                           responses="all" if args.all_responses else "own",
                           confidence=args.confidence, ifo=ifo, seed=args.seed)


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


# -- information ----------------------------------------------------------------------------------
INFORMATION_RMS = 10.0
"""Default RMS of an information-mode design (um or urad at EXC; the twin allows 30)."""


def _information(args: argparse.Namespace, optic: Any, ifo: str, limits: Any) -> Any:

    rms = INFORMATION_RMS if args.rms is None else args.rms
    design = design_information(optic, args.dof or ["POS", "PIT", "YAW"], tuple(args.band),
                                rms, args.duration, args.period, args.params or FIT_PARAMS)
    rate = optic.sus.sample_rate_hz
    for dof in design.tones:
        peak = design.peak(dof, rate)
        if peak > limits.peak:
            msg = (f"{dof}: the multisine of RMS {rms:g} peaks at {peak:.4g}, above the "
                   f"peak limit {limits.peak:g}; lower --rms")
            raise TwindError(msg)
    return design


def plot_information(design: Any, path: str | Path) -> Path:
    """Tone amplitudes per DOF, and the predicted uncertainties against white noise's.

    Parameters
    ----------
    design : InformationDesign
        As :func:`~twind.excitation.information.design_information` returns it.
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


MODES: dict[str, Callable[[argparse.Namespace, Any, str, Any], Any]] = {
    "coherence": _coherence,
    "information": _information,
}
"""Mode name -> ``design(args, optic_cfg, ifo, limits)``."""

PLOTS: dict[str, Callable[[Any, str | Path], Path]] = {
    "coherence": plot_coherence,
    "information": plot_information,
}
"""Mode name -> ``plot(design, path)``."""
