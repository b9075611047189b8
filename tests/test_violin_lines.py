"""Violin modes measured as the 40m would: rung up through the excitation past the damping
filters (LSC_EXC), then let ring down; their lines found in the OSEM readings with their
frequencies and Qs (twind.analysis.identification.lines), and ``twind freeswing`` reporting
them from a recording."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy import signal

from twind import DOFS, OSEMS
from twind.analysis.identification.lines import find_lines, violin_lines, violin_ringdown
from twind.bus.codec import SampleBlock
from twind.channels import drive_channel, osem_channel
from twind.cli import main
from twind.config import load_config
from twind.model.violin import violin_modes
from twind.recording.writer import McapSession
from twind.simulation.engine import Engine
from twind.simulation.noise import NoiseSpec

RATE = 16384


@pytest.fixture(scope="module")
def violin_etmx():  # noqa: ANN201
    cfg = load_config(None, ["ETMX"]).optics["ETMX"]
    return replace(cfg, sus=replace(cfg.sus, wire=replace(cfg.sus.wire, modes=2)))


@pytest.fixture(scope="module")
def rung(violin_etmx):  # noqa: ANN001, ANN201
    """ETMX's violin mode POS drives most, rung through LSC_EXC at the DAC's range for
    1600 s, then 400 s of its ringdown (noise on): (OSEM readings, the mode's frequency and
    Q from the plant's eigenvalues, the readings of a minute of the undriven twin)."""
    sen, rate, f_hz = violin_ringdown(violin_etmx, seed=11)
    assert rate == RATE
    _, f0, q0 = min(violin_modes(violin_etmx.mechanics()), key=lambda m: abs(m[1] - f_hz))
    quiet = Engine([violin_etmx.loop()], {"ETMX": violin_etmx.noise}, seed=12).step(60 * RATE)
    return sen, f0, q0, quiet.sen[0]


def test_lsc_exc_drives_the_coils_past_the_damping_filters(violin_etmx) -> None:  # noqa: ANN001
    """With the damping gains at zero an excitation at EXC drives nothing and one past the filters
    drives the plant, unless the watchdog has tripped; with them on, IN1 per LSC_EXC is the
    loop's ``(I - P K)^-1 P`` (from the continuous model, not the engine) within 0.1 % (3e-5
    once the pendulum's transient has gone, 0.4 % with 4 s of it), and OUT stays the damping
    filters' output alone."""
    cfg = load_config(None, ["ETMX"]).optics["ETMX"]
    n, f = 24 * RATE, 3.0
    t = np.arange(n) / RATE
    drive = np.zeros((1, len(DOFS), n))
    drive[0, 0] = 10.0 * np.sin(2 * np.pi * f * t)
    off = Engine([cfg.loop()], NoiseSpec(enabled=False))
    for dof in DOFS:
        off.set_gain("ETMX", dof, 0.0, 0.0)
    assert not np.any(off.step(n, exc=drive).in1)
    assert np.any(off.step(n, lsc=drive).in1[0, 0])
    off.trip("ETMX")
    assert not np.any(off.step(n, lsc=drive).in1)
    engine = Engine([cfg.loop()], NoiseSpec(enabled=False))
    engine.step(30 * RATE)  # nothing moves: the start is at rest
    block = engine.step(n, lsc=drive)
    late = slice(12 * RATE, n)  # the loop's transient gone
    got = _phasor(block.in1[0, 0, late], t[late], f) / _phasor(drive[0, 0, late], t[late], f)
    want = cfg.loop().responses(np.array([f]))["closed_loop_IN1_per_LSC"][0, 0, 0]
    assert abs(got / want - 1) < 1e-3
    # OUT is K (IN1 + EXC): no drive of its own in it
    out = _phasor(block.out[0, 0, late], t[late], f) / _phasor(drive[0, 0, late], t[late], f)
    k = cfg.loop().responses(np.array([f]))["controller_diag"][0, 0]
    assert abs(out / (k * want) - 1) < 1e-3


def _phasor(x: np.ndarray, t: np.ndarray, f: float) -> complex:
    return complex(2 * np.mean(x * np.exp(-2j * np.pi * f * t)))


def test_a_violin_mode_rung_through_lsc_exc_rings_down_at_its_frequency_and_q(
        rung, violin_etmx) -> None:  # noqa: ANN001
    """The line of the mode rung is found in the OSEM readings at the plant's eigenfrequency
    within 5 standard errors and with its Q within 3; a minute of noise before the drive
    holds no line; the line is named by the model's first violin mode."""
    sen, f0, q0, quiet = rung
    assert find_lines(quiet, RATE, OSEMS) == []
    report = violin_lines(violin_etmx, sen, RATE)
    line = report.found[0]
    assert line.state == "ringing down"
    assert abs(line.frequency_hz - f0) < 5 * line.frequency_sigma_hz
    assert line.frequency_sigma_hz < 1e-4
    assert abs(line.q - q0) < 3 * line.q_sigma
    assert line.q_sigma < 0.3 * q0
    assert report.nearest(line)[1] == 1
    assert all(other.amplitude < 0.1 * line.amplitude for other in report.found[1:])


def test_twind_freeswing_reports_the_violin_lines_of_a_recording(rung, violin_etmx, tmp_path,
                                                                capsys) -> None:  # noqa: ANN001
    """A recording of the ringdown's OSEMs at 2048 Hz, with the damping on: ``twind
    freeswing`` says it finds no free pendulum mode and reports the violin line, its
    frequency and Q, named by the shipped ETMX's wires (rigid in its plant)."""
    sen, f0, q0, _ = rung
    sen, rate = signal.decimate(sen, 8, ftype="fir", axis=1), RATE / 8
    path = tmp_path / "violin.mcap"
    n = int(rate)
    with McapSession(path, "C1", {"optics": ["ETMX"]}) as f:
        for k in range(sen.shape[1] // n):
            for o, osem in enumerate(OSEMS):
                f.write_block(SampleBlock(osem_channel("C1", "ETMX", osem), 1.4e9 + k, rate, k,
                                          sen[o, k * n:(k + 1) * n], "um").encode())
    assert main(["freeswing", str(path), "--json"]) == 0
    out = capsys.readouterr()
    assert "no free mode found" in out.err and "lines above 100 Hz only" in out.err
    shown = json.loads(out.out)["lines"]
    line = shown["found"][0]
    assert abs(line["frequency_hz"] - f0) < 5 * line["frequency_sigma_hz"]
    assert line["state"] == "ringing down" and abs(line["q"] - q0) < 3 * line["q_sigma"]
    named = line["model"]
    assert named["n"] == 1 and abs(named["frequency_hz"] / f0 - 1) < 1e-3
    assert main(["freeswing", str(path)]) == 0
    text = capsys.readouterr().out
    assert "n=1 at" in text and f"{line['frequency_hz']:.4f} Hz" in text
    # the shipped ETMX's wires are rigid: no violin mode to ring
    assert main(["freeswing", "--violin"]) == 2
    assert "rigid wires" in capsys.readouterr().err


def test_an_lsc_exc_channel_is_named_as_the_40m_names_it() -> None:
    assert drive_channel("C1", "ETMX", "POS") == "C1:SUS-ETMX_LSC_EXC"
    assert drive_channel("C1", "ITMY", "YAW") == "C1:SUS-ITMY_ASCYAW_EXC"
