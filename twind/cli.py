"""The ``twind`` command line: ``twind model response``, ``twind simulate``, ``twind bench``, ...

Every user error (bad configuration, foton syntax, unknown optic) ends as one line on stderr
naming the file, key and problem, and exit status 2; never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from twind import DOFS
from twind.errors import TwindError


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
    from twind.config import load_config

    cfg = load_config(args.config, [args.optic]).select([args.optic])[0]
    f = _frequencies(args)
    r = cfg.loop().responses(f)
    keys = ("plant_IN1_per_OUT", "controller_diag", "closed_loop_IN1_per_EXC",
            "closed_loop_IN2_per_EXC")
    if args.json:
        out = {"about": f"twind model response of {cfg.name} ({cfg.model} model, {cfg.source})",
               "dofs": list(DOFS), "frequency_hz": f.tolist()}
        out.update({k: _complex(r[k]) for k in keys})
        out["uncoupled_frequencies_hz"] = cfg.sus.uncoupled_frequencies_hz()
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0
    from twind.plotting import bode_matrix

    path = Path(args.output or f"{cfg.name}_response.png")
    bode_matrix(f, {"plant IN1/OUT": r["plant_IN1_per_OUT"],
                    "closed loop IN1/EXC": r["closed_loop_IN1_per_EXC"],
                    "closed loop IN2/EXC": r["closed_loop_IN2_per_EXC"]},
                path, DOFS, title=f"C1:SUS-{cfg.name} ({cfg.model} model)")
    print(f"wrote {path}")
    return 0


def cmd_model_compare(args: argparse.Namespace) -> int:
    """Geometric rigid-body model against the analytical model for one optic."""
    from twind.config import load_config
    from twind.model.compare import compare_models
    from twind.plotting import plot_comparison

    cfg = load_config(args.config, [args.optic]).select([args.optic])[0]
    cmp = compare_models(cfg.sus, np.geomspace(0.1, 10, 400))
    for dof, pct in cmp.eigen_difference_pct().items():
        print(f"{dof:5s} analytical {cmp.eigen_analytical_hz[dof]:8.5f} Hz  "
              f"geometric {cmp.eigen_geometric_hz[dof]:8.5f} Hz  ({pct:+.3f} %)")
    path = plot_comparison(cmp, args.output)
    print(f"wrote {path}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """Run the twin as fast as it can; print per-channel RMS and the speed reached."""
    from twind.channels import block_channels
    from twind.config import load_config
    from twind.simulation.engine import Engine
    from twind.timeutil import now_gps

    twin = load_config(args.config, args.optics)
    optics = twin.select(args.optics)
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
        from twind.recording.writer import SessionWriter

        writer = SessionWriter(args.record, twin.ifo, now_gps())
    sums = {p: 0.0 for p in ("exc", "in1", "in2", "out", "sen")}
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


def cmd_bench(args: argparse.Namespace) -> int:
    """Engine speed, side by side with python-control on the same closed loop."""
    from twind.simulation.benchmark import run_benchmarks

    run_benchmarks(args.config, args.duration, marginal=not args.no_marginal)
    return 0


def _seed(text: str) -> int:
    value = int(text)
    if value < 0:
        msg = f"must be a non-negative integer, got {text}"
        raise argparse.ArgumentTypeError(msg)
    return value


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    p = argparse.ArgumentParser(prog="twind", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    model = sub.add_parser("model", help="suspension model responses").add_subparsers(
        dest="model_command", required=True)
    resp = model.add_parser("response", help="plant, controller and closed-loop responses")
    resp.add_argument("--config", help="config file (default: the 40m file shipped with twind)")
    resp.add_argument("--optic", default="ETMX")
    resp.add_argument("--fmin", type=float, default=0.05)
    resp.add_argument("--fmax", type=float, default=50.0)
    resp.add_argument("--n", type=int, default=201)
    resp.add_argument("--freqs", help="comma-separated frequencies (Hz) instead of a log grid")
    resp.add_argument("--json", action="store_true", help="print golden_tf.json layout")
    resp.add_argument("-o", "--output", help="PNG to write (default <OPTIC>_response.png)")
    resp.set_defaults(func=cmd_model_response)
    comp = model.add_parser("compare", help="geometric vs analytical model, with a plot")
    comp.add_argument("--config")
    comp.add_argument("--optic", default="ETMX")
    comp.add_argument("-o", "--output", default="geometric_vs_analytical.png")
    comp.set_defaults(func=cmd_model_compare)

    sim = sub.add_parser("simulate", help="run the twin as fast as possible")
    sim.add_argument("--config")
    sim.add_argument("--optics", default="ETMX", help="comma-separated names, or 'all'")
    sim.add_argument("--duration", type=float, required=True, help="simulated seconds")
    sim.add_argument("--seed", type=_seed, default=0)
    sim.add_argument("--block", type=float, default=1.0, help="seconds per engine block")
    sim.add_argument("--record", help="MCAP file to record every block to")
    sim.set_defaults(func=cmd_simulate)

    bench = sub.add_parser("bench", help="engine speed against python-control")
    bench.add_argument("--config")
    bench.add_argument("--duration", type=float, default=20.0, help="simulated seconds per run")
    bench.add_argument("--no-marginal", action="store_true",
                       help="skip the 200 s - 20 s marginal speed of 'twind simulate'")
    bench.set_defaults(func=cmd_bench)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``twind`` console script."""
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (TwindError, OSError) as err:
        print(f"twind: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
