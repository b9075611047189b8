"""The free-swinging health check on twin ringdowns: the modes and Qs of the optic that rang,
an OSEM imbalance recovered, and a recorded ringdown read back."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import signal

from twind.analysis.identification.freeswing import HALVES_SIGMA, analyse, eigenmodes, ringdown
from twind.analysis.identification.modes import modes_hz, with_params
from twind.cli import main
from twind.client import TwinClient
from twind.config import load_config
from twind.errors import TwindError
from twind.model.effects import with_effect
from servicekit import serving

IMBALANCE = {"gain_UL": 0.08, "gain_UR": -0.05, "gain_LL": 0.0, "gain_LR": -0.03}


def test_a_drifted_optic_with_an_osem_imbalance_is_read_from_its_ringdown() -> None:
    """Analysed with the nominal model: the drifted optic's eigenfrequencies, its Qs and its
    OSEM gains (the truth: the plant that rang)."""
    nominal = load_config(None, ["ETMX"]).optics["ETMX"]
    real = with_params(nominal, {"wire_length_m": 0.259, "b_m": 0.00085, "R1_m": 0.0074})
    real = type(real)(real.name, real.sus.updated(Q={"POS": 420, "PIT": 610, "YAW": 350,
                                                     "SIDE": 520}),
                      real.damping, real.noise, real.model, real.source)
    plant = with_effect(real.loop().plant, real.sus, "osem_imbalance", IMBALANCE)
    sen, rate = ringdown(real, 400.0, seed=3, plant=plant)
    found = analyse(nominal, sen, rate)
    truth = modes_hz(real)
    for dof, f in truth.items():
        assert abs(found.frequency_hz[dof] - f) < 1e-3, dof
        assert found.q[dof] == pytest.approx(real.sus.Q[dof], rel=0.2), dof
    g = np.array([1 + IMBALANCE[f"gain_{o}"] for o in ("UL", "UR", "LL", "LR")])
    g /= g.mean()
    got = np.array(list(found.osem_gains.values()))
    np.testing.assert_allclose(got - 1, g - 1, atol=0.35 * np.abs(g - 1).max())
    # the diagonalising matrix undoes the imbalance: UL's column is the smaller
    assert abs(found.input_matrix[0, 0]) < abs(found.input_matrix[0, 1])


@pytest.mark.slow
def test_twind_freeswing_rings_a_served_twin_down_and_puts_its_damping_back(capsys) -> None:  # noqa: ANN001
    """A served ETMX, drifted live (a longer wire, an OSEM imbalance) so that it is not the
    configured one: `twind freeswing --connect` finds the served optic's modes, Qs and
    OSEM gains, and leaves its damping gains as they were, no excitation running."""
    optic = load_config(None, ["ETMX"]).optics["ETMX"]
    drifted = with_params(optic, {"wire_length_m": 1.03 * optic.sus.wire_length_m})
    with serving("--optics", "ETMX", "--speed", "40") as endpoint, \
            TwinClient(connect=[endpoint]) as twin:
        twin.params("ETMX", wire_length_m=drifted.sus.wire_length_m)
        twin.params("ETMX", effect={"id": "osem_imbalance", "values": IMBALANCE})
        gains = {d: m.gain for d, m in twin.params("ETMX").filters.items()}
        assert main(["freeswing", "--connect", endpoint, "--duration", "260", "--json"]) == 0
        assert {d: m.gain for d, m in twin.params("ETMX").filters.items()} == gains
        assert twin.status().excitations == []
    shown = json.loads(capsys.readouterr().out)
    plant = with_effect(drifted.loop().plant, drifted.sus, "osem_imbalance", IMBALANCE)
    f_true, q_true = eigenmodes(drifted, plant)
    for dof, f in f_true.items():
        assert abs(shown["frequency_hz"][dof] - f) < 5 * shown["frequency_sigma_hz"][dof], dof
        assert shown["q"][dof] == pytest.approx(q_true[dof], rel=0.2), dof
    assert shown["frequency_hz"]["POS"] < modes_hz(optic)["POS"] - 0.01  # the served optic's
    g = np.array([1 + IMBALANCE[f"gain_{o}"] for o in ("UL", "UR", "LL", "LR")])
    g /= g.mean()
    got = np.array(list(shown["osem_gains"].values()))
    np.testing.assert_allclose(got - 1, g - 1, atol=0.35 * np.abs(g - 1).max())


def test_twind_freeswing_on_a_recorded_ringdown(tmp_path, capsys) -> None:  # noqa: ANN001
    from twind.bus.codec import SampleBlock
    from twind.channels import osem_channel
    from twind import OSEMS
    from twind.bus.session import zenoh_config
    from twind.recording.reader import as_array, getdata
    from twind.recording.session import RecordingError
    from twind.recording.writer import McapSession

    optic = load_config(None, ["ETMX"]).optics["ETMX"]
    sen, rate = ringdown(optic, 300.0, seed=1)
    sen, rate = signal.decimate(sen, 64, ftype="fir", axis=1), rate / 64  # a _DQ's 256 Hz
    path = tmp_path / "ringdown.mcap"
    n = int(rate) // 4
    with McapSession(path, "C1", {"optics": ["ETMX"]}) as f:
        for k in range(sen.shape[1] // n):
            for o, osem in enumerate(OSEMS):
                f.write_block(SampleBlock(osem_channel("C1", "ETMX", osem), 1.4e9 + k * n / rate,
                                          rate, k, sen[o, k * n:(k + 1) * n], "um").encode())
    names = [osem_channel("C1", "ETMX", o) for o in OSEMS]
    whole = as_array(getdata(names, None, source=path))[0]
    assert whole.shape == (5, sen.shape[1] // n * n)  # duration None: to the end
    with pytest.raises(RecordingError, match="needs a duration"):
        getdata(names, None, source=zenoh_config(connect=["tcp/127.0.0.1:9"], mode="client"))
    assert main(["freeswing", str(path), "--start", str(1.4e9 + 10), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    for dof, f in modes_hz(optic).items():
        assert abs(shown["frequency_hz"][dof] - f) < 2e-3
    with pytest.raises(TwindError, match="too short"):
        analyse(optic, sen[:, : int(20 * rate)], rate)


@pytest.mark.slow
def test_the_standard_errors_hold_the_errors_of_twin_ringdowns() -> None:
    """Over three noise realisations the frequency and Q errors against the plant's own
    eigenvalues are, in standard errors, of RMS about 1: the noise the modes take up after
    the kick is in the sigmas (without it the RMS was above 2)."""
    optic = load_config(None, ["ETMX"]).optics["ETMX"]
    f_true, q_true = eigenmodes(optic)
    pulls = []
    for seed in (30, 31, 32):
        sen, rate = ringdown(optic, 600.0, seed=seed)
        found = analyse(optic, sen, rate)
        for dof in f_true:
            assert found.frequency_sigma_hz[dof] > 0 and found.q_sigma[dof] > 0
            pulls += [(found.frequency_hz[dof] - f_true[dof]) / found.frequency_sigma_hz[dof],
                      (found.q[dof] - q_true[dof]) / found.q_sigma[dof]]
        # the two halves agree: the modes held still
        assert max(abs(x) for pair in found.halves.values() for x in pair) < HALVES_SIGMA
    assert 0.5 < np.sqrt(np.mean(np.square(pulls))) < 2.0, np.round(pulls, 2)
    # the last one with its time scale drifting by 1e-4 over the span (83 uHz of YAW):
    # the halves tell, and the lines say the standard errors understate
    t = np.arange(sen.shape[1]) / rate
    drifting = np.array([np.interp(t * (1 + 0.5e-4 * t / t[-1]), t, x) for x in sen])
    found = analyse(optic, drifting, rate)
    assert abs(found.halves["YAW"][0]) > HALVES_SIGMA
    assert any("understate" in line for line in found.lines())


def test_the_benchmark_reads_a_ringdown_too_short_to_halve(capsys) -> None:  # noqa: ANN001
    assert main(["bench", "--suite", "freeswing", "--realisations", "1", "--duration",
                 "300"]) == 0
    out = capsys.readouterr().out
    assert "optic 1: frequencies within" in out and "too short to halve" in out
    assert "errors in standard errors over 4 modes" in out
