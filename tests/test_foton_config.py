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


def _config_with_file(tmp_path: Path, with_designs: bool = True) -> Path:
    modules = {
        f"ETMX_SUS{dof}": [
            FilterStage(i, name, design_to_sos(design, RATE), design if with_designs else None)
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


def test_foton_file_gives_the_same_loop(tmp_path: Path) -> None:
    from_designs = load_optic(CONFIG_DIR / "optics" / "ETMX.toml").loop()
    from_file = load_optic(_config_with_file(tmp_path)).loop()
    f = np.geomspace(0.05, 50, 60)
    a, b = from_designs.responses(f), from_file.responses(f)
    for key in a:
        np.testing.assert_allclose(b[key], a[key], rtol=1e-12, atol=0)
    A1 = closed_loop_matrices(from_designs, RATE)[0]
    A2 = closed_loop_matrices(from_file, RATE)[0]
    np.testing.assert_allclose(A2, A1, rtol=1e-9, atol=1e-12)


def test_coefficient_only_stages_model_the_discrete_filter(tmp_path: Path) -> None:
    loop = load_optic(_config_with_file(tmp_path, with_designs=False)).loop()
    reference = load_optic(CONFIG_DIR / "optics" / "ETMX.toml").loop()
    f = np.geomspace(0.1, 10, 30)
    k, k_ref = loop.controller(f), reference.controller(f)
    # the discrete filters differ from the continuous designs by the bilinear warping only
    assert np.max(np.abs(k / k_ref - 1)) < 1e-3
    assert np.max(np.abs(k / k_ref - 1)) > 0  # and they are not the designs


def test_missing_module_and_both_sources_are_errors(tmp_path: Path) -> None:
    path = _config_with_file(tmp_path)
    bad = tmp_path / "both.toml"
    bad.write_text(path.read_text().replace("[damping]", f"[damping]\nFM4 = [\"x\", 'gain(2)']", 1))
    with pytest.raises(ConfigError, match="not both"):
        load_optic(bad)
    text = path.read_text().replace('name = "ETMX"', 'name = "ETMY"')
    other = tmp_path / "ETMY.toml"
    other.write_text(text)
    with pytest.raises(ConfigError, match="no filter module ETMY_SUSPOS"):
        load_optic(other)
