"""`twind simulate`: RMS and speed on stdout, an MCAP session a standard reader understands."""

from __future__ import annotations

import io
import re
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from twind.cli import main


def _run(args: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = main(args)
        except SystemExit as refused:  # by the parser
            code = refused.code
    return code, out.getvalue(), err.getvalue()


def test_simulate_records_every_block(tmp_path: Path) -> None:
    path = tmp_path / "session.mcap"
    code, out, _ = _run(["simulate", "--duration", "2", "--block", "0.5", "--seed", "3",
                         "--record", str(path)])
    assert code == 0
    rms = dict(re.findall(r"^(C1:SUS-ETMX_\S+)\s+rms\s+(\S+)", out, re.M))
    assert len(rms) == 24
    assert float(rms["C1:SUS-ETMX_SUSPOS_EXC"]) == 0.0
    assert 0 < float(rms["C1:SUS-ETMX_SUSPOS_IN1"]) < 10  # um: noise-driven, damped
    assert re.search(r"x real time", out)

    blocks: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, message, proto in reader.iter_decoded_messages():
            assert channel.topic == f"twin/{proto.channel}"
            assert message.sequence == proto.sequence
            blocks.setdefault(proto.channel, []).append(proto)
    assert len(blocks) == 24
    for blist in blocks.values():
        assert [b.sequence for b in blist] == [0, 1, 2, 3]
        assert all(b.rate_hz == 16384 and len(b.samples) == 8192 for b in blist)
        assert np.allclose(np.diff([b.gps_start for b in blist]), 0.5)
    in1 = np.concatenate([b.samples for b in blocks["C1:SUS-ETMX_SUSPOS_IN1"]])
    in2 = np.concatenate([b.samples for b in blocks["C1:SUS-ETMX_SUSPOS_IN2"]])
    assert np.array_equal(in1, in2)  # EXC is zero
    # the printed RMS (4 significant digits) is the recorded samples' RMS
    assert np.isclose(np.sqrt(np.mean(in1**2)), float(rms["C1:SUS-ETMX_SUSPOS_IN1"]), rtol=1e-3)

    code, _, err = _run(["simulate", "--duration", "1", "--record", str(path)])
    assert code == 2 and "does not overwrite" in err


def test_simulate_rejects_bad_arguments() -> None:
    code, _, err = _run(["simulate", "--duration", "-1"])
    assert code == 2 and "argument --duration: must be a positive number" in err
    code, _, err = _run(["simulate", "--duration", "1", "--optics", "ETMZ"])
    assert code == 2 and "unknown optic" in err


def test_simulate_rejects_inputs_that_would_hang_or_crash(tmp_path: Path) -> None:
    for args, message in [
        (["--duration", "1e-6"], "at least one sample"),
        (["--duration", "1", "--block", "1e-5"], "at least one sample"),
        (["--duration", "1", "--block", "0"], "argument --block: must be a positive number"),
        (["--duration", "1", "--optics", "ETMX,ETMX"], "named twice"),
        (["--duration", "1", "--record", str(tmp_path / "no" / "dir.mcap")], "No such file"),
    ]:
        code, _, err = _run(["simulate", *args])
        assert code == 2 and message in err and "Traceback" not in err, (args, err)


def test_model_response_rejects_bad_frequencies() -> None:
    for args, message in [(["--freqs", "a,b"], "comma-separated numbers"),
                          (["--n", "1"], "--n >= 2"), (["--freqs", "1,-2"], "positive")]:
        code, _, err = _run(["model", "response", "--json", *args])
        assert code == 2 and message in err, (args, err)
