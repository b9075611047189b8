"""``twind excite`` and ``twind campaign``: design the excitation of the DOFs of an optic.

Modes (``--mode``):

- ``coherence``: the noise ASD that makes ``IN1`` coherent with ``EXC`` (>= ``--coherence``)
  in every bin of ``--band`` at ``--bw`` resolution and ``--averages`` averages, given the
  model and its noise, within the ``_EXC`` limits (:mod:`twind.analysis.design.coherence`).

- ``information``: D-optimal multisines (Pintelon-Schoukens) maximising det(Fisher) of
  ``--params`` at ``--rms`` per DOF over ``--duration`` seconds of measurement, with the
  uncertainty they predict next to white noise's (:mod:`twind.analysis.design.information`).

Each mode returns a design with ``summary()`` (lines for a person), ``to_json()`` and a plot;
a new mode is one more entry in :data:`MODES`. ``twind campaign`` designs, injects,
records and fits in rounds until a target (:mod:`twind.commissioning.campaign`).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from twind import strictjson
from twind.analysis.identification.params import FIT_PARAMS, param_value, with_params
from twind.config import load_config
from twind.errors import TwindError
from twind.excitation.checks import Limits
from twind.analysis.design.coherence import design_coherent
from twind.analysis.design.information import design_information
from twind.commissioning.campaign import BusTwin, LocalTwin, Twin, plot_rounds, run_campaign
from twind.commissioning.measurement import DRIFT
from twind.viz.design import plot_coherence, plot_information


def cmd_excite(args: argparse.Namespace) -> int:
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


def _coherence(args: argparse.Namespace, optic: Any, ifo: str, limits: Any) -> Any:

    return design_coherent(optic, args.dof or ["POS"], tuple(args.band), target=args.coherence,
                           averages=args.averages, bw=args.bw, limits=limits,
                           responses="all" if args.all_responses else "own",
                           confidence=args.confidence, ifo=ifo, seed=args.seed)


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


def cmd_campaign(args: argparse.Namespace) -> int:
    """``twind campaign``: run rounds until the target; print each round and the result."""

    nominal = load_config(args.config, [args.optic]).select([args.optic])[0]
    if args.connect:
        twin: Twin = BusTwin(args.connect, args.optic, args.ifo, args.update, args.workdir)
        truth = None
    else:
        truth = {k: param_value(nominal.sus, k) * (1 + args.drift * (f - 1))
                 for k, f in DRIFT.items()}
        twin = LocalTwin(replace(nominal, sus=with_params(nominal.sus, truth)), args.seed)
    rounds = run_campaign(nominal, twin, args.dof or ["POS", "PIT", "YAW"], tuple(args.band),
                          args.rms, args.period, args.averages, args.params or FIT_PARAMS,
                          args.target, args.max_rounds)
    last = rounds[-1]
    if args.json:
        out = {"rounds": [{"round": r.index, "twin_s": r.twin_s,
                           "relative_sigma": r.relative_sigma} for r in rounds],
               "fit": last.fit.to_json(), "reached": last.worst[1] <= args.target}
        if truth:
            out["truth"] = truth
        print(strictjson.dumps(out))
    else:
        for r in rounds:
            name, worst = r.worst
            print(f"round {r.index}: twin {r.twin_s / 60:.1f} min, chi2/nu "
                  f"{r.fit.chi2_nu:.3f}, worst {name} {100 * worst:.3g} %")
        print("\n".join(last.fit.lines()))
        if truth:
            print(f"  (fitted - truth) / sigma: {last.fit.pulls(truth)}")
        print(("reached" if last.worst[1] <= args.target else "did not reach")
              + f" {100 * args.target:g} % in {last.twin_s / 60:.1f} min of twin time")
    if args.output:
        print(f"wrote {plot_rounds(rounds, args.target, args.output)}", file=sys.stderr)
    return 0
