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

from twind import DOFS, strictjson
from twind.errors import TwindError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``twind excite --dof POS [--dof PIT ...] --band LO HI [...]``."""
    parser.add_argument("--mode", choices=tuple(MODES), default="coherence",
                        help="what the excitation is designed for (default coherence)")
    parser.add_argument("--config", help="config file (default: the 40m file shipped with twind)")
    parser.add_argument("--optic", default="ETMX", help="the optic (default ETMX)")
    parser.add_argument("--dof", action="append", choices=DOFS, metavar="DOF",
                        help=f"DOF to excite, one of {', '.join(DOFS)}; repeat for several "
                             "(each measured on its own); default POS")
    parser.add_argument("--band", type=float, nargs=2, metavar=("LO", "HI"), required=True,
                        help="frequency band (Hz) that must be coherent")
    parser.add_argument("--coherence", type=float, default=0.7,
                        help="coherence to reach in every bin of the band (default 0.7)")
    parser.add_argument("--averages", type=int, default=10,
                        help="non-overlapping averages of the measurement (default 10)")
    parser.add_argument("--bw", type=float, default=0.01,
                        help="frequency resolution of the measurement, Hz (default 0.01)")
    parser.add_argument("--confidence", type=float, default=0.95,
                        help="probability that a bin's estimate reaches the coherence "
                             "(sets the margin for the estimator's scatter; default 0.95)")
    parser.add_argument("--all-responses", action="store_true",
                        help="make the IN1 of every --dof coherent with each excitation, "
                             "not only the excited DOF's own")
    parser.add_argument("--rms", type=float, help="RMS limit at EXC (default: the twin's)")
    parser.add_argument("--peak", type=float, help="peak limit at EXC (default: the twin's)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the noise request")
    parser.add_argument("--params", nargs="+", metavar="NAME",
                        help="information: parameters to inform (default: all nine)")
    parser.add_argument("--duration", type=float, default=110.0,
                        help="information: seconds of measurement per DOF")
    parser.add_argument("--period", type=float, default=20.0,
                        help="information: multisine period (s); measure with bw = 1/period")
    parser.add_argument("--json", action="store_true", help="print the design as JSON")
    parser.add_argument("-o", "--output", metavar="FILE.png",
                        help="plot of the required and designed ASD and the coherence")


def excite_main(args: argparse.Namespace) -> int:
    """``twind excite``: print the design (or its JSON), optionally plot it."""
    from twind.config import load_config
    from twind.excitation.checks import Limits

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
    from twind.excitation.coherence import design_coherent

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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = design.band
    n = len(design.dofs)
    fig, axes = plt.subplots(2, n, figsize=(5.0 * n, 6.5), sharex="col", squeeze=False)
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
    plt.close(fig)
    return path


# -- information ----------------------------------------------------------------------------------
INFORMATION_RMS = 10.0
"""Default RMS of an information-mode design (um or urad at EXC; the twin allows 30)."""


def _information(args: argparse.Namespace, optic: Any, ifo: str, limits: Any) -> Any:
    from twind.analysis.fit import FIT_PARAMS
    from twind.excitation.information import design_information

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
    """Tone amplitudes per DOF, and the predicted uncertainties against white noise's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 7))
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
    plt.close(fig)
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
