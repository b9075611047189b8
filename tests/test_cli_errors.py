"""Bad input on the command line ends as one line that names the input and says what to do,
exit status 2, no traceback, and no half-written output left behind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from twind.bus.codec import SampleBlock
from twind.cli import main
from twind.recording.reader import getdata
from twind.recording.session import RecordingError
from twind.recording.writer import McapSession
from servicekit import free_port

from conftest import REFERENCE

XML = str(REFERENCE / "example_null" / "ETMX_POS_exc.xml")


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """An empty file, a text file and a recording cut inside its first chunk."""
    folder = tmp_path_factory.mktemp("bad")
    whole = folder / "whole.mcap"
    with McapSession(whole, "C1", {"optics": ["ETMX"]}) as f:
        for k in range(64):
            f.write_block(SampleBlock("C1:SUS-ETMX_ULSEN_OUT", 1.4e9 + k, 1024.0, k,
                                      np.random.default_rng(k).normal(size=1024), "um").encode())
    files = {"empty": b"", "text": b"hello, not a recording",
             "cut": whole.read_bytes()[: whole.stat().st_size // 4]}
    for name, data in files.items():
        (folder / f"{name}.mcap").write_bytes(data)
    return {name: str(folder / f"{name}.mcap") for name in files}


def _one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Run twind with `argv`; its error line (warnings may come before it)."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and ".rs:" not in err, err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and err.strip().endswith(errors[0]), err
    return errors[0]


@pytest.mark.parametrize("name", ["empty", "text", "cut"])
def test_rrd_refuses_what_is_not_a_recording_and_leaves_no_rrd(recordings, name, capsys) -> None:  # noqa: ANN001
    line = _one_line_error(capsys, ["rrd", recordings[name]])
    assert recordings[name] in line
    assert ("not an MCAP file" in line) if name != "cut" else ("no sample block" in line)
    assert not list(Path(recordings[name]).parent.glob("*.rrd"))


def test_tf_on_an_empty_file_says_it_is_not_a_recording(recordings, capsys) -> None:  # noqa: ANN001
    assert "not an MCAP file (empty" in _one_line_error(capsys, ["tf", recordings["empty"]])


@pytest.mark.parametrize(("band", "says"), [(["1", "0.1"], "LO must be below HI"),
                                            (["100", "200"], "the measurement covers 0-30 Hz")])
def test_tf_refuses_a_band_it_cannot_show(band, says, capsys) -> None:  # noqa: ANN001
    assert says in _one_line_error(capsys, ["tf", XML, "--band", *band])


def test_a_band_that_is_not_a_frequency_is_refused_by_the_parser(capsys) -> None:  # noqa: ANN001
    with pytest.raises(SystemExit) as stop:
        main(["tf", XML, "--band", "nan", "3"])
    assert stop.value.code == 2
    assert "not a frequency in Hz: 'nan'" in capsys.readouterr().err


def test_endpoints_and_an_absent_twin_are_told_in_words(capsys) -> None:  # noqa: ANN001
    line = _one_line_error(capsys, ["serve", "--listen", "garbage", "--duration", "1"])
    assert "'garbage' is not a Zenoh endpoint" in line and "tcp/127.0.0.1:7447" in line
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    line = _one_line_error(capsys, ["status", "--connect", endpoint, "--timeout", "1"])
    assert endpoint in line and "is `twind serve` running there?" in line


def test_getdata_takes_an_endpoint_for_the_bus() -> None:
    """A string that is an endpoint (and no file) is the bus, not a file name."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(RecordingError, match=f"cannot reach the bus at .*{endpoint}"):
        getdata("C1:SUS-ETMX_ULSEN_OUT", 1.0, source=endpoint, timeout=1.0)


def test_version_and_help_for_every_option(capsys) -> None:  # noqa: ANN001
    import argparse

    from twind import __version__
    from twind.cli import build_parser

    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out.strip() == f"twind {__version__}"

    def silent(parser: argparse.ArgumentParser, path: str) -> list[str]:
        """Options without help, or whose help hides a default (a number or a word)."""
        out = []
        for action in parser._actions:  # argparse has no public walk over subcommands
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    out += silent(sub, f"{path} {name}")
                continue
            name = f"{path} {'/'.join(action.option_strings) or action.dest}"
            default = action.default
            shown = parser.formatter_class(path)._get_help_string(action) or ""
            if not action.help or (isinstance(default, int | float | str)
                                   and not isinstance(default, bool)
                                   and default is not argparse.SUPPRESS
                                   and "default" not in shown):
                out.append(name)
        return out

    assert silent(build_parser(), "twind") == []
    with pytest.raises(SystemExit):
        main(["tf", "--help"])
    assert "Welch resolution (Hz) (default: 0.01)" in capsys.readouterr().out


def test_bench_offers_the_suites_it_runs() -> None:
    """The declared --suite choices (light, for --help) and the suites run are one list."""
    from twind.cli.commands import BENCH_PROGRESS, BENCH_SUITES
    from twind.cli.lab import SUITES

    assert tuple(SUITES) == BENCH_SUITES and set(BENCH_PROGRESS) < set(SUITES)


@pytest.mark.parametrize(("argv", "says"), [
    (["tf", "{null}", "--bw", "0"], "argument --bw: must be a positive number, got '0'"),
    (["tf", "{null}", "--bw", "-1"], "argument --bw: must be a positive number, got '-1'"),
    (["tf", "{null}", "--overlap", "1"], "argument --overlap: must be below 1"),
    (["fit", "{null}", "--min-coherence", "1.5"], "argument --min-coherence: must be a number "
                                                 "from 0 to 1"),
    (["serve", "--speed", "0"], "argument --speed: must be a positive number"),
    (["bench", "--suite", "rates", "--nulls", "-2"], "argument --nulls: must be a whole number"),
])
def test_a_number_out_of_range_is_refused_naming_the_option(argv, says, capsys) -> None:  # noqa: ANN001
    null = str(next((REFERENCE / "example_null").glob("*.xml")))
    with pytest.raises(SystemExit) as exit_:
        main([a.format(null=null) for a in argv])
    assert exit_.value.code == 2
    assert says in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "says"), [
    (["tf", "missing.xml"], "argument inputs: no such input: missing.xml"),
    (["diagnose", "missing.mcap"], "argument inputs: no such input: missing.mcap"),
    (["tf", "{null}", "-o", "x.pdf"], "x.pdf: give a .h5, .hdf5, .csv, .mat or .png file"),
    (["fit", "{null}", "-o", "x.jpeg"], "x.jpeg: give a .png, .pdf or .svg file"),
])
def test_inputs_and_outputs_are_checked_before_any_work(argv, says) -> None:  # noqa: ANN001
    """Refused by the parser, before the analysis is imported (it takes seconds)."""
    import subprocess
    import sys

    null = str(next((REFERENCE / "example_null").glob("*.xml")))
    code = ("import sys\nfrom twind.cli import main\ntry:\n    main(sys.argv[1:])\n"
            "except SystemExit as e:\n    print(e.code, 'twind.analysis' in sys.modules)\n")
    run = subprocess.run([sys.executable, "-c", code, *(a.format(null=null) for a in argv)],
                         capture_output=True, text=True, check=True)
    assert run.stdout.split() == ["2", "False"]
    assert says in run.stderr
