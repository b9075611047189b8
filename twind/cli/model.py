"""``twind model response``, ``twind model compare``, ``twind model config`` and
``twind simulate``."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from twind import DOFS, __version__, strictjson
from twind.channels import block_channels
from twind.cli import plant as statespace
from twind.cli.options import shown
from twind.config import default_optic, load_config
from twind.config.draft import DC_HZ, Draft, write_config
from twind.errors import TwindError
from twind.model.compare import compare_models
from twind.model.violin import violin_modes
from twind.recording.writer import SessionWriter
from twind.simulation.engine import Engine
from twind.timeutil import now_gps
from twind.viz.plotting import bode_matrix, plot_comparison


def _frequencies(args: argparse.Namespace) -> np.ndarray:
    if args.freqs:
        try:
            f = np.array([float(x) for x in args.freqs.split(",")])
        except ValueError:
            msg = f"--freqs: expected comma-separated numbers, got {args.freqs!r}"
            raise TwindError(msg) from None
    else:
        if not 0 < args.fmin < args.fmax or args.n < 2:
            msg = f"need 0 < --fmin < --fmax and --n >= 2, got {args.fmin}, {args.fmax}, {args.n}"
            raise TwindError(msg)
        f = np.geomspace(args.fmin, args.fmax, args.n)
    if np.any(f <= 0) or not np.all(np.isfinite(f)):
        msg = "frequencies must be positive and finite"
        raise TwindError(msg)
    return f


def _complex(a: np.ndarray) -> dict[str, list]:
    return {"re": a.real.tolist(), "im": a.imag.tolist()}


def cmd_model_response(args: argparse.Namespace) -> int:
    """Frequency responses of one optic's loop, as golden_tf.json or a Bode-matrix PNG."""

    cfg = _optic(args)
    f = _frequencies(args)
    if cfg.kind == "statespace":
        return statespace.response(args, cfg, f)
    violins = violin_modes(cfg.mechanics())
    at = np.array([f_hz for _, f_hz, _ in violins])
    if not args.freqs and at.size:  # a Q of millions: each drawn at its peak
        f = np.union1d(f, at[(at > f[0]) & (at < f[-1])])
    r = cfg.loop().responses(f)
    keys = ("plant_IN1_per_OUT", "controller_diag", "closed_loop_IN1_per_EXC",
            "closed_loop_IN2_per_EXC")
    if args.json:
        out = {"about": f"twind model response of {cfg.name} ({cfg.model} model, {cfg.source})",
               "dofs": list(DOFS), "frequency_hz": f.tolist()}
        out.update({k: _complex(r[k]) for k in keys})
        out["uncoupled_frequencies_hz"] = cfg.sus.uncoupled_frequencies_hz()
        strictjson.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0

    path = Path(args.output or f"{cfg.name}_response.png")
    plant = path.with_name(f"{path.stem}_plant{path.suffix}")
    name = f"C1:SUS-{cfg.name} ({cfg.model} model)"
    caption = f"model {shown(cfg.source)}; twind {__version__}"
    bode_matrix(f, path, DOFS, DOFS, {"IN1/EXC": r["closed_loop_IN1_per_EXC"],
                                      "IN2/EXC": r["closed_loop_IN2_per_EXC"]},
                title=f"{name}: closed loop", caption=caption)
    bode_matrix(f, plant, DOFS, DOFS, {"IN1/OUT": r["plant_IN1_per_OUT"]}, per="ct",
                title=f"{name}: plant", caption=caption)
    print(f"wrote {path} and {plant}")
    for f_hz, q in cfg.closed_loop_modes:
        print(f"closed-loop mode {f_hz:.3f} Hz, Q {q:.1f}")
    for name, f_hz, q in violins:
        print(f"violin mode {name}: {f_hz:.3f} Hz, Q {q:.3g}")
    return 0


def _optic(args: argparse.Namespace):  # noqa: ANN202 - OpticConfig or StateSpaceOptic
    """The optic ``--optic`` names (default: the file's only one, else ETMX)."""
    name = args.optic or default_optic(args.config)
    return load_config(args.config, [name]).optics[name]


def cmd_model_config(args: argparse.Namespace) -> int:
    """A starting configuration of an optic from its state-space model's names; what it
    maps, what it could not, and the DC check of each drive's collocated readback."""
    draft = write_config(args.model, args.optic, args.output, naming=args.naming,
                         ifo=args.ifo, system=args.system)
    print("\n".join(_draft_lines(draft, args.output)))
    return 0


def _draft_lines(draft: Draft, output: str) -> list[str]:
    """A person's summary of a written configuration."""
    out = [f"wrote {output}: {len(draft.drives)} drives, {len(draft.readbacks)} readbacks, "
           f"{len(draft.shapes)} DOFs labelling modes, {len(draft.loops)} damping loops "
           "(their controllers twind's), each line commented with the model's signal and "
           f"the rule of {draft.naming.site}'s naming that made it",
           f"check the mapping: each drive, its collocated readback and the model's response "
           f"there at {DC_HZ:g} Hz. {draft.naming.check}"]
    width = max(len(c.drive) for c in draft.checks) if draft.checks else 0
    for c in draft.checks:
        out.append(f"  {c.drive:{width}s} -> {c.readback:22s} {c.response:10.3g}   "
                   f"({c.input} -> {c.output})")
    out.append(f"not mapped (no rule names them): inputs {', '.join(draft.unmapped_inputs) or 'none'}")
    out.append(f"  outputs {', '.join(draft.unmapped_outputs) or 'none'}")
    out.append(f"next: twind model response --config {output}  (the modes, labelled), then "
               f"twind diagnose --config {output} FILES")
    return out


def cmd_model_compare(args: argparse.Namespace) -> int:
    """Geometric rigid-body model against the analytical model for one optic."""

    cfg = _optic(args)
    if cfg.kind == "statespace":
        msg = f"{cfg.name} is a state-space model: it has no geometric and analytical models to compare"
        raise TwindError(msg)
    cmp = compare_models(cfg.sus, np.geomspace(0.1, 10, 400))
    for dof, pct in cmp.eigen_difference_pct().items():
        print(f"{dof:5s} analytical {cmp.eigen_analytical_hz[dof]:8.5f} Hz  "
              f"geometric {cmp.eigen_geometric_hz[dof]:8.5f} Hz  ({pct:+.3f} %)")
    path = plot_comparison(cmp, args.output)
    print(f"wrote {path}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """Run the twin as fast as it can; print per-channel RMS and the speed reached."""

    chosen = args.optics or default_optic(args.config)
    twin = load_config(args.config, chosen)
    optics = twin.select(chosen)
    if any(o.kind == "statespace" for o in optics):
        if len(optics) != 1:
            msg = "simulate runs one state-space optic at a time: choose it with --optics"
            raise TwindError(msg)
        return statespace.simulate(args, optics[0])
    for name in ("duration", "block"):
        if not getattr(args, name) > 0:
            msg = f"--{name} must be positive, got {getattr(args, name)}"
            raise TwindError(msg)
    rate = optics[0].sus.sample_rate_hz
    n_block = int(round(args.block * rate))
    n_total = int(round(args.duration * rate))
    if n_block < 1 or n_total < 1:
        msg = f"--duration and --block must each hold at least one sample at {rate:g} Hz"
        raise TwindError(msg)
    engine = Engine([o.loop() for o in optics], {o.name: o.noise for o in optics},
                    seed=args.seed, rate_hz=rate)
    buf = engine.new_block(n_block)
    writer = None
    if args.record:
        writer = SessionWriter(args.record, twin.ifo, now_gps())
    sums = {p: 0.0 for p in ("exc", "in1", "in2", "out", "sen", "lsc")}
    t0 = time.perf_counter()
    try:
        done = 0
        while done < n_total:
            n = min(n_block, n_total - done)
            block = engine.step(n, out=buf if n == n_block else None)
            for point in sums:
                x = getattr(block, point)
                sums[point] = sums[point] + np.einsum("ock,ock->oc", x, x)
            if writer:
                writer.write_block(block)
            done += n
    finally:
        if writer:
            writer.close()
    wall = time.perf_counter() - t0
    rms = engine.new_block(1)
    for point, ss in sums.items():
        getattr(rms, point)[..., 0] = np.sqrt(ss / n_total)
    for name, unit, x in block_channels(twin.ifo, rms):
        print(f"{name:32s} rms {x[0]:11.4g} {unit}")
    speed = args.duration / wall
    print(f"simulated {args.duration:g} s of {len(optics)} optic(s) in {wall:.3f} s: "
          f"{speed:.1f} x real time ({n_total * len(optics) / wall:.3g} optic-samples/s)")
    if writer:
        print(f"recorded {args.record}")
    return 0
