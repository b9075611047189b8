"""The measurement commands: ``twind tf``, ``fit``, ``diagnose``, ``modes``, ``freeswing``,
and ``demo``, the diagnosis on a twin that hides an effect."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from twind import OSEMS, __version__, strictjson
from twind.analysis.diagnose import diagnose
from twind.analysis.diagnosis import DiagnoseError
from twind.analysis.estimation.diaggui import read_transfers
from twind.analysis.estimation.tfset import ReadOptions, TFError, TFSet, identify
from twind.analysis.identification.candidates import compare
from twind.analysis.identification.controller import check_controller
from twind.analysis.identification.fit import fit
from twind.analysis.identification.freeswing import analyse, ringdown
from twind.analysis.identification.inmatrix import InputMatrixCheck, recorded_input_matrix
from twind.analysis.identification.lines import (
    MIN_HZ,
    LineReport,
    pair_reading,
    violin_lines,
    violin_ringdown,
)
from twind.analysis.identification.modes import fit_modes, read_mode_table
from twind.analysis.identification.params import FIT_PARAMS, read_truth
from twind.analysis.prediction import fit_curves
from twind.bus.session import zenoh_config
from twind.channels import osem_channel
from twind.cli import plant as statespace
from twind.cli.twin import client
from twind.client import TwinClient
from twind.config import MEASURED_MODES, OpticConfig, load_config
from twind.errors import TwindError
from twind.recording.frames import parse_map
from twind.recording.reader import as_array, getdata
from twind.recording.session import session_files
from twind.commissioning.demo import run_demo
from twind.commissioning.ringdown import served_ringdown
from twind.viz.plotting import (
    Measured,
    bode_matrix,
    bode_transfers,
    plot_fit,
    plot_freeswing,
    plot_violin_lines,
)
from twind.viz.report import REPORT_FILES, report_dir, write_report


def _measured_tfs(args: argparse.Namespace) -> TFSet:
    """The TFs of ``args.inputs``: all diaggui XML, or time series (MCAP sessions, or HDF5
    files or GWF frames)."""

    _check_band(args)
    tfs = TFSet.read(args.inputs, ReadOptions(
        bw=args.bw, overlap=args.overlap, optic=args.optic, estimator=args.estimator,
        max_hz=args.band[1] if args.band else None, mapping=parse_map(args.map),
        exc_times={d: (a, b) for d, a, b in args.exc_times}))
    for line in tfs.found:
        print(f"twind: excitation found in the data: {line}", file=sys.stderr)
    return tfs


def _input_matrix(args: argparse.Namespace, cfg: OpticConfig) -> InputMatrixCheck:
    """The input matrix of ``args.inputs`` (a recording's IN1 and OSEM readings) checked
    against `cfg`'s."""
    if identify(args.inputs) == "diaggui":
        return InputMatrixCheck(cfg.cds_input_matrix(),
                                why="diaggui XML holds no OSEM readings")
    return recorded_input_matrix(args.inputs, cfg, parse_map(args.map))


def _check_band(args: argparse.Namespace) -> None:
    """``--band LO HI``, if given, has LO below HI."""
    if args.band is not None and not args.band[0] < args.band[1]:
        msg = f"--band {args.band[0]:g} {args.band[1]:g}: LO must be below HI"
        raise TwindError(msg)


def _coarser(bw: float, averages: int, wanted: int = 10) -> str:
    """The finest resolution among 1, 2, 5 x 10^k Hz at which the excitations that gave
    `averages` Welch averages (half-overlapped) at `bw` give at least `wanted`."""
    need = bw * (wanted + 1) / (averages + 1)
    k = math.floor(math.log10(need))
    return f"{min(m * 10.0**e for e in (k, k + 1) for m in (1, 2, 5) if m * 10.0**e >= need):g}"


def cmd_tf(args: argparse.Namespace) -> int:
    """Closed-loop TFs, coherence, errors and the recovered plant from XML or MCAP inputs;
    any other diaggui measurement's transfer functions as they were measured."""

    optic = statespace.statespace_optic(args)
    if optic is not None:
        return statespace.tf(args, optic)
    try:
        tfs = _measured_tfs(args)
    except TFError as err:
        if identify(args.inputs) != "diaggui":  # a diaggui set of other TFs: as measured
            raise
        return _show_transfers(args, str(err))
    if args.band:
        tfs = tfs.band(*args.band)
    elif identify(args.inputs) != "diaggui":
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

    f = tfs.frequency_hz
    keep = f > 0
    P, sigma = tfs.plant()
    rows = [tfs.responses.index(d) for d in tfs.excited]
    driven = tfs.coherent()
    # the inverse mixes every excitation: a plant bin is as good as the worst excited DOF's
    own = driven[:, rows, np.arange(len(rows))].all(axis=1)
    closed = Measured(tfs.tf["IN1"][keep], tfs.sigma("IN1")[keep], driven[keep])
    plant = Measured(P[keep], sigma[keep], np.broadcast_to(own[keep, None, None], P[keep].shape))
    caption = f"{tfs.caption()}; twind {__version__}"
    coh = tfs.coherence["IN1"][keep]
    done = bode_matrix(f[keep], path, tfs.responses, tfs.excited, measured={"IN1/EXC": closed},
                       title=f"{tfs.optic}: measured IN1/EXC", coherence=coh, caption=caption)
    other = bode_matrix(f[keep], path.with_name(f"{path.stem}_plant{path.suffix}"),
                        tfs.excited, tfs.excited, measured={"plant IN1/OUT": plant}, per="ct",
                        title=f"{tfs.optic}: the plant (IN1/EXC)(OUT/EXC)^-1, coherence of "
                              "IN1/EXC", coherence=coh[:, rows], caption=caption)
    return done, other


def _show_transfers(args: argparse.Namespace, why: str) -> int:
    """``twind tf`` on diaggui files that are not a suspension set: every transfer function
    with its coherence and errors (a table, ``--json`` or a Bode PNG)."""

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


def cmd_fit(args: argparse.Namespace) -> int:
    """Fit the nominal parameters to measured TFs; print them with calibrated sigmas."""

    optic = statespace.statespace_optic(args)
    if optic is not None:
        return statespace.fit(args, optic)
    truth = read_truth(args.truth) if args.truth else None  # a bad file fails before the fit
    tfs = _measured_tfs(args)
    configured = load_config(args.config, tfs.optic).select(tfs.optic)[0]
    matrix = _input_matrix(args, configured)
    check = check_controller(tfs, matrix.config(configured))
    cfg = check.config  # the plant is read through the input matrix and controller measured
    band = tuple(args.band) if args.band else None
    result = fit(tfs, cfg, args.params or FIT_PARAMS, args.min_coherence, band)
    if args.json:
        strictjson.dump({**result.to_json(), "controller": check.to_json(),
                         "input_matrix": matrix.to_json()}, sys.stdout)
        sys.stdout.write("\n")
    else:
        print("\n".join([*matrix.lines(), *check.lines(), *result.lines()]))
    if truth:
        print(f"(fitted - truth) / sigma: {result.pulls(truth)}",
              file=sys.stderr if args.json else sys.stdout)
    if args.output:
        print(f"wrote {plot_fit(fit_curves(tfs, cfg, result), args.output)}", file=sys.stderr)
    return 0


def cmd_modes(args: argparse.Namespace) -> int:
    """Each optic's free-swinging modes: measured, as configured, and with the wire length,
    break-off and clamp separation solved for the measured POS, PIT and YAW."""

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

    twin = load_config(args.config, [args.optic])
    optic = twin.optics[args.optic]
    args.ifo = args.ifo or twin.ifo  # a recording's channels and a served twin's keys
    if args.violin is not None:
        return _violin(args, optic)
    duration = 1000.0 if args.duration is None else args.duration
    if args.input:
        sen, rate = _recorded_osems(args.input, args.ifo, args.optic, args.start,
                                    args.duration)
    elif args.connect:
        sen, rate = _served_ringdown(args, optic, duration)
    else:
        print(f"twind freeswing: {optic.name} kicked, damping off, {duration:g} s of "
              "ringdown on the twin ...", file=sys.stderr, flush=True)
        sen, rate = ringdown(optic, duration, seed=args.seed)
    lines = _lines(optic, sen, rate)
    try:
        result = analyse(optic, sen, rate)
    except TwindError as err:
        if lines is None or not lines.found:
            raise
        print(f"twind freeswing: {err}; the lines above {MIN_HZ:g} Hz only", file=sys.stderr)
        result = None
    if args.json:
        strictjson.dump({**({"optic": optic.name} if result is None else result.to_json()),
                         "lines": None if lines is None else lines.to_json()}, sys.stdout)
        sys.stdout.write("\n")
    else:
        print("\n".join([*(result.lines() if result else []),
                         *(lines.lines() if lines else [])]))
    if args.output:
        done = (plot_freeswing(result, sen, rate, args.output) if result is not None
                else plot_violin_lines(lines, args.output, sen, rate))
        print(f"wrote {done}", file=sys.stderr)
    return 0


def _violin(args: argparse.Namespace, optic: OpticConfig) -> int:
    """``twind freeswing --violin``: a violin mode rung up and let ring down on the twin, and
    the lines of its OSEM readings."""
    if args.input or args.connect:
        msg = "--violin rings the twin in process: no recording or --connect with it"
        raise TwindError(msg)
    duration = 400.0 if args.duration is None else args.duration
    at = f"{args.violin:g} Hz" if args.violin else "its violin mode POS drives most"
    print(f"twind freeswing: {optic.name} driven through LSC_EXC at {at} for {args.ring_up:g} s, "
          f"then {duration:g} s of ringdown ...", file=sys.stderr, flush=True)
    sen, rate, f_hz = violin_ringdown(optic, args.violin or None, args.ring_up, duration,
                                      args.seed)
    report = violin_lines(optic, sen, rate)
    if args.json:
        strictjson.dump({"optic": optic.name, "driven_hz": f_hz, "lines": report.to_json()},
                        sys.stdout)
        sys.stdout.write("\n")
    else:
        print("\n".join([f"driven at {f_hz:.6f} Hz", *report.lines()]))
    if args.output:
        print(f"wrote {plot_violin_lines(report, args.output, sen, rate)}", file=sys.stderr)
    return 0


def _lines(optic: OpticConfig, sen: np.ndarray, rate: float) -> LineReport | None:
    """The violin lines of a free-swinging measurement; None where its rate or length
    cannot hold them (a decimated recording, a few seconds)."""
    if rate / 2 <= MIN_HZ:
        return None
    try:
        return violin_lines(optic, sen, rate)
    except TwindError:  # too short for lines: then too short for the modes, which say so
        return None


def _served_ringdown(args: argparse.Namespace, optic, duration: float):  # noqa: ANN001, ANN202
    """A ringdown of `optic` on the served twin at ``--connect``."""

    def progress(line: str) -> None:
        print(f"twind freeswing: {line}", file=sys.stderr, flush=True)

    bus = zenoh_config(connect=args.connect, mode="client", config_file=args.zenoh_config)
    with client(args) as twin:
        return served_ringdown(twin, optic, duration, bus, progress)


def _recorded_osems(paths: list[str], ifo: str, optic: str, start: float | None,
                    duration: float | None):  # noqa: ANN202 - (ndarray, float)
    """The five OSEM signals of `optic` from a recording (a session's files), from GPS
    `start` (default: where every OSEM has data) for `duration` (default: to the end)."""

    names = [osem_channel(ifo, optic, o) for o in OSEMS]
    sen, rate = as_array(getdata(names, duration, start, source=session_files(paths)))
    if not np.all(np.isfinite(sen)):
        msg = f"{paths[0]}: the OSEM readings have gaps; freeswing needs an unbroken ringdown"
        raise TwindError(msg)
    return sen, rate


def cmd_diagnose(args: argparse.Namespace) -> int:
    """Locate the mismatch, name the physics left out, fit it, show the improvement."""

    optic = statespace.statespace_optic(args)
    if optic is not None and args.violin_pair:
        msg = f"--violin-pair: {optic.name} is a state-space model, with no wire_asymmetry"
        raise TwindError(msg)
    if optic is not None:
        return statespace.diagnose(args, optic)
    if args.output:  # a report already there is refused before the work, not after it
        report_dir(args.output, REPORT_FILES, DiagnoseError)
    tfs = _measured_tfs(args)
    if args.band:
        tfs = tfs.band(*args.band)
    cfg = load_config(args.config, tfs.optic).select(tfs.optic)[0]
    result = diagnose(tfs, cfg, input_matrix=_input_matrix(args, cfg))
    pair = _weighed_pair(args.violin_pair, cfg, result) if args.violin_pair else None
    if args.json:
        strictjson.dump({**result.to_json(), **({"violin_pair": pair.to_json()} if pair else {})},
                        sys.stdout)
        sys.stdout.write("\n")
    else:
        print("\n".join([*result.lines(), *(pair.lines() if pair else [])]))
    cfg = result.read_through(cfg)
    if args.output:
        page = write_report(result, result.curves(tfs, cfg), tfs, args.output, args.inputs)
        print(f"wrote {page}", file=sys.stderr)
    if args.push:
        nominal, effect = result.final_model()
        with TwinClient(list(args.push)) as twin:
            twin.params(result.final.optic, effect=effect, **nominal)
        print(f"pushed into {', '.join(args.push)}: {len(nominal)} nominal parameter(s)"
              + (f" and {effect['id']}" if effect else ""), file=sys.stderr)
    return 0


def _weighed_pair(pair: list[float], cfg: OpticConfig, result):  # noqa: ANN001, ANN202
    """``--violin-pair``: its two readings weighed against the diagnosis's wire_asymmetry."""
    fitted = result.fitted("wire_asymmetry", "delta_m")
    if fitted is None:
        msg = ("--violin-pair: the diagnosis fitted no wire_asymmetry to weigh the pair "
               "against (see its hypotheses not fitted)")
        raise TwindError(msg)
    return pair_reading(cfg, *pair).weigh(*fitted)


def cmd_demo(args: argparse.Namespace) -> int:
    """A "real" twin with a concealed effect beside a nominal one, recorded and diagnosed."""
    cfg = load_config(args.config, ["ETMX"]).optics["ETMX"]
    run_demo(cfg, args.output, args.effect, say=lambda line: print(line, flush=True))
    return 0
