"""Configuration files: the shipped ones equal the reference, bad ones fail with clear messages."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from twind.config import NOMINAL_ETMX, load_config, load_optic
from twind.errors import ConfigError

FORTY_M = ("ETMX", "ETMY", "ITMX", "ITMY", "BS", "PRM", "SRM", "MC1", "MC2", "MC3")


def test_nominal_etmx_equals_reference(nominal: dict) -> None:
    cfg = load_optic(NOMINAL_ETMX)
    sus = cfg.sus
    for key in ("mass_kg", "radius_m", "thickness_m", "I_pitch_kgm2", "I_yaw_kgm2", "I_roll_kgm2",
                "wire_length_m", "b_m", "R1_m", "R2_m", "vertical_stiffness_Npm", "osem_lever_m",
                "coil_N_per_ct", "side_coil_N_per_ct", "loop_delay_s", "sample_rate_hz"):
        assert getattr(sus, key) == pytest.approx(nominal[key], rel=1e-12), key
    assert sus.Q == pytest.approx(nominal["Q"], rel=1e-12)
    for dof, gain in nominal["damping_gain"].items():
        assert cfg.damping[dof].gain == pytest.approx(gain, rel=1e-12)
    assert cfg.noise.osem_m == 1e-10 and cfg.noise.sp_x_m == 2e-9 and cfg.noise.sp_phi_rad == 1e-9
    assert cfg.noise.floor_hz == nominal["noise_asd"]["f_floor_hz"]


def test_40m_config_has_every_sos_with_its_own_parameters() -> None:
    twin = load_config()
    assert tuple(twin.optics) == FORTY_M
    lengths = {o.sus.wire_length_m for o in twin.optics.values()}
    assert len(lengths) == len(FORTY_M)
    assert twin.select("ITMX,BS")[1].name == "BS"
    with pytest.raises(ConfigError, match="unknown optic"):
        load_config(None, ["ETMZ"])


def _edited(tmp_path: Path, old: str, new: str) -> Path:
    text = NOMINAL_ETMX.read_text()
    assert old in text, old
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(old, new, 1))
    return path


BAD = [
    ('b = "0.0007 m"', "", "suspension.b", "missing parameter"),
    ('wire_length = "0.248 m"', 'wire_length = "0.248 kg"', "suspension.wire_length", "wrong unit"),
    ('wire_length = "0.248 m"', 'wire_length = "248 mm"', None, None),  # a unit twind converts
    ('wire_length = "0.248 m"', "wire_length = 0.248", "suspension.wire_length", "has no unit"),
    ('wire_length = "0.248 m"', 'wire_lenght = "0.248 m"', "suspension.wire_lenght", "unknown key"),
    ('mass = "0.243 kg"', 'mass = "-0.243 kg"', "suspension.mass", "must be positive"),
    ('gain = "30 ct s/um"', 'gain = "-30 ct s/um"', "damping.POS.gain", "unstable"),
    ('FM2 = ["Cheby", \'zpk(', 'FM2 = ["Cheby", \'chebby1("LowPass",4,1,10)*zpk(', "damping.FM2",
     "unknown foton function 'chebby1'"),
    ('on = [1, 2, 3]', 'on = [1, 2, 4]', "damping.on", "FM4 is switched on but holds no filter"),
    ('POS = 500', 'POS = "500"', "suspension.Q.POS", "positive number"),
    ('[optic]', '[optic', "-", "not valid TOML"),
    ('loop_delay = "', 'input_matrix = [[0.25, 0.25, 0.25, 0.25]]\nloop_delay = "', "cds.input_matrix",
     "expected 4 rows of 5 finite numbers"),
]


@pytest.mark.parametrize(("old", "new", "key", "problem"), BAD)
def test_bad_config_names_file_key_problem(tmp_path: Path, old: str, new: str, key: str | None,
                                           problem: str | None) -> None:
    path = _edited(tmp_path, old, new)
    if key is None:
        assert load_optic(path).sus.wire_length_m == pytest.approx(0.248)
        return
    with pytest.raises(ConfigError) as err:
        load_optic(path)
    assert err.value.source == str(path)
    assert err.value.key == key
    assert problem in err.value.problem


def test_cli_reports_bad_config_without_traceback(tmp_path: Path) -> None:
    path = _edited(tmp_path, 'gain = "0.45 ct s/urad"', 'gain = "0.45 ct s/um/s"')
    proc = subprocess.run([sys.executable, "-m", "twind", "model", "response", "--json",
                           "--config", str(path)], capture_output=True, text=True, check=False)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert str(path) in proc.stderr and "damping.PIT.gain" in proc.stderr
    assert "unknown unit" in proc.stderr


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nothing.toml")


def test_an_input_matrix_set_in_the_front_end_is_the_plants(tmp_path: Path) -> None:
    rows = [[0.25] * 4 + [0.0], [13.0, 13.0, -13.0, -13.0, 0.0],
            [13.0, -13.0, 13.0, -13.0, 0.0], [0.0] * 4 + [1.0]]
    path = _edited(tmp_path, 'loop_delay = "', f"input_matrix = {rows}\nloop_delay = \"")
    cfg = load_optic(path)
    assert np.array_equal(cfg.cds_input_matrix(), rows)
    assert np.allclose(cfg.loop().plant.input_matrix, 1e6 * np.array(rows))
    nominal = load_optic(NOMINAL_ETMX)
    assert nominal.input_matrix is None
    assert nominal.cds_input_matrix()[1, 0] == pytest.approx(1 / (4 * 0.019))
