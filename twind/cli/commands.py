"""Every ``twind`` command: its arguments, and where it runs (:class:`~twind.cli.command.Command`)."""

from __future__ import annotations

import argparse

from twind import DOFS
from twind.cli.command import Command, counting
from twind.cli.options import (
    CONFIG_HELP,
    FIGURES,
    SEED_HELP,
    TF_RESULTS,
    bus_arguments,
    count,
    existing,
    fraction,
    frequency,
    input_arguments,
    new_file,
    positive,
    positive_int,
    seed,
)

BENCH_SUITES = ("engine", "tf", "pull", "information", "diagnose", "rates", "freeswing",
                "statespace", "commands", "kagra", "cases")
"""``twind bench --suite``: what each measures is in ``--help``."""

BENCH_PROGRESS = {"tf": "segment", "pull": "evaluation", "information": "evaluation",
                  "diagnose": "evaluation", "rates": "case", "freeswing": "optic",
                  "statespace": "evaluation"}
"""What a bench suite's progress bar counts; the engine suite shows none, so that nothing runs
beside what it times."""


def _response(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind model response``."""
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--optic", help="the optic (default: the file's only one, else ETMX)")
    p.add_argument("--drives", help="a state-space optic: comma-separated drives (default: "
                                    "its damping loops)")
    p.add_argument("--readbacks", help="a state-space optic: comma-separated readbacks "
                                       "(default: its damping loops' IN1)")
    p.add_argument("--fmin", type=frequency, default=0.05,
                   help="lowest frequency, Hz (default 0.05)")
    p.add_argument("--fmax", type=frequency, default=50.0,
                   help="highest frequency, Hz (default 50)")
    p.add_argument("--n", type=positive_int, default=201,
                   help="frequencies, log-spaced from --fmin to --fmax (default 201)")
    p.add_argument("--freqs", help="comma-separated frequencies (Hz) instead of a log grid")
    p.add_argument("--json", action="store_true", help="print golden_tf.json layout")
    p.add_argument("-o", "--output", help="PNG to write (default <OPTIC>_response.png)")


def _compare(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind model compare``."""
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--optic", help="the optic (default: the file's only one, else ETMX)")
    p.add_argument("-o", "--output", default="geometric_vs_analytical.png",
                   help="PNG of both models' responses (default geometric_vs_analytical.png)")


def _model_config(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind model config``."""
    p.add_argument("model", type=existing,
                   help="the optic's state-space model (.mat: a struct a, b, c, d with "
                        "InputName and OutputName, or bare A..D)")
    p.add_argument("--optic", required=True, help="the optic's name in its channels, e.g. PR3")
    p.add_argument("--ifo", help="the channels' interferometer prefix (default: the naming "
                                 "table's, K1 for KAGRA's)")
    p.add_argument("--system", help="the channels' system (default: the naming table's, VIS "
                                    "for KAGRA's)")
    p.add_argument("--naming", type=existing,
                   help="a naming table: rules from test points to the model's names "
                        "(default: the one twind ships for --ifo, "
                        "twind/configs/kagra/naming.toml)")
    p.add_argument("-o", "--output", type=new_file(".toml"), required=True,
                   help="the configuration to write (never over a file); the model is named "
                        "relative to it, not copied")


def _simulate(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind simulate``."""
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--optics", help="comma-separated names, or 'all' (default: the file's "
                                    "only optic, else ETMX)")
    p.add_argument("--duration", type=positive, required=True, help="simulated seconds")
    p.add_argument("--seed", type=seed, default=0, help=SEED_HELP)
    p.add_argument("--block", type=positive, default=1.0, help="seconds per engine block")
    p.add_argument("--record", help="MCAP file to record every block to")
    p.add_argument("--max-hz", type=frequency, default=None,
                   help="a state-space optic: drop its modes above this (static part kept; "
                        "the error it costs is printed)")


def _serve(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind serve``."""
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--optics", default="all", help="comma-separated names, or 'all'")
    p.add_argument("--listen", action="append", help="endpoint (default tcp/127.0.0.1:7447)")
    p.add_argument("--connect", action="append", help="endpoint of a router or peer")
    p.add_argument("--mode", choices=("peer", "router", "client"),
                   help="Zenoh mode (default: the --zenoh-config file's, else peer)")
    p.add_argument("--zenoh-config", help="a Zenoh JSON5 configuration (TLS, access control)")
    p.add_argument("--record", help="folder for rotating MCAP recordings of the session")
    p.add_argument("--record-zenoh-config", metavar="FILE.json5",
                   help="the recorder's Zenoh configuration (behind an ACL router: "
                        "deploy/acl/recorder.json5)")
    p.add_argument("--speed", type=positive, default=1.0, help="twin seconds per wall second")
    p.add_argument("--block", type=positive, default=1 / 16, help="seconds per block")
    p.add_argument("--seed", type=seed, default=0, help=SEED_HELP)
    p.add_argument("--duration", type=positive, help="stop after this many twin seconds")


def _inject(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind inject``."""
    p.add_argument("channel", help="e.g. C1:SUS-ETMX_SUSPOS_EXC")
    p.add_argument("waveform", choices=("sine", "sweep", "noise", "multisine", "stream"),
                   help="the waveform (a stream's samples come from --file)")
    p.add_argument("--freq", type=float, help="Hz (sweep, multisine: lowest)")
    p.add_argument("--f-stop", type=float, help="Hz: sweep end, multisine highest")
    p.add_argument("--n-tones", type=positive_int, help="multisine tones")
    p.add_argument("--amp", type=float, help="peak amplitude (noise: RMS)")
    p.add_argument("--duration", type=float, help="seconds (inf: until stopped)")
    p.add_argument("--ramp", type=float, help="taper seconds at start and end")
    p.add_argument("--start", type=float, dest="start_gps", metavar="GPS",
                   help="GPS start (default: next block)")
    p.add_argument("--shape", help="noise: foton design shaping white noise")
    p.add_argument("--file", help="stream: text file of samples at the model rate")
    p.add_argument("--seed", type=seed, help="noise: the seed of its random numbers")
    bus_arguments(p)


def _stop(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind stop``."""
    p.add_argument("id", help="the excitation's id (as inject printed it), or 'all'")
    bus_arguments(p)


def _status(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind status``."""
    p.add_argument("--json", action="store_true", help="the status as JSON")
    bus_arguments(p)


def _record(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind record``."""
    p.add_argument("keyexprs", nargs="*", metavar="KEYEXPR",
                   help="data key expressions to record (default twin/**, every channel)")
    p.add_argument("-o", "--output", required=True, metavar="FILE.mcap",
                   help="file to write (with rotation: FILE-0001.mcap, FILE-0002.mcap, ...)")
    p.add_argument("--duration", type=float, metavar="S",
                   help="stop after S seconds (default: at SIGINT/SIGTERM)")
    p.add_argument("--connect", action="append", metavar="EP",
                   help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 "
                        "(repeatable; default tcp/127.0.0.1:7447 unless --listen)")
    p.add_argument("--listen", action="append", metavar="EP",
                   help="Zenoh endpoint to listen on (repeatable)")
    p.add_argument("--mode", choices=("peer", "client"), default="peer",
                   help="Zenoh mode (default peer)")
    p.add_argument("--rotate-mb", type=positive, metavar="N",
                   help="start a new file every N MB (1 MB = 10^6 bytes)")
    p.add_argument("--rotate-s", type=positive, metavar="S",
                   help="start a new file every S seconds of data (GPS)")
    p.add_argument("--ifo", default="C1", help="interferometer of the events and status "
                                               "keys (default C1)")
    p.add_argument("--no-events", action="store_true",
                   help="do not record twin/@/<IFO>/events")
    p.add_argument("--zenoh-config", metavar="FILE.json5",
                   help="a Zenoh configuration (credentials, TLS) to start from")
    p.add_argument("--parent", type=int, metavar="PID",
                   help="end the recording when process PID, which started this one, "
                        "exits or is killed (twind serve --record passes its own)")


def _replay(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind replay``."""
    p.add_argument("files", nargs="+", metavar="FILE",
                   help="recording: an MCAP file, a rotated set's name, or several files")
    p.add_argument("--rate", type=float, default=1.0, metavar="X",
                   help="speed-up: 2 is twice as fast; 0 or inf as fast as possible "
                        "(default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument("--connect", action="append", metavar="EP",
                   help="Zenoh endpoint to connect to (repeatable; default "
                        "tcp/127.0.0.1:7447 unless --listen)")
    p.add_argument("--listen", action="append", metavar="EP",
                   help="Zenoh endpoint to listen on (repeatable)")
    p.add_argument("--mode", choices=("peer", "client"), default="peer",
                   help="Zenoh mode (default peer)")
    p.add_argument("--ifo", help="interferometer of the events key (default the "
                                 "recording's)")
    p.add_argument("--no-events", action="store_true", help="do not publish events")


def _export(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind export``."""
    p.add_argument("inputs", nargs="+", metavar="FILE.mcap",
                   help="recording: an MCAP file, a rotated set's name, or several files")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="OUT.npz, OUT.h5 or OUT.hdf5 (never overwritten)")
    p.add_argument("--channels", nargs="+", metavar="CHANNEL",
                   help="channels to export, space- or comma-separated (default all)")


def _recover(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind recover``."""
    p.add_argument("input", metavar="IN.mcap", help="a killed or damaged recording")
    p.add_argument("-o", "--output", required=True, metavar="OUT.mcap",
                   help="the recovered file (never overwritten)")


def _view(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind view``."""
    p.add_argument("--connect", action="append",
                   help="Zenoh endpoint of the twin or its router (default tcp/127.0.0.1:7447)")
    p.add_argument("--zenoh-config", help="a Zenoh JSON5 configuration (credentials, TLS)")
    p.add_argument("--ifo", default="C1", help="the twin's interferometer prefix (default C1)")
    p.add_argument("--channels", help="comma-separated shell patterns, e.g. 'C1:SUS-ETMX_*' "
                                      "(default: every channel)")
    p.add_argument("--rate", type=positive, default=64.0, help="plotted rate in Hz (default 64)")
    p.add_argument("--duration", type=positive, help="stop after this many seconds (default: Ctrl-C)")
    sink = p.add_mutually_exclusive_group()
    sink.add_argument("--viewer", metavar="URL",
                      help="send to a running Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy")
    sink.add_argument("--save", metavar="FILE.rrd", help="write a .rrd file instead of viewing")
    sink.add_argument("--web", action="store_true",
                      help="serve the web viewer (http://localhost:9090) for a browser, e.g. on a "
                           "headless host")
    p.add_argument("--port", type=int, default=9876,
                   help="gRPC port of the spawned viewer or of --web (default 9876)")


def _rrd(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind rrd``."""
    p.add_argument("mcap", help="a session recorded by 'twind simulate --record' or 'twind record'")
    p.add_argument("-o", "--output", help="the .rrd to write (default: the MCAP's name, .rrd)")
    p.add_argument("--channels", help="comma-separated shell patterns (default: every channel)")
    p.add_argument("--rate", type=positive, default=256.0, help="plotted rate in Hz (default 256)")
    p.add_argument("--no-bode", action="store_true",
                   help="skip the IN1/EXC and IN2/EXC transfer functions of excited DOFs")


def _tf(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind tf``."""
    input_arguments(p)
    p.add_argument("--config", help="the optic's configuration: needed for a state-space "
                                    "model's (another site's) channel names")
    p.add_argument("-o", "--output", type=new_file(*TF_RESULTS),
                   help=".h5/.hdf5, .csv or .mat (MATLAB) results, or a .png Bode matrix")


def _fit(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind fit``."""
    input_arguments(p)
    p.add_argument("--config", help="twin config (TOML) holding the optic's nominal model")
    p.add_argument("--params", nargs="+", metavar="NAME",
                   help="parameters to fit (default: all nine of docs/model.md)")
    p.add_argument("--min-coherence", type=fraction, default=0.5,
                   help="IN1/EXC bins less coherent (averaged over neighbours) are unused")
    p.add_argument("-o", "--output", type=new_file(*FIGURES),
                   help=".png (.pdf, .svg): measured, nominal and fitted Bode matrix")
    p.add_argument("--truth", metavar="JSON",
                   help="a simulated optic's truth.json: also print (fitted - truth)/sigma")


def _diagnose(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind diagnose``."""
    input_arguments(p)
    p.add_argument("--config", help="twin config (TOML) holding the optic's nominal model")
    p.add_argument("-o", "--output", metavar="REPORT_DIR",
                   help="write PNGs, the JSON and an HTML summary here")
    p.add_argument("--push", action="append", metavar="ENDPOINT",
                   help="give the fitted (augmented) model to the running twin there")
    p.add_argument("--violin-pair", type=frequency, nargs=2, metavar=("F_A", "F_B"),
                   help="the optic's two first violin modes (Hz, e.g. from twind freeswing): "
                        "weigh their length and tension readings against the fitted "
                        "wire_asymmetry")
    p.add_argument("--budget", type=positive, default=None, metavar="SECONDS",
                   help="state-space optics: seconds after which no further change is tried "
                        "(default 90; the diagnosis says when it stopped)")


def _modes(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind modes``."""
    p.add_argument("table", nargs="?", help="CSV of measured modes (Hz): optic, POS, PIT, "
                                            "YAW, SIDE (default: the 40m's, 2020)")
    p.add_argument("--optic", nargs="+", metavar="NAME", help="optics (default: the table's)")
    p.add_argument("--config", help="twin config (TOML) holding the optics")
    p.add_argument("--candidates", action="store_true",
                   help="fit candidate physics for what the model misses (SIDE), optic by "
                        "optic, and weigh them over the optics")
    p.add_argument("--json", action="store_true", help="the numbers as JSON")


def _freeswing(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind freeswing``."""
    p.add_argument("input", nargs="*", help="a recording of a ringdown (MCAP; a session's "
                                            "files); default: ring the twin down, in "
                                            "process or at --connect")
    p.add_argument("--optic", default="ETMX", help="the optic (default ETMX)")
    p.add_argument("--config", help="twin config (TOML) holding the optic's model")
    p.add_argument("--start", type=float, metavar="GPS",
                   help="a recording: GPS start of the ringdown (default: its start)")
    p.add_argument("--duration", type=float,
                   help="seconds of ringdown: made on the twin (default 1000), or read from "
                        "a recording (default: to its end)")
    p.add_argument("--seed", type=seed, default=0, help="noise seed of the twin's ringdown")
    p.add_argument("--violin", type=frequency, nargs="?", const=0.0, metavar="HZ",
                   help="on the twin in process: ring a violin mode up through POS's LSC_EXC "
                        "(at HZ; default the model's mode POS drives most), then measure its "
                        "line's frequency and Q from the ringdown (--duration, default 400 s)")
    p.add_argument("--ring-up", type=float, default=1600.0, metavar="S",
                   help="--violin: seconds of drive (default 1600)")
    p.add_argument("--json", action="store_true", help="the numbers as JSON")
    p.add_argument("-o", "--output", type=new_file(*FIGURES),
                   help="PNG (PDF, SVG): OSEM spectra with the modes, and both input matrices")
    bus_arguments(p)


def _excite(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind excite``."""
    p.add_argument("--mode", choices=("coherence", "information"), default="coherence",
                   help="what the excitation is designed for (default coherence)")
    p.add_argument("--config", help="config file (default: the 40m file shipped with twind)")
    p.add_argument("--optic", default="ETMX", help="the optic (default ETMX)")
    p.add_argument("--dof", action="append", choices=DOFS, metavar="DOF",
                   help=f"DOF to excite, one of {', '.join(DOFS)}; repeat for several "
                        "(each measured on its own); default POS")
    p.add_argument("--band", type=float, nargs=2, metavar=("LO", "HI"), required=True,
                   help="frequency band (Hz) that must be coherent")
    p.add_argument("--coherence", type=fraction, default=0.7,
                   help="coherence to reach in every bin of the band (default 0.7)")
    p.add_argument("--averages", type=positive_int, default=10,
                   help="non-overlapping averages of the measurement (default 10)")
    p.add_argument("--bw", type=positive, default=0.01,
                   help="frequency resolution of the measurement, Hz (default 0.01)")
    p.add_argument("--confidence", type=fraction, default=0.95,
                   help="probability that a bin's estimate reaches the coherence "
                        "(sets the margin for the estimator's scatter; default 0.95)")
    p.add_argument("--all-responses", action="store_true",
                   help="make the IN1 of every --dof coherent with each excitation, "
                        "not only the excited DOF's own")
    p.add_argument("--rms", type=positive, help="RMS limit at EXC (default: the twin's)")
    p.add_argument("--peak", type=positive, help="peak limit at EXC (default: the twin's)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the noise request")
    p.add_argument("--params", nargs="+", metavar="NAME",
                   help="information: parameters to inform (default: all nine)")
    p.add_argument("--duration", type=positive, default=110.0,
                   help="information: seconds of measurement per DOF")
    p.add_argument("--period", type=positive, default=20.0,
                   help="information: multisine period (s); measure with bw = 1/period")
    p.add_argument("--json", action="store_true", help="print the design as JSON")
    p.add_argument("-o", "--output", metavar="FILE.png", type=new_file(*FIGURES),
                   help="plot of the required and designed ASD and the coherence")


def _campaign(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind campaign``."""
    p.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="measure a running twin (twind serve) at this Zenoh endpoint; "
                        "default: an in-process twin of the optic drifted by --drift")
    p.add_argument("--update", action="append", metavar="ENDPOINT",
                   help="push each round's fit into the twin at this endpoint")
    p.add_argument("--config", help="twin config (TOML): the nominal model")
    p.add_argument("--optic", default="ETMX", help="the optic (default ETMX)")
    p.add_argument("--ifo", default="C1", help="the twin's interferometer prefix (default C1)")
    p.add_argument("--dof", action="append", choices=DOFS, metavar="DOF",
                   help="excited DOF, repeatable (default POS, PIT, YAW)")
    p.add_argument("--band", type=float, nargs=2, default=(0.1, 10.0), metavar=("LO", "HI"),
                   help="band of the multisines, Hz (default 0.1 10)")
    p.add_argument("--rms", type=positive, default=10.0, help="RMS at each EXC")
    p.add_argument("--period", type=positive, default=20.0, help="multisine period (s)")
    p.add_argument("--averages", type=positive_int, default=5, help="periods per DOF per round")
    p.add_argument("--params", nargs="+", metavar="NAME",
                   help="parameters to identify (default: the nine twind fit fits)")
    p.add_argument("--target", type=positive, default=0.01,
                   help="relative sigma to reach on every identifiable parameter")
    p.add_argument("--max-rounds", type=positive_int, default=8,
                   help="rounds at most, if the target is not reached (default 8)")
    p.add_argument("--drift", type=positive, default=1.0,
                   help="in-process twin: scale of the built-in drift of the 'real' optic")
    p.add_argument("--seed", type=seed, default=0,
                   help="in-process twin: seed of its noise (default 0)")
    p.add_argument("--workdir", help="running twin: where the rounds' MCAP files go")
    p.add_argument("--json", action="store_true", help="the result as JSON")
    p.add_argument("-o", "--output", type=new_file(*FIGURES),
                   help=".png (.pdf, .svg): relative sigma per round")


def _demo(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind demo``."""
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--effect", default="actuator_pole",
                   choices=["coil_imbalance", "osem_imbalance", "loop_delay",
                            "actuator_pole", "wire_asymmetry", "bounce_roll"],
                   help="the effect the 'real' twin hides (default actuator_pole)")
    p.add_argument("-o", "--output", default="twind-demo",
                   help="directory for the recordings and reports (default twind-demo)")


def _bench(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind bench``."""
    p.add_argument("--suite", choices=BENCH_SUITES, default="engine",
                   help="engine: simulation speed; tf: twind tf on a written session; "
                        "pull: calibration of twind fit's sigmas; information: D-optimal "
                        "excitation against white noise on the twin; diagnose: twind "
                        "diagnose on the proof corpus (--route, --per-effect, --nulls); "
                        "rates: twind diagnose's claims, located bands and p-values on many "
                        "nulls at each setting (--nulls per setting, default 20, "
                        "--settings), and finds at the corpus' concealment (--per-effect, "
                        "--effects); "
                        "freeswing: twind freeswing on random drifted optics; statespace: "
                        "twind on KAGRA's state-space optics (--optic, default SRM,PRM): "
                        "nulls and moved modes measured open and closed loop (--nulls, "
                        "default 6, --per-effect: moved modes, default 4); commands: "
                        "--help, a refused input and inject, timed from process start "
                        "(--realisations runs each, default 5); kagra: twind diagnose on "
                        "KAGRA's real files in tests/data/kagra, scored against their "
                        "independent reference (--optic: comma-separated file names); "
                        "cases: realistic KAGRA cases made from the models and scored "
                        "against their truth (--optic, default SRM,PRM,BS; --per-effect: "
                        "cases per optic and kind, default 1)")
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--duration", type=float, default=None,
                   help="engine: simulated seconds per run (default 20); tf: seconds of "
                        "recording (default 3600)")
    p.add_argument("--workdir", help="tf: directory for the session file; statespace: for "
                                     "the diaggui files (default a temporary one)")
    p.add_argument("--keep", action="store_true", help="tf: keep the session file")
    p.add_argument("--realisations", type=positive_int, default=None,
                   help="pull: noise realisations (default 100); freeswing: optics (8)")
    p.add_argument("--route", choices=["xml", "mcap", "both"], default="xml",
                   help="diagnose: the corpus as diaggui XML sets or MCAP sessions")
    p.add_argument("--optic",
                   help="diagnose, rates: the optic of --config whose drifts make the "
                        "corpus (default ETMX); statespace: comma-separated optics")
    p.add_argument("--per-effect", type=count, default=None,
                   help="diagnose, rates: cases per effect (default 3)")
    p.add_argument("--nulls", type=count, default=None,
                   help="diagnose: drift-only cases (default 3); rates: nulls (default 20)")
    p.add_argument("--effects", help="diagnose, rates: comma-separated kinds to hide: catalogue "
                                     "effects, resonance (a body on the face), "
                                     "channel_filter (one channel's stage), pairs a+b "
                                     "(diagnose's default the catalogue's six, those three "
                                     "kinds and three pairs; rates' osem_imbalance,"
                                     "wire_asymmetry)")
    p.add_argument("--averages", type=positive_int,
                   help="diagnose: averages of the corpus measurement (default 10)")
    p.add_argument("--rms", type=positive,
                   help="diagnose: RMS of its excitation (counts; default 3)")
    p.add_argument("--excite", help="diagnose: comma-separated DOFs excited in turn "
                                    "(default POS,PIT,YAW; add SIDE for side_coupling)")
    p.add_argument("--bw", type=positive, help="pull: Welch resolution (Hz, default 0.02; "
                   "the LPM's record is as long as 10 averages of it); diagnose: the "
                   "corpus measurement's (default 0.01 for XML, example_null's; 0.05 for "
                   "MCAP); rates: one setting's nulls, case by case")
    p.add_argument("--estimator", choices=["welch", "lpm"], default=None,
                   help="pull: TF estimator (default welch); rates: the nulls' (with --bw, "
                        "one setting case by case instead of the table of settings)")
    p.add_argument("--settings", help="rates: comma-separated settings of the table, as it "
                                      "names them (default all eight: bins of 0.01, 0.02, "
                                      "0.05 and 0.1 Hz, 5 and 20 averages, half the "
                                      "excitation, LPM)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="pull: realisations measured and fitted side by side")
    p.add_argument("--no-marginal", action="store_true",
                   help="skip the 200 s - 20 s marginal speed of 'twind simulate'")


def _soak(p: argparse.ArgumentParser) -> None:
    """Arguments of ``twind soak``."""
    p.add_argument("--duration", type=positive, default=3600.0, help="seconds of serving")
    p.add_argument("--optics", default="all", help="comma-separated names, or 'all'")
    p.add_argument("--hostile", type=count, default=1000, help="malformed requests to send")
    p.add_argument("--port", type=int, default=17461,
                   help="loopback port the soak's twin listens on (default 17461)")
    p.add_argument("--config", help="twin config (TOML); default the shipped one with its "
                                    "watchdogs at 20 um, so that one drive trips one")
    p.add_argument("--load", type=count, default=0, metavar="N",
                   help="N busy processes share the cores with the twin (2: both cores)")
    p.add_argument("--suspend", type=positive, default=6.0, metavar="S",
                   help="seconds a second subscriber is suspended (SIGSTOP) at the end")
    fleet = p.add_argument_group("a fleet (several twins behind a router)")
    fleet.add_argument("--connect", metavar="ENDPOINT",
                       help="soak the twins already serving behind ENDPOINT instead of "
                            "starting one: per twin, its CPU, lag, losses and latency")
    fleet.add_argument("--zenoh-config", metavar="FILE",
                       help="with --connect: Zenoh configuration (credentials, TLS)")
    fleet.add_argument("--json", action="store_true", help="with --connect: print JSON")
    fleet.add_argument("--fleet", action="store_true",
                       help="build hosts as network namespaces (root) running deploy/: a "
                            "router, twin hosts splitting the ten optics, a recorder and a "
                            "control room, and soak them from the control room")
    fleet.add_argument("--layout", choices=("acl", "open"), default="acl",
                       help="with --fleet: deploy/acl (default) or the open layout")
    fleet.add_argument("--twin-hosts", type=positive_int, default=2,
                       help="with --fleet: twin hosts the optics are split between")


COMMANDS: tuple[Command, ...] = (
    Command("model", "suspension model responses; a configuration from a state-space model",
            subcommands=(
        Command("response", "plant, controller and closed-loop responses", _response,
                "twind.cli.model:cmd_model_response"),
        Command("compare", "geometric vs analytical model, with a plot", _compare,
                "twind.cli.model:cmd_model_compare"),
        Command("config", "a starting configuration of an optic from its state-space model's "
                "names, by the site's naming", _model_config,
                "twind.cli.model:cmd_model_config"))),
    Command("simulate", "run the twin as fast as possible", _simulate,
            "twind.cli.model:cmd_simulate"),
    Command("serve", "run the twin on Zenoh (embedded session)", _serve,
            "twind.cli.twin:cmd_serve"),
    Command("inject", "start an excitation on a running twin", _inject,
            "twind.cli.twin:cmd_inject"),
    Command("stop", "stop an excitation by id, or 'all'", _stop, "twind.cli.twin:cmd_stop"),
    Command("status", "status of a running twin", _status, "twind.cli.twin:cmd_status"),
    Command("record", "record twin channels to MCAP", _record,
            "twind.cli.recording:cmd_record"),
    Command("replay", "republish a recording on Zenoh", _replay,
            "twind.cli.recording:cmd_replay"),
    Command("export", "MCAP session to .npz or .h5", _export,
            "twind.cli.recording:cmd_export"),
    Command("recover", "a valid MCAP file from a killed or damaged recording", _recover,
            "twind.cli.recording:cmd_recover"),
    Command("view", "live twin channels in a Rerun viewer", _view,
            "twind.cli.view:cmd_view"),
    Command("rrd", "MCAP session to a Rerun .rrd (series, events, Bode)", _rrd,
            "twind.cli.view:cmd_rrd"),
    Command("tf", "transfer functions and the open-loop plant from diaggui XML or MCAP "
            "sessions", _tf, "twind.cli.measure:cmd_tf", counting("segment")),
    Command("fit", "fit the nominal physical parameters to measured TFs", _fit,
            "twind.cli.measure:cmd_fit", counting("evaluation")),
    Command("diagnose", "where the model misses, which physics it left out, and the fit "
            "with it", _diagnose, "twind.cli.measure:cmd_diagnose", counting("evaluation")),
    Command("modes", "free-swinging modes: measured, as configured, and with the geometry "
            "solved for them", _modes, "twind.cli.measure:cmd_modes"),
    Command("freeswing", "free-swinging health check: modes, Qs, OSEM gains, diagonalising "
            "input matrix", _freeswing, "twind.cli.measure:cmd_freeswing"),
    Command("excite", "design an excitation: a coherence in a band, or the most information",
            _excite, "twind.cli.design:cmd_excite"),
    Command("campaign", "identify an optic: design, inject, record, fit, redesign to a target",
            _campaign, "twind.cli.design:cmd_campaign", counting("evaluation")),
    Command("demo", "a 'real' twin with a concealed effect beside a nominal one: excited, "
            "recorded, diagnosed", _demo, "twind.cli.measure:cmd_demo", counting("evaluation")),
    Command("bench", "the benchmarks, every ratio measured side by side in one run", _bench,
            "twind.cli.lab:cmd_bench", lambda args: BENCH_PROGRESS.get(args.suite)),
    Command("soak", "serve, record, inject and attack; print the figures", _soak,
            "twind.cli.lab:cmd_soak"),
)
