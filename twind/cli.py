"""The ``twind`` command line: ``twind model response``, ``twind simulate``, ``twind bench``, ...

Every user error (bad configuration, foton syntax, unknown optic) ends as one line on stderr
naming the file, key and problem, and exit status 2; never a traceback.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import warnings
from collections.abc import Sequence
from contextlib import nullcontext
from pathlib import Path

import numpy as np

from twind import __version__, DOFS, OSEMS, progress, strictjson
from twind.errors import TwindError, TwindWarning


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
        strictjson.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0
    from twind.viz.plotting import bode_matrix

    path = Path(args.output or f"{cfg.name}_response.png")
    plant = path.with_name(f"{path.stem}_plant{path.suffix}")
    name = f"C1:SUS-{cfg.name} ({cfg.model} model)"
    bode_matrix(f, path, DOFS, DOFS, {"IN1/EXC": r["closed_loop_IN1_per_EXC"],
                                      "IN2/EXC": r["closed_loop_IN2_per_EXC"]},
                title=f"{name}: closed loop")
    bode_matrix(f, plant, DOFS, DOFS, {"IN1/OUT": r["plant_IN1_per_OUT"]}, per="ct",
                title=f"{name}: plant")
    print(f"wrote {path} and {plant}")
    return 0


def cmd_model_compare(args: argparse.Namespace) -> int:
    """Geometric rigid-body model against the analytical model for one optic."""
    from twind.config import load_config
    from twind.model.compare import compare_models
    from twind.viz.plotting import plot_comparison

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


def _endpoints(args: argparse.Namespace) -> tuple[list[str], list[str]]:
    from twind.bus.session import DEFAULT_ENDPOINT

    # a Zenoh configuration file brings its own endpoints
    default = [] if args.connect or getattr(args, "zenoh_config", None) else [DEFAULT_ENDPOINT]
    return args.listen or default, args.connect or []


def cmd_serve(args: argparse.Namespace) -> int:
    """The twin as a Zenoh service."""
    # OpenMP threads that spin between blocks cost a whole core while serving in real time;
    # set before the engine loads its compiled kernel (the runtime reads it once)
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    from twind.bus.session import zenoh_config
    from twind.config import load_config
    from twind.service.serve import main as serve_main

    twin = load_config(args.config, args.optics)
    optics = twin.select(args.optics)
    listen, connect = _endpoints(args)
    conf = zenoh_config(listen, connect, mode=args.mode, config_file=args.zenoh_config)
    return serve_main(conf, twin, optics, block_s=args.block, speed=args.speed, seed=args.seed,
                      duration=args.duration, record_dir=args.record, endpoints=listen + connect,
                      record_config=args.record_zenoh_config)


def _client(args: argparse.Namespace):  # noqa: ANN202 - TwinClient
    from twind.bus.session import DEFAULT_ENDPOINT
    from twind.client import TwinClient

    return TwinClient(connect=args.connect or [DEFAULT_ENDPOINT], ifo=args.ifo,
                      timeout=args.timeout, config_file=args.zenoh_config)


def cmd_inject(args: argparse.Namespace) -> int:
    """Start an excitation on a running twin; prints its id, or the reason it was refused."""
    settings = {k: getattr(args, k) for k in ("freq", "amp", "duration", "ramp", "f_stop",
                                              "n_tones", "shape", "seed")
                if getattr(args, k) is not None}
    if args.start is not None:
        settings["start_gps"] = args.start
    if args.file:
        try:
            settings["samples"] = np.loadtxt(args.file, ndmin=1)
        except ValueError as err:
            msg = f"{args.file}: not a column of numbers ({err})"
            raise TwindError(msg) from None
    with _client(args) as twin:
        exc_id = twin.inject(args.channel, args.waveform, **settings)
    print(exc_id)
    return 0


def cmd_stop(args: argparse.Namespace) -> int:
    """Stop an excitation by id (or all)."""
    with _client(args) as twin:
        print(" ".join(twin.stop(None if args.id == "all" else args.id)))
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    """Print the service status."""
    with _client(args) as twin:
        status = twin.status()
    if args.json:
        print(strictjson.dumps(status))
        return 0
    print(f"{status['ifo']} twin of {', '.join(status['optics'])}: GPS {status['gps']:.3f}, "
          f"up {status['uptime_s']:.1f} s, {status['real_time_factor']:.3f} x real time "
          f"(speed {status['speed']:g}), lag {1e3 * status['lag_s']:.1f} ms "
          f"(max {1e3 * status['max_lag_s']:.1f}), {status['late_blocks']} late blocks, "
          f"busy {100 * status['cpu_fraction']:.1f} %")
    for exc in status["excitations"]:
        when = "waits for" if exc["scheduled"] else "since"
        print(f"  {exc['id']}: {exc['waveform']} on {exc['channel']}, {when} GPS "
              f"{exc['start_gps']:.3f}")
    return 0


def _bus_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", action="append", help="Zenoh endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--ifo", default="C1", help="the twin's interferometer prefix (default C1)")
    p.add_argument("--timeout", type=float, default=5.0,
                   help="seconds to wait for the twin's reply (default 5)")
    p.add_argument("--zenoh-config", help="a Zenoh JSON5 configuration (TLS, access control)")


def cmd_soak(args: argparse.Namespace) -> int:
    """Serve, record, inject and attack for a while; print the service figures."""
    from twind.lab.soak import soak

    report = soak(args.duration, args.optics, args.hostile, args.port, config=args.config,
                  load=args.load, suspend=args.suspend)
    print("\n".join(report.lines()))
    return 0


def _delegate(module: str, function: str):  # noqa: ANN202
    """A subcommand implemented by ``module.function(args)``, imported when it runs."""
    def run(args: argparse.Namespace) -> int:
        import importlib

        return getattr(importlib.import_module(module), function)(args)

    return run


def _arguments_of(module: str, parser: argparse.ArgumentParser) -> None:
    import importlib

    importlib.import_module(module).add_arguments(parser)


def _measured_tfs(args: argparse.Namespace):  # noqa: ANN202 - TFSet
    """The TFs of ``args.inputs``: all diaggui XML or all MCAP sessions."""
    from twind.analysis.tf import from_diaggui, from_session

    _check_band(args)
    paths = [Path(p) for p in args.inputs]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        msg = f"no such input: {', '.join(missing)}"
        raise TwindError(msg)
    kinds = {p.suffix.lower() for p in paths}
    if kinds <= {".xml"}:
        if args.estimator != "welch":
            msg = (f"--estimator {args.estimator} needs the time series: diaggui XML holds "
                   "diaggui's Welch estimates only")
            raise TwindError(msg)
        return from_diaggui(paths)
    if kinds <= {".mcap"}:
        return from_session(paths, bw=args.bw, overlap=args.overlap, optic=args.optic,
                            estimator=args.estimator,
                            max_hz=args.band[1] if args.band else None)
    msg = f"inputs must be all diaggui .xml or all .mcap, got {sorted(kinds)}"
    raise TwindError(msg)


CONFIG_HELP = "twin config (TOML); default: the 40m file shipped with twind"
SEED_HELP = "seed of the twin's noise (default 0)"


def _frequency(text: str) -> float:
    """A frequency argument (Hz): a finite number, zero or more."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        msg = f"not a frequency in Hz: {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return value


def _check_band(args: argparse.Namespace) -> None:
    """``--band LO HI``, if given, has LO below HI."""
    if args.band is not None and not args.band[0] < args.band[1]:
        msg = f"--band {args.band[0]:g} {args.band[1]:g}: LO must be below HI"
        raise TwindError(msg)


def _input_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", nargs="+", help="diaggui XML files (one per excited DOF) or MCAP")
    p.add_argument("--bw", type=float, default=0.01, help="MCAP: Welch resolution (Hz)")
    p.add_argument("--overlap", type=float, default=0.5, help="MCAP: Welch overlap")
    p.add_argument("--optic", help="MCAP: the optic, when several were excited")
    p.add_argument("--estimator", choices=["welch", "lpm"], default="welch",
                   help="MCAP: Welch (diaggui's) or Pintelon-Schoukens' local polynomial "
                        "method over each whole excitation (leakage removed; --bw unused)")
    p.add_argument("--band", type=_frequency, nargs=2, metavar=("LO", "HI"),
                   help="only the frequencies from LO to HI Hz")
    p.add_argument("--json", action="store_true", help="the numbers as JSON")


def _coarser(bw: float, averages: int, wanted: int = 10) -> str:
    """The finest resolution among 1, 2, 5 x 10^k Hz at which the excitations that gave
    `averages` Welch averages (half-overlapped) at `bw` give at least `wanted`."""
    need = bw * (wanted + 1) / (averages + 1)
    k = math.floor(math.log10(need))
    return f"{min(m * 10.0**e for e in (k, k + 1) for m in (1, 2, 5) if m * 10.0**e >= need):g}"


def cmd_tf(args: argparse.Namespace) -> int:
    """Closed-loop TFs, coherence, errors and the recovered plant from XML or MCAP inputs;
    any other diaggui measurement's transfer functions as they were measured."""
    from twind.analysis.tf import TFError

    try:
        tfs = _measured_tfs(args)
    except TFError as err:
        if not all(Path(p).suffix.lower() == ".xml" for p in args.inputs):
            raise
        return _show_transfers(args, str(err))
    if args.band:
        tfs = tfs.band(*args.band)
    elif all(Path(p).suffix.lower() == ".mcap" for p in args.inputs):
        # a recording's bins reach Nyquist: 800 000 at 0.01 Hz, most of them noise
        band = tfs.coherent_band()
        if band is None:
            msg = (f"no bin of IN1/EXC stands above the coherence of noise with "
                   f"{tfs.averages} averages at {args.bw:g} Hz; --bw "
                   f"{_coarser(args.bw, tfs.averages)} gives about 10, --band LO HI shows the "
                   "bins anyway")
            raise TwindError(msg)
        tfs = tfs.band(*band)
        print(f"twind tf: {band[0]:g}-{band[1]:g} Hz, where IN1 is driven by EXC (--band for "
              "others)", file=sys.stderr)
    if args.json:
        strictjson.dump(tfs.to_json(), sys.stdout)
        sys.stdout.write("\n")
    if args.output and not args.output.lower().endswith(".png"):
        print(f"wrote {tfs.write(args.output)}", file=sys.stderr)
    elif args.output:
        print(f"wrote {' and '.join(map(str, _plot_tfs(tfs, Path(args.output))))}",
              file=sys.stderr)
    if not args.json and not args.output:
        print(f"{tfs.optic}: excited {', '.join(tfs.excited)}; {len(tfs.frequency_hz)} bins "
              f"from {tfs.frequency_hz[0]:g} to {tfs.frequency_hz[-1]:g} Hz, {tfs.averages} "
              "averages; --json for the numbers, -o FILE.png for a plot")
    return 0


def _plot_tfs(tfs, path: Path) -> tuple[Path, Path]:  # noqa: ANN001 - TFSet
    """``twind tf -o``: the measured IN1/EXC matrix, and the plant beside it (``_plant``)."""
    from twind.viz.plotting import Measured, bode_matrix

    f = tfs.frequency_hz
    keep = f > 0
    P, sigma = tfs.plant()
    rows = [tfs.responses.index(d) for d in tfs.excited]
    driven = tfs.coherent()
    # the inverse mixes every excitation: a plant bin is as good as the worst excited DOF's
    own = driven[:, rows, np.arange(len(rows))].all(axis=1)
    closed = Measured(tfs.tf["IN1"][keep], tfs.sigma("IN1")[keep], driven[keep])
    plant = Measured(P[keep], sigma[keep], np.broadcast_to(own[keep, None, None], P[keep].shape))
    done = bode_matrix(f[keep], path, tfs.responses, tfs.excited, measured={"IN1/EXC": closed},
                       title=f"{tfs.optic}: measured IN1/EXC ({tfs.averages} averages)")
    other = bode_matrix(f[keep], path.with_name(f"{path.stem}_plant{path.suffix}"),
                        tfs.excited, tfs.excited, measured={"plant IN1/OUT": plant}, per="ct",
                        title=f"{tfs.optic}: the plant (IN1/EXC)(OUT/EXC)^-1")
    return done, other


def _show_transfers(args: argparse.Namespace, why: str) -> int:
    """``twind tf`` on diaggui files that are not a suspension set: every transfer function
    with its coherence and errors (a table, ``--json`` or a Bode PNG)."""
    from twind.analysis.diaggui import read_transfers
    from twind.viz.plotting import bode_transfers

    transfers = [t for path in args.inputs for t in read_transfers(path)]
    if args.band:
        transfers = [t.band(*args.band) for t in transfers]
    print(f"twind tf: not a suspension measurement set ({why}); its transfer functions:",
          file=sys.stderr)
    if args.json:
        strictjson.dump({"transfers": [t.to_json() for t in transfers]}, sys.stdout)
        sys.stdout.write("\n")
    elif args.output:
        if not args.output.lower().endswith(".png"):
            msg = f"-o {args.output}: these transfer functions go to a .png; --json for the numbers"
            raise TwindError(msg)
        print(f"wrote {bode_transfers(transfers, args.output)}", file=sys.stderr)
    else:
        print("\n\n".join("\n".join(t.lines()) for t in transfers))
    return 0


def _show(result, as_json: bool) -> None:  # noqa: ANN001 - anything with to_json and lines
    """Print a result as its JSON object or as lines for a person."""
    if as_json:
        strictjson.dump(result.to_json(), sys.stdout)
        sys.stdout.write("\n")
    else:
        print("\n".join(result.lines()))


def cmd_fit(args: argparse.Namespace) -> int:
    """Fit the nominal parameters to measured TFs; print them with calibrated sigmas."""
    from twind.analysis.fit import FIT_PARAMS, fit, read_truth
    from twind.viz.plotting import plot_fit
    from twind.config import load_config

    truth = read_truth(args.truth) if args.truth else None  # a bad file fails before the fit
    tfs = _measured_tfs(args)
    cfg = load_config(args.config, tfs.optic).select(tfs.optic)[0]
    band = tuple(args.band) if args.band else None
    result = fit(tfs, cfg, args.params or FIT_PARAMS, args.min_coherence, band)
    _show(result, args.json)
    if truth:
        print(f"(fitted - truth) / sigma: {result.pulls(truth)}",
              file=sys.stderr if args.json else sys.stdout)
    if args.output:
        print(f"wrote {plot_fit(tfs, cfg, result, args.output)}", file=sys.stderr)
    return 0


def cmd_modes(args: argparse.Namespace) -> int:
    """Each optic's free-swinging modes: measured, as configured, and with the wire length,
    break-off and clamp separation solved for the measured POS, PIT and YAW."""
    from twind.analysis.candidates import compare
    from twind.analysis.modes import fit_modes, read_mode_table
    from twind.config import MEASURED_MODES, load_config

    table = read_mode_table(args.table or MEASURED_MODES)
    names = args.optic or list(table)
    missing = [n for n in names if n not in table]
    if missing:
        msg = f"{', '.join(missing)} not in {args.table or MEASURED_MODES}"
        raise TwindError(msg)
    twin = load_config(args.config, names)
    if args.candidates:
        comparison = compare(twin.optics, {n: table[n] for n in names})
        if args.json:
            strictjson.dump(comparison.to_json(), sys.stdout)
            sys.stdout.write("\n")
        else:
            print("\n".join(comparison.lines()))
        return 0
    fits = [fit_modes(twin.optics[n], table[n]) for n in names]
    if args.json:
        strictjson.dump([f.to_json() for f in fits], sys.stdout)
        sys.stdout.write("\n")
    else:
        print(fits[0].header(list(fits[0].measured)))
        print("\n".join(line for f in fits for line in f.lines()))
    return 0


def cmd_freeswing(args: argparse.Namespace) -> int:
    """The free-swinging health check: modes, Qs, OSEM gains and the diagonalising input
    matrix from a ringdown, made on the twin (in process or served) or read from a
    recording."""
    from twind.analysis.freeswing import analyse, ringdown
    from twind.config import load_config
    from twind.viz.plotting import plot_freeswing

    optic = load_config(args.config, [args.optic]).optics[args.optic]
    duration = 1000.0 if args.duration is None else args.duration
    if args.input:
        sen, rate = _recorded_osems(args.input, args.ifo, args.optic, args.start, args.duration)
    elif args.connect:
        sen, rate = _served_ringdown(args, optic, duration)
    else:
        print(f"twind freeswing: {optic.name} kicked, damping off, {duration:g} s of "
              "ringdown on the twin ...", file=sys.stderr, flush=True)
        sen, rate = ringdown(optic, duration, seed=args.seed)
    result = analyse(optic, sen, rate)
    _show(result, args.json)
    if args.output:
        print(f"wrote {plot_freeswing(result, sen, rate, args.output)}", file=sys.stderr)
    return 0


def _served_ringdown(args: argparse.Namespace, optic, duration: float):  # noqa: ANN001, ANN202
    """A ringdown of `optic` on the served twin at ``--connect``."""
    from twind.bus.session import zenoh_config
    from twind.service.ringdown import served_ringdown

    def progress(line: str) -> None:
        print(f"twind freeswing: {line}", file=sys.stderr, flush=True)

    bus = zenoh_config(connect=args.connect, mode="client", config_file=args.zenoh_config)
    with _client(args) as twin:
        return served_ringdown(twin, optic, duration, bus, progress)


def _recorded_osems(paths: list[str], ifo: str, optic: str, start: float | None,
                    duration: float | None):  # noqa: ANN202 - (ndarray, float)
    """The five OSEM signals of `optic` from a recording (a session's files), from GPS
    `start` (default: where every OSEM has data) for `duration` (default: to the end)."""
    import numpy as np

    from twind.channels import osem_channel
    from twind.recording.reader import as_array, getdata, session_files

    names = [osem_channel(ifo, optic, o) for o in OSEMS]
    sen, rate = as_array(getdata(names, duration, start, source=session_files(paths)))
    if not np.all(np.isfinite(sen)):
        msg = f"{paths[0]}: the OSEM readings have gaps; freeswing needs an unbroken ringdown"
        raise TwindError(msg)
    return sen, rate


def cmd_diagnose(args: argparse.Namespace) -> int:
    """Locate the mismatch, name the physics left out, fit it, show the improvement."""
    from twind.analysis.diagnose import diagnose
    from twind.config import load_config
    from twind.viz.report import write_report

    tfs = _measured_tfs(args)
    if args.band:
        tfs = tfs.band(*args.band)
    cfg = load_config(args.config, tfs.optic).select(tfs.optic)[0]
    result = diagnose(tfs, cfg)
    _show(result, args.json)
    if args.output:
        print(f"wrote {write_report(result, tfs, cfg, args.output)}", file=sys.stderr)
    if args.push:
        from twind.client import TwinClient

        nominal, effect = result.final_model()
        with TwinClient(list(args.push)) as twin:
            twin.params(result.final.optic, effect=effect, **nominal)
        print(f"pushed into {', '.join(args.push)}: {len(nominal)} nominal parameter(s)"
              + (f" and {effect['id']}" if effect else ""), file=sys.stderr)
    return 0


def _bench_engine(args: argparse.Namespace) -> int:
    """Engine speed, side by side with python-control on the same closed loop."""
    from twind.lab.engine_speed import run_benchmarks

    duration = 20.0 if args.duration is None else args.duration
    run_benchmarks(args.config, duration, marginal=not args.no_marginal)
    return 0


def _bench_tf(args: argparse.Namespace) -> int:
    """``twind tf`` on a written session (default 1 h of 12 channels at 16384 Hz)."""
    from twind.lab.tf_speed import run_tf_benchmark

    duration = 3600.0 if args.duration is None else args.duration
    run_tf_benchmark(duration, workdir=args.workdir, keep=args.keep)
    return 0


def _optic(args: argparse.Namespace, name: str = "ETMX"):  # noqa: ANN202 - OpticConfig
    """Optic `name` of ``--config``: the one the identification benchmarks run on."""
    from twind.config import load_config

    return load_config(args.config, [name]).optics[name]


def _bench_pull(args: argparse.Namespace) -> int:
    """Monte-Carlo pull test of ``twind fit`` on the twin (>= 100 realisations)."""
    from twind.lab.calibration import pull_test
    cfg = _optic(args)
    report = pull_test(cfg, n=args.realisations or 100, bw=args.bw or 0.02, estimator=args.estimator,
                       workers=args.workers)
    print("\n".join(report.lines()))
    return 0


def _bench_information(args: argparse.Namespace) -> int:
    """D-optimal multisines against white noise of equal RMS, measured and fitted on the twin."""
    from twind.lab.calibration import information_benchmark
    cfg = _optic(args)
    print("\n".join(information_benchmark(cfg)))
    return 0


def _bench_diagnose(args: argparse.Namespace) -> int:
    """twind diagnose on the proof corpus: drifted optics with concealed effects."""
    from twind.lab.corpus import AVERAGES, BEYOND, EFFECTS, EXCITED, MADE, RMS, run_corpus

    effects = args.effects.split(",") if args.effects else [*EFFECTS, *BEYOND]
    excited = args.excite.split(",") if args.excite else list(EXCITED)
    if set(excited) - set(DOFS):
        msg = f"--excite takes DOFs among {', '.join(DOFS)}, not {args.excite}"
        raise TwindError(msg)
    unknown = [e for e in effects if set(e.split("+")) - set(MADE)]
    if unknown:
        msg = f"the corpus cannot hide {', '.join(unknown)}; it makes {', '.join(MADE)}"
        raise TwindError(msg)
    cfg = _optic(args, args.optic)
    for route in ("xml", "mcap") if args.route == "both" else (args.route,):
        print(f"--- route: {route}", flush=True)
        run_corpus(cfg, route, args.per_effect, args.nulls, effects=effects,
                   say=lambda line: print(line, flush=True), excited=excited, bw=args.bw,
                   averages=args.averages or AVERAGES, rms=args.rms or RMS)
    return 0


def _bench_freeswing(args: argparse.Namespace) -> int:
    """twind freeswing on the ringdowns of random drifted optics with OSEM imbalances."""
    from twind.lab.freeswing_bench import benchmark

    duration = 1000.0 if args.duration is None else args.duration
    for line in benchmark(_optic(args, args.optic), n=args.realisations or 8,
                          duration_s=duration):
        print(line, flush=True)
    return 0


BENCH_SUITES = {"engine": _bench_engine, "tf": _bench_tf, "pull": _bench_pull,
                "information": _bench_information, "diagnose": _bench_diagnose,
                "freeswing": _bench_freeswing}


def cmd_demo(args: argparse.Namespace) -> int:
    """A "real" twin with a concealed effect beside a nominal one, recorded and diagnosed."""
    from twind.lab.corpus import run_demo

    run_demo(_optic(args), args.output, args.effect, say=lambda line: print(line, flush=True))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    """Run the benchmark suite chosen with ``--suite``."""
    return BENCH_SUITES[args.suite](args)


def _seed(text: str) -> int:
    value = int(text)
    if value < 0:
        msg = f"must be a non-negative integer, got {text}"
        raise argparse.ArgumentTypeError(msg)
    return value


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    p = argparse.ArgumentParser(
        prog="twind", description="twind: a digital twin of the LIGO 40m's suspended optics. "
                                  "'twind COMMAND --help' tells a command's options.")
    p.add_argument("--version", action="version", version=f"twind {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    model = sub.add_parser("model", help="suspension model responses").add_subparsers(
        dest="model_command", required=True)
    resp = model.add_parser("response", help="plant, controller and closed-loop responses")
    resp.add_argument("--config", help=CONFIG_HELP)
    resp.add_argument("--optic", default="ETMX", help="the optic (default ETMX)")
    resp.add_argument("--fmin", type=_frequency, default=0.05,
                      help="lowest frequency, Hz (default 0.05)")
    resp.add_argument("--fmax", type=_frequency, default=50.0,
                      help="highest frequency, Hz (default 50)")
    resp.add_argument("--n", type=int, default=201,
                      help="frequencies, log-spaced from --fmin to --fmax (default 201)")
    resp.add_argument("--freqs", help="comma-separated frequencies (Hz) instead of a log grid")
    resp.add_argument("--json", action="store_true", help="print golden_tf.json layout")
    resp.add_argument("-o", "--output", help="PNG to write (default <OPTIC>_response.png)")
    resp.set_defaults(func=cmd_model_response)
    comp = model.add_parser("compare", help="geometric vs analytical model, with a plot")
    comp.add_argument("--config", help=CONFIG_HELP)
    comp.add_argument("--optic", default="ETMX", help="the optic (default ETMX)")
    comp.add_argument("-o", "--output", default="geometric_vs_analytical.png",
                      help="PNG of both models' responses (default geometric_vs_analytical.png)")
    comp.set_defaults(func=cmd_model_compare)

    sim = sub.add_parser("simulate", help="run the twin as fast as possible")
    sim.add_argument("--config", help=CONFIG_HELP)
    sim.add_argument("--optics", default="ETMX", help="comma-separated names, or 'all'")
    sim.add_argument("--duration", type=float, required=True, help="simulated seconds")
    sim.add_argument("--seed", type=_seed, default=0, help=SEED_HELP)
    sim.add_argument("--block", type=float, default=1.0, help="seconds per engine block")
    sim.add_argument("--record", help="MCAP file to record every block to")
    sim.set_defaults(func=cmd_simulate)

    serve = sub.add_parser("serve", help="run the twin on Zenoh (embedded session)")
    serve.add_argument("--config", help=CONFIG_HELP)
    serve.add_argument("--optics", default="all", help="comma-separated names, or 'all'")
    serve.add_argument("--listen", action="append", help="endpoint (default tcp/127.0.0.1:7447)")
    serve.add_argument("--connect", action="append", help="endpoint of a router or peer")
    serve.add_argument("--mode", choices=("peer", "router", "client"),
                       help="Zenoh mode (default: the --zenoh-config file's, else peer)")
    serve.add_argument("--zenoh-config", help="a Zenoh JSON5 configuration (TLS, access control)")
    serve.add_argument("--record", help="folder for rotating MCAP recordings of the session")
    serve.add_argument("--record-zenoh-config", metavar="FILE.json5",
                       help="the recorder's Zenoh configuration (behind an ACL router: "
                            "deploy/acl/recorder.json5)")
    serve.add_argument("--speed", type=float, default=1.0, help="twin seconds per wall second")
    serve.add_argument("--block", type=float, default=1 / 16, help="seconds per block")
    serve.add_argument("--seed", type=_seed, default=0, help=SEED_HELP)
    serve.add_argument("--duration", type=float, help="stop after this many twin seconds")
    serve.set_defaults(func=cmd_serve)

    inject = sub.add_parser("inject", help="start an excitation on a running twin")
    inject.add_argument("channel", help="e.g. C1:SUS-ETMX_SUSPOS_EXC")
    inject.add_argument("waveform", choices=("sine", "sweep", "noise", "multisine", "stream"),
                        help="the waveform (a stream's samples come from --file)")
    inject.add_argument("--freq", type=float, help="Hz (sweep, multisine: lowest)")
    inject.add_argument("--f-stop", type=float, help="Hz: sweep end, multisine highest")
    inject.add_argument("--n-tones", type=int, help="multisine tones")
    inject.add_argument("--amp", type=float, help="peak amplitude (noise: RMS)")
    inject.add_argument("--duration", type=float, help="seconds (inf: until stopped)")
    inject.add_argument("--ramp", type=float, help="taper seconds at start and end")
    inject.add_argument("--start", type=float, help="GPS start (default: next block)")
    inject.add_argument("--shape", help="noise: foton design shaping white noise")
    inject.add_argument("--file", help="stream: text file of samples at the model rate")
    inject.add_argument("--seed", type=_seed, help="noise: the seed of its random numbers")
    _bus_arguments(inject)
    inject.set_defaults(func=cmd_inject)

    stop = sub.add_parser("stop", help="stop an excitation by id, or 'all'")
    stop.add_argument("id", help="the excitation's id (as inject printed it), or 'all'")
    _bus_arguments(stop)
    stop.set_defaults(func=cmd_stop)

    status = sub.add_parser("status", help="status of a running twin")
    status.add_argument("--json", action="store_true", help="the status as JSON")
    _bus_arguments(status)
    status.set_defaults(func=cmd_status)

    for name, module, function, text in [
            ("record", "twind.recording.recorder", "record_main", "record twin channels to MCAP"),
            ("replay", "twind.recording.replay", "replay_main", "republish a recording on Zenoh"),
            ("export", "twind.recording.export", "export_main", "MCAP session to .npz or .h5"),
            ("recover", "twind.recording.recover", "recover_main",
             "a valid MCAP file from a killed or damaged recording"),
            ("excite", "twind.excitation.excite", "excite_main",
             "design an excitation: a coherence in a band, or the most information"),
            ("campaign", "twind.lab.campaign", "campaign_main",
             "identify an optic: design, inject, record, fit, redesign to a target")]:
        cmd = sub.add_parser(name, help=text)
        _arguments_of(module, cmd)
        cmd.set_defaults(func=_delegate(module, function))

    from twind.viz import add_rrd_arguments, add_view_arguments, rrd_main, view_main

    view = sub.add_parser("view", help="live twin channels in a Rerun viewer")
    add_view_arguments(view)
    view.set_defaults(func=view_main)
    rrd = sub.add_parser("rrd", help="MCAP session to a Rerun .rrd (series, events, Bode)")
    add_rrd_arguments(rrd)
    rrd.set_defaults(func=rrd_main)

    tf = sub.add_parser("tf", help="transfer functions and the open-loop plant from "
                                   "diaggui XML or MCAP sessions")
    _input_arguments(tf)
    tf.add_argument("-o", "--output", help=".h5/.hdf5 or .csv results, or a .png Bode matrix")
    tf.set_defaults(func=cmd_tf)

    fitp = sub.add_parser("fit", help="fit the nominal physical parameters to measured TFs")
    _input_arguments(fitp)
    fitp.add_argument("--config", help="twin config (TOML) holding the optic's nominal model")
    fitp.add_argument("--params", nargs="+", metavar="NAME",
                      help="parameters to fit (default: all nine of docs/model.md)")
    fitp.add_argument("--min-coherence", type=float, default=0.5,
                      help="IN1/EXC bins less coherent (averaged over neighbours) are unused")
    fitp.add_argument("-o", "--output", help=".png: measured, nominal and fitted Bode matrix")
    fitp.add_argument("--truth", metavar="JSON",
                      help="a simulated optic's truth.json: also print (fitted - truth)/sigma")
    fitp.set_defaults(func=cmd_fit)

    modes = sub.add_parser("modes", help="free-swinging modes: measured, as configured, and "
                                         "with the geometry solved for them")
    modes.add_argument("table", nargs="?", help="CSV of measured modes (Hz): optic, POS, PIT, "
                                                "YAW, SIDE (default: the 40m's, 2020)")
    modes.add_argument("--optic", nargs="+", metavar="NAME", help="optics (default: the table's)")
    modes.add_argument("--config", help="twin config (TOML) holding the optics")
    modes.add_argument("--candidates", action="store_true",
                       help="fit candidate physics for what the model misses (SIDE), optic by "
                            "optic, and weigh them over the optics")
    modes.add_argument("--json", action="store_true", help="the numbers as JSON")
    modes.set_defaults(func=cmd_modes)

    free = sub.add_parser("freeswing", help="free-swinging health check: modes, Qs, OSEM "
                                            "gains, diagonalising input matrix")
    free.add_argument("input", nargs="*", help="a recording of a ringdown (MCAP; a session's "
                                               "files); default: ring the twin down, in "
                                               "process or at --connect")
    free.add_argument("--optic", default="ETMX", help="the optic (default ETMX)")
    free.add_argument("--config", help="twin config (TOML) holding the optic's model")
    free.add_argument("--start", type=float, metavar="GPS",
                      help="a recording: GPS start of the ringdown (default: its start)")
    free.add_argument("--duration", type=float,
                      help="seconds of ringdown: made on the twin (default 1000), or read from "
                           "a recording (default: to its end)")
    free.add_argument("--seed", type=int, default=0, help="noise seed of the twin's ringdown")
    free.add_argument("--json", action="store_true", help="the numbers as JSON")
    free.add_argument("-o", "--output", help="PNG: OSEM spectra with the modes, and both "
                                             "input matrices")
    _bus_arguments(free)
    free.set_defaults(func=cmd_freeswing)

    diag = sub.add_parser("diagnose", help="where the model misses, which physics it left "
                                           "out, and the fit with it")
    _input_arguments(diag)
    diag.add_argument("--config", help="twin config (TOML) holding the optic's nominal model")
    diag.add_argument("-o", "--output", metavar="REPORT_DIR",
                      help="write PNGs, the JSON and an HTML summary here")
    diag.add_argument("--push", action="append", metavar="ENDPOINT",
                      help="give the fitted (augmented) model to the running twin there")
    diag.set_defaults(func=cmd_diagnose)

    soak_p = sub.add_parser("soak", help="serve, record, inject and attack; print the figures")
    soak_p.add_argument("--duration", type=float, default=3600.0, help="seconds of serving")
    soak_p.add_argument("--optics", default="all", help="comma-separated names, or 'all'")
    soak_p.add_argument("--hostile", type=int, default=1000, help="malformed requests to send")
    soak_p.add_argument("--port", type=int, default=17461,
                        help="loopback port the soak's twin listens on (default 17461)")
    soak_p.add_argument("--config", help="twin config (TOML); default the shipped one with its "
                                         "watchdogs at 20 um, so that one drive trips one")
    soak_p.add_argument("--load", type=int, default=0, metavar="N",
                        help="N busy processes share the cores with the twin (2: both cores)")
    soak_p.add_argument("--suspend", type=float, default=6.0, metavar="S",
                        help="seconds a second subscriber is suspended (SIGSTOP) at the end")
    soak_p.set_defaults(func=cmd_soak)

    demo = sub.add_parser("demo", help="a 'real' twin with a concealed effect beside a "
                                       "nominal one: excited, recorded, diagnosed")
    demo.add_argument("--config", help=CONFIG_HELP)
    demo.add_argument("--effect", default="actuator_pole",
                      choices=["coil_imbalance", "osem_imbalance", "loop_delay",
                               "actuator_pole", "wire_asymmetry", "bounce_roll"],
                      help="the effect the 'real' twin hides (default actuator_pole)")
    demo.add_argument("-o", "--output", default="twind-demo",
                      help="directory for the recordings and reports (default twind-demo)")
    demo.set_defaults(func=cmd_demo)

    bench = sub.add_parser("bench", help="engine speed against python-control, or twind tf")
    bench.add_argument("--suite", choices=list(BENCH_SUITES), default="engine",
                       help="engine: simulation speed; tf: twind tf on a written session; "
                            "pull: calibration of twind fit's sigmas; information: D-optimal "
                            "excitation against white noise on the twin; diagnose: twind "
                            "diagnose on the proof corpus (--route, --per-effect, --nulls); "
                            "freeswing: twind freeswing on random drifted optics")
    bench.add_argument("--config", help=CONFIG_HELP)
    bench.add_argument("--duration", type=float, default=None,
                       help="engine: simulated seconds per run (default 20); tf: seconds of "
                            "recording (default 3600)")
    bench.add_argument("--workdir", help="tf: directory for the session file (default a "
                                         "temporary one)")
    bench.add_argument("--keep", action="store_true", help="tf: keep the session file")
    bench.add_argument("--realisations", type=int, default=None,
                       help="pull: noise realisations (default 100); freeswing: optics (8)")
    bench.add_argument("--route", choices=["xml", "mcap", "both"], default="xml",
                       help="diagnose: the corpus as diaggui XML sets or MCAP sessions")
    bench.add_argument("--optic", default="ETMX",
                       help="diagnose: the optic of --config whose drifts make the corpus")
    bench.add_argument("--per-effect", type=int, default=3, help="diagnose: cases per effect")
    bench.add_argument("--nulls", type=int, default=3, help="diagnose: drift-only cases")
    bench.add_argument("--effects", help="diagnose: comma-separated kinds to hide: catalogue "
                                         "effects, resonance (a body on the face), "
                                         "channel_filter (one channel's stage), pairs a+b "
                                         "(default the catalogue's six, those three kinds and "
                                         "three pairs)")
    bench.add_argument("--averages", type=int,
                       help="diagnose: averages of the corpus measurement (default 10)")
    bench.add_argument("--rms", type=float,
                       help="diagnose: RMS of its excitation (counts; default 3)")
    bench.add_argument("--excite", help="diagnose: comma-separated DOFs excited in turn "
                                        "(default POS,PIT,YAW; add SIDE for side_coupling)")
    bench.add_argument("--bw", type=float, help="pull: Welch resolution (Hz, default 0.02; "
                       "the LPM's record is as long as 10 averages of it); diagnose: the "
                       "corpus measurement's (default 0.01 for XML, example_null's; 0.05 for "
                       "MCAP)")
    bench.add_argument("--estimator", choices=["welch", "lpm"], default="welch",
                       help="pull: TF estimator")
    bench.add_argument("--workers", type=int, default=1,
                       help="pull: realisations measured and fitted side by side")
    bench.add_argument("--no-marginal", action="store_true",
                       help="skip the 200 s - 20 s marginal speed of 'twind simulate'")
    bench.set_defaults(func=cmd_bench)
    return p


_DEFAULT_SHOWWARNING = warnings.showwarning


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """twind's own warnings in one line for a person; the rest as Python shows them."""
    if issubclass(category, TwindWarning):
        print(f"twind: warning: {message}", file=sys.stderr)
    else:
        _DEFAULT_SHOWWARNING(message, category, filename, lineno, file, line)


PROGRESS_UNITS = {"tf": "segment", "fit": "evaluation", "diagnose": "evaluation",
                  "demo": "evaluation", "campaign": "evaluation", "bench tf": "segment",
                  "bench pull": "evaluation", "bench information": "evaluation",
                  "bench diagnose": "evaluation", "bench freeswing": "optic"}
"""Commands (``bench`` by suite) that show a progress bar on a terminal, and what it counts
(Welch segments summed, model evaluations of the fits, optics rung down); the engine
benchmark shows none, so that nothing runs beside what it times."""


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``twind`` console script."""
    args = build_parser().parse_args(argv)
    unit = PROGRESS_UNITS.get(f"bench {args.suite}" if args.command == "bench" else args.command)
    try:
        with warnings.catch_warnings(), \
                progress.shown(f"twind {args.command}", unit) if unit else nullcontext():
            warnings.showwarning = _show_warning
            return args.func(args)
    except (TwindError, OSError) as err:
        print(f"twind: error: {err}", file=sys.stderr)
        return 2
    except Exception as err:
        if type(err).__module__.startswith("zenoh"):  # e.g. an endpoint that cannot be bound
            from twind.bus.session import zenoh_message

            print(f"twind: error: {zenoh_message(err)}", file=sys.stderr)
            return 2
        raise
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
