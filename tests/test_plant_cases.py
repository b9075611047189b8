"""The bench of realistic KAGRA cases: the perturbed suspension and the correspondence of its
modes, the measurement chain as Welch sees it, a case made into a directory, and the scoring
of a diagnosis's JSON against the truth."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from twind.analysis.estimation.diaggui import read_transfers
from twind.lab.plant_cases import bench_case, make_case, optic_of, score, totals
from twind.lab.plant_measurement import Chain, Coupling, Crosstalk, measure_chain
from twind.lab.plant_truth import Perturbation, SuspensionError, View, correspondence, suspension
from twind.model.statespace import StateSpace


@pytest.fixture(scope="module")
def srm():  # noqa: ANN201 - StateSpaceOptic
    return optic_of("SRM")


def oscillators(f_hz: list[float], q: float = 200.0, k23: float = 0.0) -> StateSpace:
    """Uncoupled oscillators of unit mass (the second and third coupled by `k23`, in units
    of their stiffness), a force and a position each."""
    n = len(f_hz)
    w2 = (2 * math.pi * np.asarray(f_hz)) ** 2
    k = np.diag(w2)
    k[1, 2] = k[2, 1] = k23 * math.sqrt(w2[1] * w2[2])
    c = np.diag(np.sqrt(w2) / q)
    a = np.block([[np.zeros((n, n)), np.eye(n)], [-k, -c]])
    b = np.vstack([np.zeros((n, n)), np.eye(n)])
    return StateSpace(a, b, np.hstack([np.eye(n), np.zeros((n, n))]), np.zeros((n, n)),
                      tuple(f"f{i}" for i in range(n)), tuple(f"x{i}" for i in range(n)),
                      "three oscillators")


def view_of(model: StateSpace) -> View:
    """Every input and output, a negligible noise floor, 0-20 Hz."""
    floor = np.full((len(model.outputs), len(model.inputs)), 1e-12)
    return View(model.inputs, model.outputs, floor, (0.01, 20.0), 1 / 128)


# ------------------------------------------------------------------------ the suspension
def test_a_model_without_a_second_order_block_is_refused() -> None:
    model = StateSpace(-np.eye(2), np.eye(2), np.eye(2), np.zeros((2, 2)), ("u1", "u2"),
                       ("y1", "y2"), "two poles")
    with pytest.raises(SuspensionError, match="no second-order block"):
        suspension(model)


def test_the_kagra_models_block_is_found_and_left_alone_unperturbed(srm) -> None:  # noqa: ANN001
    sus = suspension(srm.model)
    assert sus.dofs == 51 and sus.body.sum() == 45  # six free DOFs: the ground's
    same = sus.perturbed(Perturbation.none(sus.dofs))
    assert np.array_equal(same.a, srm.model.a) and np.array_equal(same.b, srm.model.b)


def test_a_mass_moves_the_mode_it_carries_alone_by_one_over_its_root(srm) -> None:  # noqa: ANN001
    """DOF 13 of the SRM's block carries 99 % of a mode of its stiffness (its share, from
    K''s own eigenvectors); 30 % more mass there moves that mode by ``1.3^(-share / 2)``
    and no other by more than 0.5 %."""
    sus = suspension(srm.model)
    body = np.flatnonzero(sus.body)
    w, v = np.linalg.eig(sus.stiffness[np.ix_(body, body)])
    share = (np.linalg.inv(v).T * v).real
    i = int(np.flatnonzero(body == 13)[0])
    k = int(np.argmax(share[i]))
    assert share[i, k] > 0.98
    mass = np.zeros(sus.dofs)
    mass[13] = 0.3
    modes = correspondence(sus, replace(Perturbation.none(sus.dofs), mass=mass),
                           view_of(srm.model))
    moved = [m for m in modes if abs(m.shift) > 0.005]
    assert len(moved) == 1
    assert moved[0].shift == pytest.approx(1.3 ** (-share[i, k] / 2) - 1, abs=0.003)
    assert abs(moved[0].model_f_hz - math.sqrt(w[k].real) / (2 * math.pi)) < 0.02


def test_a_mode_is_followed_across_another_it_crosses() -> None:
    """Doubling the mass of a 1.2 Hz oscillator takes it to 1.2 / sqrt(2) = 0.849 Hz, across
    a 1.0 Hz one, which stays: nearest poles at the end would pair them the other way."""
    model = oscillators([1.2, 1.0, 2.0], k23=0.01)
    sus = suspension(model)
    p = replace(Perturbation.none(3), mass=np.array([1.0, 0.0, 0.0]))
    modes = {round(m.model_f_hz, 3): m for m in correspondence(sus, p, view_of(model))}
    assert modes[1.2].true_f_hz == pytest.approx(1.2 / math.sqrt(2), rel=1e-6)
    assert modes[1.0].true_f_hz == pytest.approx(modes[1.0].model_f_hz, rel=1e-9)
    assert modes[1.2].mac == pytest.approx(1.0, abs=1e-9)


def test_a_rotation_of_the_springs_changes_the_shapes_not_the_frequencies() -> None:
    """Turning the coupled pair's springs and dampers by 0.3 rad keeps every pole and turns
    both modes' shapes: the MAC of their residues is cos(0.3)^4."""
    model = oscillators([1.2, 1.0, 2.0], k23=0.01)
    sus = suspension(model)
    angles = np.zeros((3, 3))
    angles[1, 2] = 0.3
    modes = correspondence(sus, replace(Perturbation.none(3), coupling=angles), view_of(model))
    for m in modes:
        assert m.true_f_hz == pytest.approx(m.model_f_hz, rel=1e-9)
    turned = [m.mac for m in modes if m.model_f_hz < 1.1 or m.model_f_hz > 1.9]
    assert turned == pytest.approx([math.cos(0.3) ** 4] * 2, abs=2e-3)


# ------------------------------------------------------------------------ the chain
def test_welch_shows_the_chains_calibration_delay_low_pass_coupling_and_crosstalk(
        srm, tmp_path) -> None:  # noqa: ANN001
    """A short measurement (1/16 Hz bins, 10 averages) of a truth damped so that no mode
    rings past a segment: over the bins coherent to 0.99, each readback is its calibration
    times the model's response (StateSpace.response, with what the coupling adds), the
    delay, the discretised low-pass and the engine's half-cycle hold, within 2 %; the
    crosstalk is the flat term it adds. Leaving out the delay or the low-pass misses by far
    more."""
    sus = suspension(srm.model)
    truth = sus.perturbed(replace(Perturbation.none(sus.dofs),
                                  damping=np.where(sus.body, math.log(100.0), 0.0)))
    chain = Chain(calibration={"IM_DAMP_P_IN1": -0.37, "IM_DAMP_V_IN1": 2.0,
                               "TM_OPLEV_PIT_DIAG": 0.004, "TM_OPLEV_LEN_DIAG": 5.0},
                  delay_s=0.0123, lowpass_hz=25.0, noise={"IM_DAMP_P_IN1": 1e-7},
                  couplings=(Coupling("IM_DAMP_V_IN1", "IM_DAMP_P_IN1", 0.03),),
                  crosstalk=(Crosstalk("TM_TEST_P", "TM_OPLEV_LEN_DIAG", 0.002),))
    path = measure_chain(srm, "TM_TEST_P", tmp_path / "chain.xml", chain, model=truth,
                         averages=10, bw_hz=1 / 16, stop_hz=30.0, seed=3)
    measured = {t.numerator: t for t in read_transfers(path)}
    f = measured[srm.channel("IM_DAMP_P_IN1")].frequency_hz
    band = (f >= 2) & (f <= 30)
    names = list(srm.readbacks)
    h = truth.response(f[band], ["exc_TMP"], [srm.readbacks[r] for r in names])[:, :, 0]
    common = chain.common(f[band], 512.0)
    expected = {
        "IM_DAMP_P_IN1": -0.37 * common * h[:, names.index("IM_DAMP_P_IN1")],
        "IM_DAMP_V_IN1": 2.0 * common * (h[:, names.index("IM_DAMP_V_IN1")]
                                         + 0.03 * h[:, names.index("IM_DAMP_P_IN1")]),
        "TM_OPLEV_PIT_DIAG": 0.004 * common * h[:, names.index("TM_OPLEV_PIT_DIAG")],
        "TM_OPLEV_LEN_DIAG": 5.0 * common * h[:, names.index("TM_OPLEV_LEN_DIAG")] + 0.002}
    for name, want in expected.items():
        t = measured[srm.channel(name)]
        good = t.coherence[band] >= 0.99
        assert good.sum() > 100, name
        got = t.tf[band][good]
        assert np.median(np.abs(got / want[good] - 1)) < 0.02, name
        undelayed = want[good] * np.exp(2j * math.pi * f[band][good] * chain.delay_s)
        assert np.median(np.abs(got / undelayed - 1)) > 0.2, name
        unfiltered = want[good] * (1 + 1j * f[band][good] / chain.lowpass_hz)
        assert np.median(np.abs(got / unfiltered - 1)) > 0.2, name


# ------------------------------------------------------------------------ a case
def test_a_case_is_written_with_its_truth(srm, tmp_path) -> None:  # noqa: ANN001
    """A test-mass case (coarse bins, few averages: quick): 5-8 visible modes moved by
    2-60 %, none in the band by more, each followed unambiguously; its file in the site's
    names, its truth and its chain in case.json."""
    case = make_case(srm, "tm", 2, tmp_path / "case", resolution_hz=1 / 16, averages=3)
    assert len(case.files) == 1 and case.files[0].exists()
    assert 5 <= len(case.moved) <= 8
    assert all(0.02 <= abs(m.shift) <= 0.6 for m in case.moved)
    assert all(abs(m.shift) <= 0.6 for m in case.modes if m.in_band)
    assert all(0 <= m.mac <= 1 + 1e-9 and not m.ambiguous for m in case.moved)
    written = json.loads((tmp_path / "case" / "case.json").read_text())
    assert written["files"] == [case.files[0].name]
    assert sum(m["moved"] for m in written["modes"]) == len(case.moved)
    assert set(written["chain"]["calibration"]) == set(srm.readbacks)
    assert 0 <= written["chain"]["delay_s"] <= 0.02 and 10 <= written["chain"]["lowpass_hz"] <= 100
    transfers = read_transfers(case.files[0])
    assert {t.denominator for t in transfers} == {srm.channel(f"{case.drives[0]}_EXC")}
    assert {t.numerator for t in transfers} == {srm.channel(r) for r in srm.readbacks}


def test_a_case_that_cannot_be_made_is_reported_not_raised(tmp_path) -> None:  # noqa: ANN001
    (tmp_path / "SRM_tm_0").mkdir()
    (tmp_path / "SRM_tm_0" / "case.json").write_text("{")
    result = bench_case("SRM", "tm", 0, tmp_path, timeout_s=1.0)
    assert "making it raised" in result.score.error
    assert "FAILED" in result.line()
    assert "failed 1" in totals([result])[0]


# ------------------------------------------------------------------------ scoring
TRUTH = [  # a moved mode, a narrow moved one, one moved to be read as new, one unmoved
    {"model_f_hz": 0.500, "true_f_hz": 0.450, "true_q": 50.0, "moved": True,
     "shift_percent": -10.0},
    {"model_f_hz": 1.000, "true_f_hz": 1.100, "true_q": 1e5, "moved": True,
     "shift_percent": 10.0},
    {"model_f_hz": 2.000, "true_f_hz": 2.400, "true_q": 30.0, "moved": True,
     "shift_percent": 20.0},
    {"model_f_hz": 3.000, "true_f_hz": 3.010, "true_q": 30.0, "moved": False,
     "shift_percent": 0.3},
]


def claim(family: str, f_hz: float, model_hz: float | None = None,
          rival_of: str | None = None) -> dict:
    out = {"family": family, "rival_of": rival_of, "params": {}}
    if family == "mode_frequency":
        out.update(mode={"f_hz": model_hz, "q": 10.0, "label": ""}, f_hz=f_hz)
    elif family == "resonance":
        out["params"] = {"f_hz": f_hz, "q": 20.0}
    return out


def test_a_diagnosis_is_scored_from_its_json_alone() -> None:
    diagnosis = {"coherent": {"A/B": [[0.1, 3.5]], "C/B": [[4.0, 4.5]]}, "effects": [
        claim("mode_frequency", 0.455, 0.5002),       # read: 1.1 % from the truth
        claim("mode_frequency", 1.150, 1.0),          # read: 4.5 %, the mode a bin wide
        claim("resonance", 2.45),                     # the third read as new (2 %)
        claim("mode_frequency", 3.2, 3.0),            # wrong: an unmoved mode put 6 % off
        claim("resonance", 3.8),                      # beyond the coherent band: wrong
        claim("mode_frequency", 2.1, 2.0, rival_of="resonance[0]"),  # a rival: not chosen
        claim("cross_coupling", 0.0)]}
    s = score(diagnosis, TRUTH, resolution_hz=1 / 128)
    assert (s.moved, s.read, s.read_as_new) == (3, 2, 1)
    assert (s.claims, s.wrong, s.beyond) == (6, 2, 1)


def test_a_claim_too_far_reads_nothing_and_a_rival_counts_for_nothing() -> None:
    diagnosis = {"coherent": {"A/B": [[0.1, 3.5]]}, "effects": [
        claim("mode_frequency", 0.47, 0.5),           # 4.4 % off a mode 0.009 Hz wide
        claim("mode_frequency", 1.10, 1.0, rival_of="mode_frequency[0]"),
        claim("resonance", 2.6)]}                     # 8 % and 26 bins off
    s = score(diagnosis, TRUTH, resolution_hz=1 / 128)
    assert (s.read, s.read_as_new, s.wrong, s.beyond) == (0, 0, 2, 0)


def test_a_readback_calibrated_off_or_of_the_wrong_sign_is_counted() -> None:
    """Every fitted calibration carries the first drive's true strength (here -2): a
    readback is off when its sign or its size (beyond 2x) disagrees with the others'."""
    truth = {"A": 1.0, "B": -0.5, "C": 3.0, "D": 0.01, "E": 7.0}
    fitted = {"A": -2.0, "B": 1.1, "C": 6.0 * 2.5, "D": 0.02, "E": -14.0 / 1e4}
    diagnosis = {"coherent": {}, "effects": [],
                 "nuisance": {f"calibration {k}": {"value": v, "sigma": None}
                              for k, v in [*fitted.items(), ("F", 1.0)]}}
    s = score(diagnosis, TRUTH, 1 / 128, {**truth, "G": 1.0})
    assert (s.calibrated, s.miscalibrated) == (5, 3)
    assert [n for n in s.notes if n.startswith("calibration")] == [
        "calibration off: C", "calibration off: D", "calibration off: E"]


def test_a_moved_mode_whose_shape_changed_is_counted_apart() -> None:
    truth = [{**m, "mac": mac} for m, mac in zip(TRUTH, (0.2, 0.9, 0.3, 1.0), strict=True)]
    diagnosis = {"coherent": {"A/B": [[0.1, 3.5]]}, "effects": [
        claim("mode_frequency", 0.455, 0.5002), claim("mode_frequency", 1.150, 1.0)]}
    s = score(diagnosis, truth, resolution_hz=1 / 128)
    assert (s.reshaped, s.reshaped_read) == (2, 1)
    assert s.notes == ["missed: 2 Hz moved to 2.4 Hz (+20.0 %, MAC 0.30)"]
