"""The input matrix measured from a recording's IN1 and OSEM readings and checked against the
configuration's before the plant is read: twin recordings made with a front-end matrix that
differs from the configuration (OSEM cables swapped, a row left from a diagonalisation)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from measurekit import record_excited_session

from twind.analysis.diagnose import diagnose
from twind.analysis.estimation.tf import from_session
from twind.analysis.identification.inmatrix import (
    EXACT,
    TOLERANCE,
    check_input_matrix,
    recorded_input_matrix,
)
from twind.config import OpticConfig, load_config

AMPS = {"POS": 2.0, "PIT": 5.0, "YAW": 5.0}


@pytest.fixture(scope="module")
def etmx() -> OpticConfig:
    return load_config(None, "ETMX").select("ETMX")[0]


def with_matrix(cfg: OpticConfig, m: np.ndarray) -> OpticConfig:
    return replace(cfg, input_matrix=tuple(map(tuple, m)))


@pytest.fixture(scope="module")
def pit_row(etmx: OpticConfig, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A recording whose front end's PIT row has UR 20 % high and LL 20 % low."""
    m = etmx.cds_input_matrix()
    m[1, 1] *= 1.2
    m[1, 2] *= 0.8
    path = tmp_path_factory.mktemp("inmatrix") / "pit.mcap"
    return record_excited_session(with_matrix(etmx, m), path, AMPS, seconds=55), m


def test_a_null_recording_is_as_configured(etmx: OpticConfig, tmp_path: Path) -> None:
    path = record_excited_session(etmx, tmp_path / "null.mcap", {"POS": 2.0}, seconds=10)
    check = recorded_input_matrix([path], etmx)
    assert check.checked and check.same, check.lines()
    assert check.seconds == pytest.approx(10.0)
    assert np.allclose(check.measured, etmx.cds_input_matrix(), atol=1e-9)
    assert check.config(etmx) is etmx
    assert "as configured" in check.lines()[0]


def test_swapped_cables_are_named_in_the_rows_they_change(etmx: OpticConfig,
                                                          tmp_path: Path) -> None:
    m = etmx.cds_input_matrix()
    m[:, [0, 1]] = m[:, [1, 0]]  # UL and UR swapped: only YAW's row changes
    path = record_excited_session(with_matrix(etmx, m), tmp_path / "swap.mcap", {"POS": 2.0},
                                  seconds=10)
    check = recorded_input_matrix([path], etmx)
    assert check.rows == ["YAW"]
    assert check.differs[2].tolist() == [True, True, False, False, False]
    assert np.allclose(check.measured, m, atol=1e-9)
    assert np.allclose(check.config(etmx).cds_input_matrix(), m, atol=1e-9)
    assert "YAW's row differs from the configuration at UL, UR" in check.lines()[0]


@pytest.mark.slow
def test_a_wrong_row_is_read_as_physics_unless_it_is_measured_first(
        etmx: OpticConfig, pit_row: tuple[Path, np.ndarray]) -> None:
    path, truth = pit_row
    tfs = from_session([path], bw=0.1)
    blind = diagnose(tfs, etmx)
    assert not blind.consistent  # the wrong row looks like the suspension's misfit
    check = recorded_input_matrix([path], etmx)
    assert check.rows == ["PIT"]
    assert np.allclose(check.measured[1], truth[1], atol=1e-9)
    d = diagnose(tfs, etmx, input_matrix=check)
    assert d.consistent, d.lines()
    assert d.summary().startswith("the input matrix differs from the configuration in PIT")
    assert d.final.chi2_nu < 1.5 < blind.nominal.chi2_nu
    assert d.read_through(etmx).input_matrix is not None
    assert d.to_json()["input_matrix"]["differs"] == ["PIT"]


@pytest.mark.slow
def test_fit_says_it_on_the_command_line(pit_row: tuple[Path, np.ndarray]) -> None:
    path, _ = pit_row
    out = subprocess.run([sys.executable, "-m", "twind", "fit", str(path), "--bw", "0.1",
                          "--json"], capture_output=True, text=True, check=True).stdout
    got = json.loads(out)["input_matrix"]
    assert got["differs"] == ["PIT"] and got["checked"]


def test_rounding_is_not_a_difference_and_a_filter_is_not_a_matrix(etmx: OpticConfig) -> None:
    rng = np.random.default_rng(1)
    sen = rng.standard_normal((5, 4096)) * [[3.0], [2.0], [1.0], [0.5], [1.0]]
    m = etmx.cds_input_matrix()
    in1 = (m @ sen).astype(np.float32).astype(float)  # a data system's float32 test points
    check = check_input_matrix(in1, sen.astype(np.float32).astype(float), etmx, 256.0)
    assert check.checked and check.same, check.lines()
    worst = np.abs(check.measured - m).max(axis=1) / np.abs(m).max(axis=1)
    assert np.all(worst < TOLERANCE)
    filtered = in1.copy()
    filtered[0] = np.convolve(in1[0], [0.5, 0.5], mode="same")
    check = check_input_matrix(filtered, sen, etmx, 256.0)
    assert not check.checked
    assert check.residual[0] > EXACT and "POS IN1 is not a fixed combination" in check.why


def test_what_is_not_recorded_is_said(etmx: OpticConfig, tmp_path: Path) -> None:
    from twind.bus.codec import SampleBlock
    from twind.recording.writer import McapSession

    path = tmp_path / "in1.mcap"
    with McapSession(path, "C1", {"optics": ["ETMX"]}) as f:
        for k in range(4):
            f.write_block(SampleBlock("C1:SUS-ETMX_SUSPOS_IN1", 1.4e9 + k, 256.0, k,
                                      np.zeros(256), "um").encode())
    check = recorded_input_matrix([path], etmx)
    assert not check.checked and check.same
    assert "C1:SUS-ETMX_SUSPIT_IN1" in check.why
    assert check.lines()[0].startswith("input matrix: not checked")
