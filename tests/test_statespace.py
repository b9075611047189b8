"""A plant from a state-space file: KAGRA's published models read, their responses against
python-control's, the site's channel names, the measured plant (open and closed loop), the
engine, and the diagnosis on files the time-domain engine made (nulls and a moved mode) and on
KAGRA's real SRM measurement."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from types import SimpleNamespace

import control
import numpy as np
import pytest
import scipy.io
from scipy import signal
from threadpoolctl import threadpool_info, threadpool_limits

from twind.analysis.estimation.tfset import TFError
from twind.analysis.statespace.diagnose import diagnose_plant
from twind.analysis.statespace import fit as fit_module
from twind.analysis.statespace.fit import fit_baseline, start_gains
from twind.analysis.statespace.measurement import read_plant
from twind.channels import Convention
from twind.cli import main
from twind.config import CONFIG_DIR, load_config
from twind.errors import ConfigError
from twind.lab.plant_measurement import measure, moved, peak
from twind.model.statespace import StateSpaceError, modal_form, read_mat
from twind.simulation.statespace import truncation_error

from conftest import REFERENCE

KAGRA = CONFIG_DIR / "kagra"
SRM_FILE = REFERENCE / "kagra" / "SRM_TMP_200722.xml"
IM = [f"exc_IM{d}" for d in "LTVRPY"]
OSEM = [f"OSEM_IM{d}" for d in "LTVRPY"]


@pytest.fixture(scope="module")
def srm():  # noqa: ANN201 - StateSpaceOptic
    return load_config(KAGRA / "SRM.toml").optics["SRM"]


# ------------------------------------------------------------------------------ the model
@pytest.mark.parametrize("name", ["SRM", "PRM", "BS"])
def test_the_modal_form_answers_as_python_control_does(name: str) -> None:
    ss = read_mat(KAGRA / f"{name}_safe.mat")
    outs = [*OSEM, "OpLev_TMP"]
    mf = modal_form(ss, IM, outs)
    cols, rows = [ss.input_index(i) for i in IM], [ss.output_index(o) for o in outs]
    ref = control.ss(ss.a, ss.b[:, cols], ss.c[rows], ss.d[np.ix_(rows, cols)])
    f = np.geomspace(0.02, 200, 300)
    theirs = np.moveaxis(ref(2j * np.pi * f), 2, 0)
    ours = mf.response(f)
    scale = np.abs(theirs).max(axis=(1, 2), keepdims=True)  # each frequency's largest
    assert (np.abs(ours - theirs) / scale).max() < 1e-6
    assert mf.condition < 1e6  # 1e20 for the eigenvectors: split by blocks, not diagonalised


def test_modes_are_labelled_by_the_dof_that_carries_them(srm) -> None:  # noqa: ANN001
    modal = srm.modal(("TM_TEST_P",), ("IM_DAMP_P_IN1",))
    near = {round(m.f_hz, 1): m.label for m in modal.modes}
    # a suspension's bounce and roll modes: the test mass vertical and roll
    assert near[11.6] == "TM V" and near[15.9] == "TM R"


def test_dropping_high_modes_costs_what_truncation_error_says(srm) -> None:  # noqa: ANN001
    full = srm.modal(tuple(f"IM_TEST_{d}" for d in "LTVRPY"),
                     tuple(f"IM_DAMP_{d}_IN1" for d in "LTVRPY"))
    reduced, dropped = full.truncated(30.0)
    assert dropped > 0
    assert truncation_error(full, reduced, 10.0) < 0.05
    assert truncation_error(full, reduced, 100.0) > truncation_error(full, reduced, 10.0)


def test_bare_matrices_and_their_names_are_read(tmp_path) -> None:  # noqa: ANN001
    a = np.array([[0.0, 1.0], [-(2 * np.pi) ** 2, -0.1]])
    path = tmp_path / "bare.mat"
    scipy.io.savemat(path, {"A": a, "B": [[0.0], [1.0]], "C": [[1.0, 0.0]], "D": [[0.0]],
                            "InputName": np.array(["force"], dtype=object),
                            "OutputName": np.array(["x"], dtype=object)})
    ss = read_mat(path)
    assert ss.inputs == ("force",) and ss.outputs == ("x",)
    modal = modal_form(ss, ["force"], ["x"])
    assert modal.modes[0].f_hz == pytest.approx(1.0, rel=1e-3)


@pytest.mark.parametrize(("content", "words"), [
    ({"x": np.eye(2)}, "no state-space model"),
    ({"A": np.eye(2), "B": np.ones((3, 1)), "C": np.ones((1, 2)), "D": [[0.0]]}, "2 rows"),
    ({"sys": {"a": [[-1.0]], "b": [[1.0]], "c": [[1.0]], "d": [[0.0]], "Ts": 0.01}}, "discrete"),
])
def test_a_file_that_is_no_usable_model_is_named(tmp_path, content, words) -> None:  # noqa: ANN001
    path = tmp_path / "bad.mat"
    scipy.io.savemat(path, content)
    with pytest.raises(StateSpaceError, match=words):
        read_mat(path)


def test_a_name_the_model_lacks_is_a_config_error(tmp_path) -> None:  # noqa: ANN001
    text = (KAGRA / "SRM.toml").read_text().replace('TM_TEST_P = "exc_TMP"',
                                                    'TM_TEST_P = "exc_TMQ"')
    (tmp_path / "SRM_safe.mat").write_bytes((KAGRA / "SRM_safe.mat").read_bytes())
    (tmp_path / "SRM.toml").write_text(text)
    with pytest.raises(ConfigError, match=r"drives.TM_TEST_P: .*no input 'exc_TMQ'"):
        load_config(tmp_path / "SRM.toml")


def test_a_site_names_its_channels() -> None:
    k1 = load_config(KAGRA / "k1.toml")
    assert k1.convention == Convention("K1", "VIS") and set(k1.optics) == {"SRM", "PRM", "BS"}
    assert load_config().convention == Convention("C1", "SUS")
    assert k1.optics["PRM"].channel("IM_DAMP_L_IN1") == "K1:VIS-PRM_IM_DAMP_L_IN1"


# ------------------------------------------------------------------------------ the engine
def test_the_engine_answers_as_the_model_does(srm) -> None:  # noqa: ANN001
    rate = 512.0
    engine = srm.engine(rate_hz=rate, closed=())
    x = np.random.default_rng(0).standard_normal(int(rate * 256))
    block = engine.step(x.size, {"TM_TEST_P_EXC": x})
    f, pxy = signal.csd(x, block.channels["TM_OPLEV_PIT_DIAG"], fs=rate, nperseg=int(rate * 32))
    _, pxx = signal.welch(x, fs=rate, nperseg=int(rate * 32))
    band = (f > 1.5) & (f < 10)
    h = pxy[band] / pxx[band]
    zoh = np.exp(-1j * np.pi * f[band] / rate)  # the hold's half cycle
    model = srm.model.response(f[band], ["exc_TMP"], ["OpLev_TMP"])[:, 0, 0] * zoh
    assert np.median(np.abs(h / model - 1)) < 0.01


# ------------------------------------------------------------------------------ measurements
@pytest.fixture(scope="module")
def files(tmp_path_factory, srm):  # noqa: ANN001, ANN201 - dict of paths
    """diaggui files the engine made: a null and a moved mode through TM_TEST_P, and the
    IM pitch plant open and closed loop."""
    folder = tmp_path_factory.mktemp("kagra")
    out = {}
    model, f_true = moved(srm.model, 4.92, 0.88)
    for name, drive, truth, closed, noise in (("null", "TM_TEST_P", None, (), 1e-2),
                                              ("moved", "TM_TEST_P", model, (), 1e-2),
                                              ("open", "IM_TEST_P", None, (), 1e-3),
                                              ("closed", "IM_DAMP_P", None, None, 1e-3)):
        out[name] = measure(srm, drive, folder / f"{name}.xml", model=truth, seed=7,
                            rate_hz=1024.0, noise=noise, closed=closed)
    out["f_true"] = f_true
    # the IM L mode moved, seen through all six loops: the others damp it and shift its peak
    model, out["f_true_closed"] = moved(srm.model, 1.246, 1.14)
    out["moved_closed"] = measure(srm, "IM_DAMP_L", folder / "moved_closed.xml", model=model,
                                  seed=8, rate_hz=1024.0, noise=1e-2, closed=None)
    return out


@pytest.mark.slow
def test_a_closed_loop_file_gives_the_plant_of_the_open_loop_one(files, srm) -> None:  # noqa: ANN001
    a, b = read_plant([files["open"]], srm), read_plant([files["closed"]], srm)
    assert b.drives == ("IM_DAMP_P",) and "IM_DAMP_P" in b.loops
    i = a.readbacks.index("IM_DAMP_P_IN1")
    ha, hb = a.H[:, i, 0], b.H[:, i, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.hypot(a.sigma[:, i, 0] / np.abs(ha), b.sigma[:, i, 0] / np.abs(hb))
    good = (rel < 0.02) & (a.frequency_hz > 0)
    assert good.sum() > 100
    w = 1 / rel[good] ** 2
    assert abs(np.sum(w * (hb[good] / ha[good] - 1)) / np.sum(w)) < 0.05
    # and the controller, OUT/IN2, is the configuration's where it is measured
    k, _ = b.loops["IM_DAMP_P"].controller()
    expected = srm.loops["IM_DAMP_P"].filters.build().response(a.frequency_hz)
    sel = (a.frequency_hz > 0.5) & (a.frequency_hz < 5)
    assert np.median(np.abs(k[sel] / expected[sel] - 1)) < 0.05


@pytest.mark.slow
def test_a_file_of_another_optic_is_refused_by_name(files) -> None:  # noqa: ANN001
    prm = load_config(KAGRA / "PRM.toml").optics["PRM"]
    with pytest.raises(TFError, match="expected one excitation of PRM named like K1:VIS-PRM_"):
        read_plant([files["null"]], prm)


@pytest.mark.slow
def test_a_null_claims_nothing_and_a_moved_mode_is_found(files, srm) -> None:  # noqa: ANN001
    null = diagnose_plant(read_plant([files["null"]], srm), srm)
    assert null.consistent and not null.effects
    plant = read_plant([files["moved"]], srm)
    d = diagnose_plant(plant, srm)
    claim = d.chosen[0]
    assert claim.effect.family == "mode_frequency"
    mode = d.modal.modes[claim.effect.target[0]]
    assert mode.f_hz == pytest.approx(4.92, rel=1e-3) and mode.label == "IM P"
    found = mode.f_hz * math.exp(d.final.own(claim.effect)["log_f"])
    i = plant.readbacks.index("IM_DAMP_P_IN1")
    assert found == pytest.approx(peak(plant.frequency_hz, plant.H[:, i, 0], files["f_true"]),
                                  rel=0.02)
    assert found == pytest.approx(files["f_true"], rel=0.002)
    assert d.nominal.chi2_nu / d.final.chi2_nu >= 2
    # the mode moved by 15 % leaves no readback the model reaches uncalibrated
    assert not d.uncalibrated()


@pytest.mark.slow
def test_a_mode_moved_is_found_through_the_closed_loops(files, srm) -> None:  # noqa: ANN001
    plant = read_plant([files["moved_closed"]], srm)
    d = diagnose_plant(plant, srm, max_effects=0)  # the modes moved together, no more
    claim = next(c for c in d.chosen if c.effect.family == "mode_frequency")
    mode = d.modal.modes[claim.effect.target[0]]
    assert mode.label == "IM L"
    found = mode.f_hz * math.exp(d.final.own(claim.effect)["log_f"])
    assert found == pytest.approx(files["f_true_closed"], rel=0.005)
    before, after, _ = claim.local
    assert before / after >= 2
    # started where each was found, the moves shared the IM L peak and stopped at 16
    assert d.final.chi2_nu < 3


# ------------------------------------------------------------------------------ the real SRM
@pytest.mark.slow
def test_kagra_srm_the_ip_mode_moved_and_im_v_reads_im_p(srm) -> None:  # noqa: ANN001
    plant = read_plant([SRM_FILE], srm)
    d = diagnose_plant(plant, srm)
    moved_modes = {d.modal.modes[c.effect.target[0]].f_hz: c for c in d.chosen
                   if c.effect.family == "mode_frequency"}
    pitch = next(c for f, c in moved_modes.items() if abs(f - 4.92) < 0.01)
    found = 4.92016 * math.exp(d.final.own(pitch.effect)["log_f"])
    i = plant.readbacks.index("IM_DAMP_P_IN1")
    assert found == pytest.approx(peak(plant.frequency_hz, plant.H[:, i, 0], 4.18), rel=0.02)
    # one drive: the mode's amplitude and IM P's calibration reach the data as a product
    assert d.traded(pitch, d.final)["amplitude"][0] == "calibration IM_DAMP_P_IN1"
    assert "trades against the calibration IM_DAMP_P_IN1" in d.describe(pitch)
    cross = [c for c in d.chosen if c.effect.family == "cross_coupling"]
    assert any(plant.readbacks[c.effect.target[0]] == "IM_DAMP_V_IN1" for c in cross)
    assert d.nominal.chi2_nu / d.final.chi2_nu > 2
    # IM P's own stage (a likelihood ratio of hundreds, traded against the common low-pass)
    # stays through the pruning, and with it the fit reaches the noise
    stages = [c for c in d.chosen if c.effect.family == "channel_response"]
    assert [plant.readbacks[c.effect.target[0]] for c in stages] == ["IM_DAMP_P_IN1"]
    assert d.final.chi2_nu < 2
    # the pitch drive's yaw share: a number where the data determine it, none where not
    share = next(c for c in d.chosen if c.effect.family == "drive_coupling")
    assert "TM_OPLEV_YAW_DIAG -" in d.describe(share) and "+-" in d.describe(share)
    blind = replace(d.final, sigma=np.full_like(d.final.sigma, np.nan))
    words = d.describe(share, blind)
    assert "TM_OPLEV_YAW_DIAG" in words and "do not determine" in words and "%" not in words


# ------------------------------------------------------------------------------ commands
@pytest.mark.slow
def test_twind_tf_and_diagnose_on_a_kagra_file(files, capsys) -> None:  # noqa: ANN001
    config = str(KAGRA / "SRM.toml")
    assert main(["tf", "--config", config, str(files["moved"]), "--json"]) == 0
    tf = json.loads(capsys.readouterr().out)
    assert tf["drives"] == ["TM_TEST_P"] and tf["coherent_bands"]["IM_DAMP_P_IN1/TM_TEST_P"]
    assert main(["diagnose", "--config", config, str(files["null"]), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["consistent"] and d["coherent"]["IM_DAMP_P_IN1/TM_TEST_P"]


def test_a_kagra_optic_takes_diaggui_files_only(tmp_path, capsys) -> None:  # noqa: ANN001
    path = tmp_path / "rec.mcap"
    path.write_bytes(b"")
    assert main(["tf", "--config", str(KAGRA / "SRM.toml"), str(path)]) == 2
    assert "diaggui XML" in capsys.readouterr().err


def test_model_response_of_a_state_space_optic(capsys) -> None:  # noqa: ANN001
    assert main(["model", "response", "--config", str(KAGRA / "PRM.toml"), "--json",
                 "--n", "20"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["drives"] == [f"IM_DAMP_{d}" for d in "LTVRPY"]
    assert any(m["label"] == "TM V" for m in out["modes"])


class _Seen(Exception):
    """Raised where a test has seen what it looks for."""


def test_a_diagnosis_runs_on_one_blas_thread(monkeypatch, srm) -> None:  # noqa: ANN001
    """OpenBLAS's threaded sums differ in their last bits from run to run, and a diagnosis's
    path of local fits can turn on such a difference (one six-drive file gave chi2/nu 1.2e3
    in one run and 2.2e3 in the next): the state-space fits run on one BLAS thread, so a
    file gives the same diagnosis every time."""
    seen = []

    def fit_data(*args, **kwargs) -> None:  # noqa: ANN002, ANN003 - the first step of a fit
        seen.append({p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"})
        raise _Seen

    monkeypatch.setattr(fit_module, "fit_data", fit_data)
    plant = SimpleNamespace(H=None, sigma=None, coherent=lambda c: None, frequency_hz=None,
                            readbacks=[], drives=[], averages=5, resolution_hz=0.0)
    with threadpool_limits(limits=2, user_api="blas"):
        for entry in (diagnose_plant, fit_baseline):
            with pytest.raises(_Seen):
                entry(plant, srm)
    assert seen == [{1}, {1}]


def test_a_drive_takes_its_sign_from_the_elements_that_tell_it_surely() -> None:
    """Two readbacks, two drives, every calibration positive; the model reaches readback 1
    from drive 1 only faintly and with the wrong phase. Walked from whichever element came
    first, that one element would give drive 1 (and its range would keep) the wrong sign;
    the three clean elements outvote it."""
    rng = np.random.default_rng(3)
    f = np.linspace(0.1, 10.0, 200)
    shape = 1.0 / (1.0 - (f / 2.0) ** 2 + 0.1j * f / 2.0)
    model = np.stack([np.stack([shape, shape], -1), np.stack([shape, -0.02 * shape], -1)], 1)
    readbacks, drives = np.array([2.0, 3.0]), np.array([1.0, 0.5])
    sigma = np.full(model.shape, 0.05)
    noise = rng.normal(size=model.shape) + 1j * rng.normal(size=model.shape)
    truth = model * readbacks[None, :, None] * drives[None, None, :]
    truth[:, 1, 1] *= -1  # the faint element's phase the model has wrong
    data = SimpleNamespace(H=truth + sigma * noise, sigma=sigma,
                           mask=np.ones(model.shape, dtype=bool))
    gains = start_gains(data, lambda nuisance, effects: model, {},
                        np.ones((2, 2), dtype=bool))
    assert gains["g_d1"] == pytest.approx(0.5, rel=0.1)
    assert gains["g_0"] == pytest.approx(2.0, rel=0.1)
    assert gains["g_1"] == pytest.approx(3.0, rel=0.1)
