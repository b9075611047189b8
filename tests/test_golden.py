"""`twind model response --json` of the nominal ETMX against tests/data/golden_tf.json."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from contextlib import redirect_stdout

import numpy as np
import pytest
from conftest import complex_array

from twind.cli import main
from twind.config import NOMINAL_ETMX, load_optic
from twind.loop.damping import sensitivity

KEYS = ("plant_IN1_per_OUT", "controller_diag", "closed_loop_IN1_per_EXC", "closed_loop_IN2_per_EXC")


def _response(args: list[str]) -> dict:
    buf = io.StringIO()
    with redirect_stdout(buf):
        assert main(["model", "response", "--json", "--config", str(NOMINAL_ETMX), *args]) == 0
    return json.loads(buf.getvalue())


def assert_matches(ours: np.ndarray, gold: np.ndarray, rtol: float = 1e-6) -> float:
    """Every element to `rtol` relative; elements that are round-off in the golden file
    (below 1e-12 of the largest element at that frequency: exact zeros of the model that
    its matrix inversion left as ~1e-18) must be round-off in ours too."""
    axes = tuple(range(1, gold.ndim))
    scale = np.abs(gold).max(axis=axes, keepdims=True)
    structural_zero = np.abs(gold) < 1e-12 * scale
    rel = np.abs(ours - gold) / np.where(structural_zero, 1.0, np.abs(gold))
    assert np.all(rel[~structural_zero] < rtol), rel[~structural_zero].max()
    assert np.all(np.abs(ours[structural_zero]) < 1e-12 * np.broadcast_to(scale, gold.shape)[structural_zero])
    return float(rel[~structural_zero].max())


def test_json_reproduces_golden(golden: dict) -> None:
    ours = _response(["--fmin", "0.05", "--fmax", "50", "--n", "201"])
    np.testing.assert_allclose(ours["frequency_hz"], golden["frequency_hz"], rtol=1e-12)
    assert ours["dofs"] == golden["dofs"]
    worst = {k: assert_matches(complex_array(ours[k]), complex_array(golden[k])) for k in KEYS}
    assert max(worst.values()) < 1e-9  # the model is the golden model, not an approximation
    for dof, f in golden["uncoupled_frequencies_hz"].items():
        assert ours["uncoupled_frequencies_hz"][dof] == pytest.approx(f, rel=1e-9)


def test_explicit_frequencies(golden: dict) -> None:
    f = golden["frequency_hz"][::50]
    ours = _response(["--freqs", ",".join(repr(x) for x in f)])
    gold = complex_array(golden["closed_loop_IN2_per_EXC"])[::50]
    assert_matches(complex_array(ours["closed_loop_IN2_per_EXC"]), gold)


def test_golden_check_can_fail(golden: dict) -> None:
    """A 1e-5 change of one parameter must break the comparison."""
    cfg = load_optic(NOMINAL_ETMX)
    f = np.asarray(golden["frequency_hz"])
    loop = cfg.loop()
    loop.modules["POS"].gain *= 1 + 1e-5
    with pytest.raises(AssertionError):
        assert_matches(loop.responses(f)["closed_loop_IN2_per_EXC"],
                       complex_array(golden["closed_loop_IN2_per_EXC"]))


@pytest.mark.slow
def test_console_script_png(tmp_path) -> None:  # noqa: ANN001
    out = tmp_path / "etmx.png"
    proc = subprocess.run([sys.executable, "-m", "twind", "model", "response", "-o", str(out),
                           "--n", "50"], capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sensitivity_equals_the_inverse_and_refuses_a_singular_loop() -> None:
    """The compiled ``(I - P K)^-1`` against LAPACK's, on matrices that need row exchanges
    (a zero first pivot) and on a loop that is singular at one frequency."""
    rng = np.random.default_rng(3)
    P = rng.standard_normal((50, 4, 4)) + 1j * rng.standard_normal((50, 4, 4))
    k = rng.standard_normal((50, 4)) + 1j * rng.standard_normal((50, 4))
    P[0] = np.eye(4)[[1, 0, 2, 3]] + np.eye(4)  # I - P K has a zero (0, 0) entry
    k[0] = 1.0
    want = np.linalg.inv(np.eye(4) - P * k[:, None, :])
    assert np.allclose(sensitivity(P, k), want, rtol=1e-10, atol=1e-12 * np.abs(want).max())
    P[7], k[7] = np.eye(4), 1.0
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        sensitivity(P, k)


REFERENCE_MODES = [(0.689, 4.9), (0.847, 5.4), (1.073, 6.1), (1.075, 6.1)]
"""The nominal ETMX's closed-loop suspension modes (Hz, Q) as the reference model states them
(the seed's model description, alongside golden_tf.json; tests/data/README.md)."""


@pytest.mark.slow
def test_model_response_prints_the_reference_closed_loop_modes(tmp_path, capsys) -> None:  # noqa: ANN001
    assert main(["model", "response", "--config", str(NOMINAL_ETMX), "--n", "20", "-o",
                 str(tmp_path / "r.png")]) == 0
    printed = [line.split() for line in capsys.readouterr().out.splitlines()
               if line.startswith("closed-loop mode")]
    assert [(float(w[2]), float(w[5])) for w in printed] == REFERENCE_MODES
