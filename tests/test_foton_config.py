"""Damping filters read from a foton filter file instead of design strings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from twind import DOFS
from twind.config import CONFIG_DIR, load_optic
from twind.errors import ConfigError
from twind.loop.foton import NOMINAL_FM1, NOMINAL_FM2, NOMINAL_FM3, design_to_sos
from twind.loop.foton_file import FilterStage, write_filter_file
from twind.simulation.discretize import closed_loop_matrices

RATE = 16384.0
DESIGNS = [("velocity", NOMINAL_FM1), ("Cheby", NOMINAL_FM2), ("BounceRoll", NOMINAL_FM3)]


def _config_with_file(tmp_path: Path) -> Path:
    modules = {
        f"ETMX_SUS{dof}": [
            FilterStage(i, name, design_to_sos(design, RATE), design)
            for i, (name, design) in enumerate(DESIGNS)
        ]
        for dof in DOFS
    }
    write_filter_file(tmp_path / "C1SUSETMX.txt", modules, RATE)
    text = (CONFIG_DIR / "optics" / "ETMX.toml").read_text()
    kept = [ln for ln in text.splitlines() if not ln.startswith(("FM1 =", "FM2 =", "FM3 ="))]
    text = "\n".join(kept).replace("[damping]", '[damping]\nfoton_file = "C1SUSETMX.txt"', 1)
    path = tmp_path / "ETMX.toml"
    path.write_text(text)
    return path


def test_foton_file_runs_the_same_loop(tmp_path: Path) -> None:
    from_designs = load_optic(CONFIG_DIR / "optics" / "ETMX.toml").loop()
    from_file = load_optic(_config_with_file(tmp_path)).loop()
    A1 = closed_loop_matrices(from_designs, RATE)[0]
    A2 = closed_loop_matrices(from_file, RATE)[0]
    np.testing.assert_allclose(A2, A1, rtol=1e-9, atol=1e-12)


def test_model_follows_the_coefficients_not_a_stale_design(tmp_path: Path) -> None:
    """What runs is the file's coefficients; a design line may be out of date."""
    path = _config_with_file(tmp_path)
    filters = tmp_path / "C1SUSETMX.txt"
    filters.write_text(filters.read_text().replace(NOMINAL_FM1, 'zpk([0],[3],6.2832,"n")'))
    loop = load_optic(path).loop()
    reference = load_optic(CONFIG_DIR / "optics" / "ETMX.toml").loop()
    f = np.geomspace(0.1, 10, 30)
    k, k_ref = loop.controller(f), reference.controller(f)
    # the discrete filters differ from the continuous designs by the bilinear warping only
    assert 0 < np.max(np.abs(k / k_ref - 1)) < 1e-3


def test_missing_module_and_both_sources_are_errors(tmp_path: Path) -> None:
    path = _config_with_file(tmp_path)
    bad = tmp_path / "both.toml"
    bad.write_text(path.read_text().replace("[damping]", "[damping]\nFM4 = [\"x\", 'gain(2)']", 1))
    with pytest.raises(ConfigError, match="not both"):
        load_optic(bad)
    text = path.read_text().replace('name = "ETMX"', 'name = "ETMY"')
    other = tmp_path / "ETMY.toml"
    other.write_text(text)
    with pytest.raises(ConfigError, match="no filter module ETMY_SUSPOS"):
        load_optic(other)
