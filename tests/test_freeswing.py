"""The free-swinging health check on twin ringdowns: the modes and Qs of the optic that rang,
an OSEM imbalance recovered, and a recorded ringdown read back."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import signal

from twind.analysis.freeswing import analyse, ringdown
from twind.analysis.modes import modes_hz, with_params
from twind.cli import main
from twind.config import load_config
from twind.errors import TwindError
from twind.model.effects import with_effect

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


def test_twind_freeswing_on_a_recorded_ringdown(tmp_path, capsys) -> None:  # noqa: ANN001
    from twind.bus.codec import SampleBlock
    from twind.channels import osem_channel
    from twind.model.osem import OSEMS
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
    assert main(["freeswing", str(path), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    for dof, f in modes_hz(optic).items():
        assert abs(shown["frequency_hz"][dof] - f) < 2e-3
    with pytest.raises(TwindError, match="too short"):
        analyse(optic, sen[:, : int(20 * rate)], rate)
