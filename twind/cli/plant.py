"""``twind tf``, ``fit``, ``diagnose``, ``model response`` and ``simulate`` of an optic whose
plant is a state-space model (``model = "statespace"`` in its configuration)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from twind import __version__, strictjson
from twind.analysis.estimation.diaggui import read_transfers
from twind.analysis.statespace.diagnose import BUDGET_S, diagnose_plant
from twind.analysis.statespace.fit import fit_baseline
from twind.analysis.statespace.measurement import PlantSet, read_plant
from twind.config import load_config, optic_kinds
from twind.config.statespace import SENSOR_NOISE, StateSpaceOptic
from twind.cli.options import show, shown
from twind.errors import TwindError
from twind.simulation.statespace import truncation_error
from twind.viz.plant import plot_plant, write_plant_report
from twind.viz.plotting import bode_matrix


def statespace_optic(args: argparse.Namespace) -> StateSpaceOptic | None:
    """The state-space optic `args` name (``--config``, and ``--optic`` or the excitation
    in the first input when the file lists several), None for an SOS."""
    if not getattr(args, "config", None):
        return None
    kinds = optic_kinds(args.config)
    if set(kinds.values()) == {"sos"}:
        return None
    name = getattr(args, "optic", None)
    if name is None:
        name = next(iter(kinds)) if len(kinds) == 1 else _excited_optic(
            args.inputs, load_config(args.config, []).convention)
    if kinds.get(name) == "sos":
        return None
    return load_config(args.config, [name]).optics[name]


def _excited_optic(inputs: list[str], convention) -> str:  # noqa: ANN001 - Convention
    """The optic whose excitation the first diaggui input holds."""
    for t in read_transfers(_checked(inputs)[0]):
        parsed = convention.parse(t.denominator)
        if parsed:
            return parsed[0]
    msg = f"{inputs[0]}: no excitation named in {convention.ifo}'s convention; give --optic"
    raise TwindError(msg)


def _checked(inputs: list[str]) -> list[Path]:
    """The inputs: existing diaggui XML files."""
    paths = [Path(p) for p in inputs]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise TwindError(f"no such input: {', '.join(missing)}")
    if any(p.suffix.lower() != ".xml" for p in paths):
        msg = ("a state-space optic is measured from diaggui XML files (one per excitation); "
               f"got {', '.join(p.name for p in paths if p.suffix.lower() != '.xml')}")
        raise TwindError(msg)
    return paths


_SOS_ONLY = {"params": "an SOS's physical parameters are what --params chooses",
             "truth": "--truth holds a simulated SOS's parameters",
             "push": "a running twin takes an SOS's parameters; a state-space plant's are "
                     "not pushed"}


def _plant(args: argparse.Namespace, optic: StateSpaceOptic) -> PlantSet:
    """The measured plant of the inputs, in ``--band`` if given; a TwindError first for an
    option only an SOS takes."""
    for name, why in _SOS_ONLY.items():
        if getattr(args, name, None):
            raise TwindError(f"--{name}: {optic.name} is a state-space model; {why}")
    plant = read_plant(_checked(args.inputs), optic)
    return plant.band(*args.band) if getattr(args, "band", None) else plant


def tf(args: argparse.Namespace, optic: StateSpaceOptic) -> int:
    """``twind tf``: each readback per drive (per OUT in a closed loop), its coherence and
    the bins where it is coherent; a closed loop's controller OUT/IN2."""
    plant = _plant(args, optic)
    if args.json:
        strictjson.dump(plant.to_json(), sys.stdout)
        sys.stdout.write("\n")
    if args.output:
        if not args.output.lower().endswith(".png"):
            msg = (f"-o {args.output}: a state-space optic's TFs go to a .png; --json for "
                   "the numbers")
            raise TwindError(msg)
        written = plot_plant(plant, args.output)
        print(f"wrote {' and '.join(map(str, written))}", file=sys.stderr)
    if not args.json and not args.output:
        print("\n".join(_plant_lines(plant)))
    return 0


def _plant_lines(plant: PlantSet) -> list[str]:
    """A person's summary: the drives, the bins, where each element is coherent."""
    f = plant.frequency_hz
    out = [f"{plant.optic}: excited {', '.join(plant.channels[d] for d in plant.drives)}"
           + (" (closed loop: per unit of its OUT)" if plant.loops else " (open loop)")
           + f"; {f.size} bins from {f[0]:g} to {f[-1]:g} Hz, {plant.averages} averages",
           "coherent bins (neighbour-averaged coherence >= 0.5):"]
    mask = plant.coherent()
    for (name, runs), n in zip(plant.coherent_bands().items(),
                               mask.reshape(f.size, -1).sum(axis=0), strict=True):
        text = ", ".join(f"{a:.3g}-{b:.3g}" for a, b in runs[:6]) + (
            " ..." if len(runs) > 6 else "")
        out.append(f"  {name:40s} {int(n):6d}  {text or 'none'}")
    for module, loop in plant.loops.items():
        k = loop.controller()
        if k is not None:
            good = np.isfinite(k[0]) & (loop.coherence["OUT"] >= 0.5)
            out.append(f"  controller {module} OUT/IN2 measured in {int(good.sum())} coherent bins")
    out.append("--json for the numbers, -o FILE.png for a plot")
    return out


def fit(args: argparse.Namespace, optic: StateSpaceOptic) -> int:
    """``twind fit``: what the measurement adds to the model (calibrations, delay,
    low-pass), with sigmas."""
    plant = _plant(args, optic)
    result = fit_baseline(plant, optic, args.min_coherence).fit
    names = {f"g_{i}": f"calibration {r}" for i, r in enumerate(plant.readbacks)}
    names.update({f"g_d{j}": f"calibration {d}" for j, d in enumerate(plant.drives)})
    names.update(tau_s="delay_s", inv_lp_hz="inv_lowpass_hz", loops="other loops' gain")
    params = {names[n]: {"value": float(v), "sigma": result.error(n)}
              for n, v in zip(result.names, result.values, strict=True)}
    if args.json:
        strictjson.dump({"optic": optic.name, "params": params, "chi2_nu": result.chi2_nu,
                         "bins": result.bins, "noise_scale": result.noise_scale}, sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(f"{optic.name}: the model's calibrations, delay and low-pass fitted to "
          f"{result.bins} bins: chi2/nu {result.chi2_nu:.3g}")
    for name, p in params.items():
        sigma = "not determined" if p["sigma"] is None else f"+- {p['sigma']:.2g}"
        print(f"  {name:36s} {p['value']:12.5g} {sigma}")
    print("  (one drive's calibration is not separable from the readbacks': their products "
          "are what is fitted)")
    return 0


def diagnose(args: argparse.Namespace, optic: StateSpaceOptic) -> int:
    """``twind diagnose`` of a state-space optic."""
    plant = _plant(args, optic)
    result = diagnose_plant(plant, optic, budget_s=args.budget or BUDGET_S)
    show(result, args.json)
    if args.output:
        print(f"wrote {write_plant_report(result, args.output)}", file=sys.stderr)
    return 0


def response(args: argparse.Namespace, optic: StateSpaceOptic, f: np.ndarray) -> int:
    """``twind model response``: the model between its drives and readbacks (by default
    each damping loop's OUT to every loop's IN1), and its modes."""
    drives = (tuple(args.drives.split(",")) if args.drives
              else tuple(optic.loops) or tuple(optic.drives))
    readbacks = tuple(args.readbacks.split(",")) if args.readbacks else \
        tuple(f"{m}_IN1" for m in optic.loops) or tuple(optic.readbacks)
    unknown = [r for r in readbacks if r not in optic.readbacks]
    if unknown:
        msg = f"--readbacks {', '.join(unknown)}: not readbacks of {optic.source}"
        raise TwindError(msg)
    unknown = [d for d in drives if d not in optic.drives and d not in optic.loops]
    if unknown:
        msg = (f"--drives {', '.join(unknown)}: not TEST points or damping loops of "
               f"{optic.source}")
        raise TwindError(msg)
    modal = optic.modal(drives, readbacks)
    H = modal.response(f)
    if args.json:
        strictjson.dump({"about": f"twind model response of {optic.name} ({optic.source})",
                         "drives": list(drives), "readbacks": list(readbacks),
                         "frequency_hz": f.tolist(),
                         "response": {"re": H.real.tolist(), "im": H.imag.tolist()},
                         "modes": [{"f_hz": m.f_hz, "q": m.q, "label": m.label,
                                    "share": m.share} for m in modal.modes]}, sys.stdout)
        sys.stdout.write("\n")
        return 0
    path = Path(args.output or f"{optic.name}_response.png")
    bode_matrix(f, path, readbacks, drives, {"model": H}, per="drive",
                title=f"{optic.convention.ifo}:{optic.convention.system}-{optic.name}: "
                      f"state-space model ({Path(optic.model.source).name})",
                caption=f"model {shown(optic.model.source)}; twind {__version__}")
    print(f"wrote {path}")
    print(f"{len(modal.modes)} modes (modal form's condition {modal.condition:.2g}); label: "
          "the DOF that carries the largest share of each")
    for m in modal.modes:
        if f[0] <= m.f_hz <= f[-1]:
            print(f"  {m.f_hz:9.4f} Hz  Q {m.q:9.3g}  {m.label or '-':6s} ({m.share:.2f})")
    return 0


def simulate(args: argparse.Namespace, optic: StateSpaceOptic) -> int:
    """``twind simulate`` of a state-space optic: its engine with the damping loops closed,
    each loop's EXC driven by white noise, run as fast as it goes in ``--block`` steps; the
    channels' RMS and the speed."""
    if args.record:
        msg = ("--record: a state-space optic's session is recorded from the bus: twind serve "
               "--config ... --record DIR")
        raise TwindError(msg)
    engine = optic.engine(max_hz=args.max_hz, seed=args.seed,
                          noise=dict.fromkeys(optic.readbacks, SENSOR_NOISE))
    if engine.dropped:
        err = truncation_error(engine.full, engine.modal, min(args.max_hz / 3, 100.0))
        print(f"{engine.dropped} modes above {args.max_hz:g} Hz dropped (static part kept): "
              f"the response up to {min(args.max_hz / 3, 100.0):g} Hz differs by at most "
              f"{100 * err:.2g} % of each element's largest")
    n, per = int(round(args.duration * engine.rate)), max(1, int(round(args.block * engine.rate)))
    if n < 1:
        raise TwindError(f"--duration {args.duration:g}: not one sample at {engine.rate:g} Hz")
    rng = np.random.default_rng([args.seed, 1])  # not the engine's noise stream
    power: dict[str, float] = {}
    wall = 0.0
    for start in range(0, n, per):
        k = min(per, n - start)
        exc = {f"{m}_EXC": rng.standard_normal(k) for m in engine.loops}
        t0 = time.perf_counter()
        block = engine.step(k, exc)
        wall += time.perf_counter() - t0
        for name, x in block.channels.items():
            power[name] = power.get(name, 0.0) + float(np.sum(x * x))
    for name, total in power.items():
        print(f"{optic.channel(name):40s} rms {math.sqrt(total / n):11.4g}")
    print(f"simulated {args.duration:g} s of {optic.name} ({engine.ad.shape[0]} states, "
          f"loops closed: {', '.join(engine.closed) or 'none'}) in {wall:.3f} s: "
          f"{args.duration / wall:.1f} x real time")
    return 0
