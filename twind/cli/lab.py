"""The commands that prove twind: ``twind bench`` and ``soak``."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile

from twind import DOFS
from twind.config import CONFIG_DIR, load_config, optic_kinds
from twind.errors import TwindError
from twind.lab import kagra_files, kagra_reference, plant_bench, plant_cases
from twind.lab.calibration import information_benchmark, pull_test
from twind.commissioning.concealed import AVERAGES, EXCITED, RMS
from twind.commissioning.hidden import MADE
from twind.lab.corpus import BEYOND, EFFECTS, run_corpus
from twind.lab.engine_speed import run_benchmarks
from twind.lab.freeswing_bench import benchmark
from twind.lab.latency import command_latency
from twind.lab.rates import (
    NEAR_LIMIT,
    SETTINGS,
    at_settings,
    concealed,
    nulls,
    report,
    settings_report,
)
from twind.lab.fleet import soak_fleet, twin_line
from twind.lab.soak import soak, soak_connected
from twind.lab.tf_speed import run_tf_benchmark


def cmd_soak(args: argparse.Namespace) -> int:
    """Serve, record, inject and attack for a while; print the service figures. With
    ``--connect``, soak a running fleet; with ``--fleet``, build one on namespaced hosts."""

    if args.fleet:
        report = soak_fleet(args.duration, args.layout, args.twin_hosts, args.hostile)
        print("\n".join(report.lines()))
    elif args.connect:
        figures = soak_connected(args.connect, args.duration, args.zenoh_config, args.hostile)
        print(json.dumps(figures, indent=1) if args.json else
              "\n".join(twin_line(t) for t in figures["twins"]))
    else:
        report = soak(args.duration, args.optics, args.hostile, args.port, config=args.config,
                      load=args.load, suspend=args.suspend)
        print("\n".join(report.lines()))
    return 0


def _bench_engine(args: argparse.Namespace) -> int:
    """Engine speed, side by side with python-control on the same closed loop."""

    duration = 20.0 if args.duration is None else args.duration
    run_benchmarks(args.config, duration, marginal=not args.no_marginal)
    return 0


def _bench_tf(args: argparse.Namespace) -> int:
    """``twind tf`` on a written session (default 1 h of 12 channels at 16384 Hz)."""

    duration = 3600.0 if args.duration is None else args.duration
    run_tf_benchmark(duration, workdir=args.workdir, keep=args.keep)
    return 0


KAGRA = CONFIG_DIR / "kagra" / "k1.toml"
"""The state-space optics the statespace suite runs on by default."""


def _optic(args: argparse.Namespace, name: str | None = "ETMX"):  # noqa: ANN202 - OpticConfig
    """Optic `name` of ``--config``: the one the identification benchmarks run on."""

    name = name or "ETMX"
    return load_config(args.config, [name]).optics[name]


def _bench_pull(args: argparse.Namespace) -> int:
    """Monte-Carlo pull test of ``twind fit`` on the twin (>= 100 realisations)."""
    cfg = _optic(args)
    report = pull_test(cfg, n=args.realisations or 100, bw=args.bw or 0.02,
                       estimator=args.estimator or "welch", workers=args.workers)
    print("\n".join(report.lines()))
    return 0


def _bench_information(args: argparse.Namespace) -> int:
    """D-optimal multisines against white noise of equal RMS, measured and fitted on the twin."""
    cfg = _optic(args)
    print("\n".join(information_benchmark(cfg)))
    return 0


def _effects(args: argparse.Namespace, default: list[str]) -> list[str]:
    """The kinds of effect ``--effects`` asks the corpus to hide, checked."""
    effects = args.effects.split(",") if args.effects else default
    unknown = [e for e in effects if set(e.split("+")) - set(MADE)]
    if unknown:
        msg = f"the corpus cannot hide {', '.join(unknown)}; it makes {', '.join(MADE)}"
        raise TwindError(msg)
    return effects


def _bench_diagnose(args: argparse.Namespace) -> int:
    """twind diagnose on the proof corpus: drifted optics with concealed effects."""

    effects = _effects(args, [*EFFECTS, *BEYOND])
    excited = args.excite.split(",") if args.excite else list(EXCITED)
    if set(excited) - set(DOFS):
        msg = f"--excite takes DOFs among {', '.join(DOFS)}, not {args.excite}"
        raise TwindError(msg)
    cfg = _optic(args, args.optic)
    per_effect = 3 if args.per_effect is None else args.per_effect
    n_nulls = 3 if args.nulls is None else args.nulls
    for route in ("xml", "mcap") if args.route == "both" else (args.route,):
        print(f"--- route: {route}", flush=True)
        run_corpus(cfg, route, per_effect, n_nulls, effects=effects,
                   say=lambda line: print(line, flush=True), excited=excited, bw=args.bw,
                   averages=args.averages or AVERAGES, rms=args.rms or RMS)
    return 0


def _bench_rates(args: argparse.Namespace) -> int:
    """twind diagnose's rates: claims, bands and p-values on many nulls at each setting (or
    at the one --bw and --estimator give, case by case), finds at the concealment."""

    cfg = _optic(args, args.optic)
    effects = _effects(args, list(NEAR_LIMIT))
    per_effect = 3 if args.per_effect is None else args.per_effect
    if args.bw or args.estimator:
        measurement = {"bw": args.bw} if args.bw else {}
        null_set = nulls(cfg, 20 if args.nulls is None else args.nulls,
                         estimator=args.estimator or "welch", **measurement)
        effect_set = concealed(cfg, per_effect, effects) if per_effect else []
        print("\n".join(report(null_set, effect_set)))
        return 0
    names = args.settings.split(",") if args.settings else list(SETTINGS)
    unknown = [n for n in names if n not in SETTINGS]
    if unknown:
        msg = f"--settings: unknown {', '.join(unknown)}; known: {', '.join(SETTINGS)}"
        raise TwindError(msg)
    by_setting = at_settings(cfg, 20 if args.nulls is None else args.nulls, names)
    effect_set = concealed(cfg, per_effect, effects) if per_effect else []
    print("\n".join(settings_report(by_setting, effect_set)))
    return 0


def _bench_statespace(args: argparse.Namespace) -> int:
    """twind on state-space optics (KAGRA's by default): nulls and moved modes measured open
    and closed loop, diagnosed file by file; closed-loop plants against open-loop ones."""

    path = args.config or KAGRA
    kinds = optic_kinds(path)
    names = args.optic.split(",") if args.optic else [
        n for n in ("SRM", "PRM") if kinds.get(n) == "statespace"]
    if not names or any(kinds.get(n) != "statespace" for n in names):
        msg = (f"--suite statespace runs on state-space optics; {path} has "
               f"{', '.join(f'{n} ({k})' for n, k in kinds.items())}: name them with --optic")
        raise TwindError(msg)
    optics = load_config(path, names).select(names)
    lines = plant_bench.run(optics, nulls=6 if args.nulls is None else args.nulls,
                            moves=4 if args.per_effect is None else args.per_effect,
                            workdir=args.workdir)
    print("\n".join(lines))
    return 0


def _bench_freeswing(args: argparse.Namespace) -> int:
    """twind freeswing on the ringdowns of random drifted optics with OSEM imbalances."""

    duration = 1000.0 if args.duration is None else args.duration
    for line in benchmark(_optic(args, args.optic), n=args.realisations or 8,
                          duration_s=duration):
        print(line, flush=True)
    return 0


def _bench_commands(args: argparse.Namespace) -> int:
    """The commands a person waits on, timed from process start to their answer."""

    lines = command_latency(runs=args.realisations or 5,
                            say=lambda line: print(line, file=sys.stderr, flush=True))
    print("\n".join(lines))
    return 0


def _bench_kagra(args: argparse.Namespace) -> int:
    """twind diagnose on KAGRA's real measurements shared in tests/data/kagra, scored against
    the independent reference of each."""

    names = args.optic.split(",") if args.optic else list(kagra_reference.FILES)
    with tempfile.TemporaryDirectory(prefix="twind-kagra-") as tmp:
        lines = kagra_files.run(names, args.workdir or tmp,
                                say=lambda line: print(line, flush=True))
    print("\n".join(lines))
    return 0


def _bench_cases(args: argparse.Namespace) -> int:
    """Realistic cases made from KAGRA's models (several modes moved in shapes of their own,
    a measurement chain no model has), diagnosed and scored against their truth."""

    optics = args.optic.split(",") if args.optic else ["SRM", "PRM", "BS"]
    with tempfile.TemporaryDirectory(prefix="twind-cases-") as tmp:
        lines = plant_cases.run(optics, args.per_effect or 1, args.workdir or tmp,
                                say=lambda line: print(line, flush=True))
    print("\n".join(lines))
    return 0


SUITES = {"engine": _bench_engine, "tf": _bench_tf, "pull": _bench_pull,
          "information": _bench_information, "diagnose": _bench_diagnose,
          "rates": _bench_rates, "freeswing": _bench_freeswing,
          "statespace": _bench_statespace, "commands": _bench_commands,
          "kagra": _bench_kagra, "cases": _bench_cases}
"""The functions of ``twind bench --suite`` (:data:`twind.cli.commands.BENCH_SUITES`)."""


def cmd_bench(args: argparse.Namespace) -> int:
    """Run the benchmark suite chosen with ``--suite``."""
    return SUITES[args.suite](args)
