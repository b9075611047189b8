"""Files as a site writes them, and an optic twind does not ship: stored channels (``_DQ``)
read as their test points, KAGRA's real BS files read through their lock banks, the line a
configuration lacks told from the site's naming rules, and a configuration written from a
state-space model's names (``twind model config``) that maps what the shipped ones map and
measures a renamed PRM end to end."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from twind.analysis.estimation.diaggui import write_fft_measurement
from twind.analysis.estimation.tfset import TFError
from twind.analysis.statespace.measurement import read_plant
from twind.channels import C1, Convention
from twind.cli import main
from twind.config import CONFIG_DIR, load_config
from twind.config.draft import write_config
from twind.config.naming import UnmappedReadbackWarning, load_naming
from twind.errors import ConfigError, TwindError

from conftest import REFERENCE

KAGRA = CONFIG_DIR / "kagra"
DATA = REFERENCE / "kagra"
K1 = Convention("K1", "VIS")


def _file(path: Path, exc: str, channels: list[str], h: np.ndarray) -> Path:
    """A diaggui FFT file exciting `exc` and reading `channels` with TFs `h` (channels, nf)
    on 0.05-10 Hz, coherence 0.99."""
    f = np.linspace(0.05, 10.0, h.shape[1])
    return write_fft_measurement(path, exc, channels, f, np.ones_like(f), h,
                                 np.full(h.shape, 0.99), 10)


def _config(tmp_path: Path, name: str, drop: str = "") -> Path:
    """A copy of the shipped `name`.toml without line `drop`, naming the shipped model."""
    text = (KAGRA / f"{name}.toml").read_text()
    assert not drop or drop in text
    text = text.replace(drop + "\n", "") if drop else text
    text = text.replace(f'file = "{name}_safe.mat"',
                        f'file = "{(KAGRA / f"{name}_safe.mat").as_posix()}"')
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


# ------------------------------------------------------------------------------ stored channels
def test_a_stored_channel_is_its_test_point_and_the_40m_names_are_unchanged() -> None:
    assert K1.parse("K1:VIS-PR3_IM_DAMP_L_IN1_DQ") == ("PR3", "IM_DAMP_L_IN1")
    assert K1.parse("K1:VIS-BS_TM_OPLEV_PIT_DIAG_DQ") == ("BS", "TM_OPLEV_PIT_DIAG")
    assert K1.parse("K1:VIS-BS_TM_LOCK_L_EXC") == ("BS", "TM_LOCK_L_EXC")
    assert C1.parse("C1:SUS-ETMX_SUSPOS_IN1") == ("ETMX", "SUSPOS_IN1")
    assert C1.parse("K1:VIS-BS_TM_LOCK_L_EXC") is None


def test_the_real_srm_file_saved_from_stored_data_reads_as_saved_live(tmp_path) -> None:  # noqa: ANN001
    """KAGRA's SRM file with its readbacks renamed as stored channels gives the same plant."""
    text = (DATA / "SRM_TMP_200722.xml").read_text()
    stored, n = re.subn(r"(K1:VIS-SRM_[A-Z0-9_]*_(?:IN1|DIAG))(?![A-Z0-9_])", r"\1_DQ", text)
    assert n > 100
    (tmp_path / "stored.xml").write_text(stored)
    srm = load_config(KAGRA / "SRM.toml").optics["SRM"]
    live, dq = (read_plant([p], srm) for p in (DATA / "SRM_TMP_200722.xml",
                                                 tmp_path / "stored.xml"))
    assert dq.readbacks == live.readbacks and len(dq.readbacks) == 12
    assert np.array_equal(dq.H, live.H, equal_nan=True)


# ------------------------------------------------------------------------------ real BS files
def test_kagra_bs_files_are_read_through_the_lock_banks() -> None:
    bs = load_config(KAGRA / "BS.toml").optics["BS"]
    plant = read_plant([DATA / "BS_TMP_exc_20200730a.xml", DATA / "BS_TML_exc_20200730a.xml"],
                       bs)
    assert plant.drives == ("TM_LOCK_P", "TM_LOCK_L") and len(plant.readbacks) == 12
    assert plant.channels["TM_LOCK_P"] == "K1:VIS-BS_TM_LOCK_P_EXC"
    i = plant.readbacks.index("TM_OPLEV_PIT_DIAG")
    assert plant.coherent()[:, i, 0].sum() > 1000  # the optical lever reads the pitch drive


# ------------------------------------------------------------------------------ the lines to add
def test_a_drive_the_configuration_lacks_is_told_the_line_to_add(tmp_path) -> None:  # noqa: ANN001
    bs = load_config(_config(tmp_path, "BS", 'TM_LOCK_Y = "exc_TMY"')).optics["BS"]
    path = _file(tmp_path / "yaw.xml", "K1:VIS-BS_TM_LOCK_Y_EXC",
                 ["K1:VIS-BS_TM_OPLEV_YAW_DIAG"], np.ones((1, 50)))
    with pytest.raises(TFError) as err:
        read_plant([path], bs)
    assert str(err.value) == (
        f"{path}: K1:VIS-BS_TM_LOCK_Y_EXC is not a drive of BS.toml: add TM_LOCK_Y = "
        '"exc_TMY" to its [drives] (the model input guessed from KAGRA\'s naming; check it)')
    other = _file(tmp_path / "other.xml", "K1:VIS-BS_TM_WHIRL_Y_EXC",
                  ["K1:VIS-BS_TM_OPLEV_YAW_DIAG"], np.ones((1, 50)))
    with pytest.raises(TFError, match=r'add TM_WHIRL_Y = "MODEL INPUT" to its \[drives\]'):
        read_plant([other], bs)


def test_a_readback_the_configuration_lacks_is_noted_with_its_line(tmp_path) -> None:  # noqa: ANN001
    bs = load_config(_config(tmp_path, "BS", 'IP_BLEND_LVDTL_IN1 = "LVDT_IPL"')).optics["BS"]
    path = _file(tmp_path / "ip.xml", "K1:VIS-BS_IP_TEST_L_EXC",
                 ["K1:VIS-BS_IP_BLEND_LVDTL_IN1_DQ", "K1:VIS-BS_IP_BLEND_LVDTT_IN1_DQ"],
                 np.ones((2, 50)))
    with pytest.warns(UnmappedReadbackWarning,
                      match=r'K1:VIS-BS_IP_BLEND_LVDTL_IN1 is not a readback of BS.toml, left '
                            r'out: add IP_BLEND_LVDTL_IN1 = "LVDT_IPL" to its \[readbacks\]'):
        plant = read_plant([path], bs)
    assert plant.readbacks == ("IP_BLEND_LVDTT_IN1",)


def test_a_configuration_points_at_its_naming_table(tmp_path) -> None:  # noqa: ANN001
    table = tmp_path / "naming.toml"
    table.write_text((KAGRA / "naming.toml").read_text().replace('site = "KAGRA"',
                                                                 'site = "a lab"'))
    path = _config(tmp_path, "BS")
    path.write_text(path.read_text().replace('system = "VIS"',
                                             'system = "VIS"\nnaming = "naming.toml"'))
    assert load_config(path).optics["BS"].naming.site == "a lab"
    path.write_text(path.read_text().replace('naming = "naming.toml"', 'naming = "no.toml"'))
    with pytest.raises(ConfigError, match=r"channels.naming: no naming table .*no.toml"):
        load_config(path)
    table.write_text('[naming]\nsite = "x"\nifo = "X1"\nsystem = "S"\n[fields]\ndof = ["L"]\n'
                     '[[drives]]\npoint = "{stage}_TEST_{dof}"\ninput = "exc_{dof}"\n')
    with pytest.raises(ConfigError, match=r"drives\[0\].point: uses \{stage\}, which "
                                          r"\[fields\] does not define"):
        load_naming(table)


# ------------------------------------------------------------------------------ your own optic
@pytest.mark.parametrize("name", ["SRM", "PRM", "BS"])
def test_a_written_configuration_maps_what_the_shipped_one_does(name, tmp_path) -> None:  # noqa: ANN001
    draft = write_config(KAGRA / f"{name}_safe.mat", name, tmp_path / f"{name}.toml")
    ours = load_config(tmp_path / f"{name}.toml").optics[name]
    shipped = load_config(KAGRA / f"{name}.toml").optics[name]
    assert dict(ours.drives) == dict(shipped.drives)
    assert dict(ours.readbacks) == dict(shipped.readbacks)
    assert dict(ours.shapes) == dict(shipped.shapes)
    assert {m: (s.drive, s.filters.gain) for m, s in ours.loops.items()} == \
        {m: (s.drive, s.filters.gain) for m, s in shipped.loops.items()}
    assert ours.model.source.endswith(f"{name}_safe.mat") and not list(tmp_path.glob("*.mat"))
    assert "accGndL" in draft.unmapped_inputs
    assert any(n.startswith("IFO_") for n in draft.unmapped_outputs)
    check = next(c for c in draft.checks if c.drive == "IM_TEST_P")
    assert check.readback == "IM_DAMP_P_IN1" and 0.1 < check.response < 1


def test_a_configuration_is_never_written_over(tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "PR3.toml"
    out.write_text("mine")
    with pytest.raises(TwindError, match="exists; twind does not overwrite"):
        write_config(KAGRA / "PRM_safe.mat", "PR3", out)
    with pytest.raises(SystemExit):
        main(["model", "config", str(KAGRA / "PRM_safe.mat"), "--optic", "PR3", "-o", str(out)])
    assert "exists; twind does not overwrite" in capsys.readouterr().err
    assert out.read_text() == "mine"
    with pytest.raises(TwindError, match="--optic 'PR-3': a channel name's part is letters"):
        write_config(KAGRA / "PRM_safe.mat", "PR-3", tmp_path / "bad.toml")
    assert not (tmp_path / "bad.toml").exists()


@pytest.fixture(scope="module")
def pr3(tmp_path_factory) -> Path:  # noqa: ANN001
    """A PRM model renamed PR3 and its configuration, written by ``twind model config``."""
    folder = tmp_path_factory.mktemp("pr3")
    shutil.copy(KAGRA / "PRM_safe.mat", folder / "PR3_safe.mat")
    assert main(["model", "config", str(folder / "PR3_safe.mat"), "--optic", "PR3", "-o",
                 str(folder / "PR3.toml")]) == 0
    return folder / "PR3.toml"


def test_twind_model_config_prints_the_dc_check_and_what_it_could_not_map(pr3, capsys) -> None:  # noqa: ANN001
    main(["model", "config", str(pr3.parent / "PR3_safe.mat"), "--optic", "PR3", "-o",
          str(pr3.parent / "again.toml")])
    out = capsys.readouterr().out
    assert re.search(r"IM_TEST_P\s+-> IM_DAMP_P_IN1\s+0\.385", out)
    assert re.search(r"BF_TEST_L\s+-> BF_DAMP_L_IN1\s+0\.0296", out)
    assert "inputs accGndL" in out and "IFO_LTM" in out
    text = pr3.read_text()
    assert 'file = "PR3_safe.mat"' in text and "[damping.IM_DAMP_P]" in text
    assert 'IM_TEST_P = "exc_IMP"  # ctrl_typeBp/exc_IMP: {stage}_TEST_{dof}' in text


def test_a_renamed_prm_is_measured_under_its_own_name(pr3, tmp_path, capsys) -> None:  # noqa: ANN001
    optic = load_config(pr3).optics["PR3"]
    assert optic.convention == K1 and optic.naming.site == "KAGRA"
    reads = [f"IM_DAMP_{d}_IN1" for d in "LTVRPY"] + ["TM_OPLEV_PIT_DIAG"]
    f = np.linspace(0.05, 10.0, 200)
    h = optic.model.response(f, ["exc_IMP"], [optic.readbacks[r] for r in reads])[:, :, 0].T
    path = _file(tmp_path / "PR3_IMP.xml", "K1:VIS-PR3_IM_TEST_P_EXC",
                 [f"K1:VIS-PR3_{r}_DQ" for r in reads], h)
    assert main(["tf", "--config", str(pr3), str(path), "--json"]) == 0
    tf = json.loads(capsys.readouterr().out)
    assert tf["optic"] == "PR3" and tf["drives"] == ["IM_TEST_P"]
    assert tf["readbacks"] == reads and tf["channels"]["IM_TEST_P"] == "K1:VIS-PR3_IM_TEST_P_EXC"
    got = np.array(tf["plant"]["re"]) + 1j * np.array(tf["plant"]["im"])
    assert np.allclose(got[:, :, 0], h.T, rtol=1e-5, atol=0)
    assert main(["model", "response", "--config", str(pr3), "--json", "--n", "20"]) == 0
    modes = json.loads(capsys.readouterr().out)["modes"]
    assert any(m["label"] == "IM P" for m in modes)
