"""The catalogue of physics left out (docs/model.md): each effect against an identity it must obey."""

from __future__ import annotations

import numpy as np
import pytest

from twind import DOFS
from twind.model.analytical import analytical_mechanics
from twind.model.effects import CATALOGUE, CHANNEL_FILTERS, EffectError, with_effect
from twind.model.params import SOSParams
from twind.model.plant import Plant

F = np.logspace(-1, 1.5, 60)
S = 2j * np.pi * F


@pytest.fixture(scope="module")
def sus() -> SOSParams:
    return SOSParams()


@pytest.fixture(scope="module")
def plant(sus: SOSParams) -> Plant:
    return Plant.from_params(sus, analytical_mechanics(sus))


@pytest.mark.parametrize("effect", list(CATALOGUE))
def test_every_effect_nests_the_nominal_model(effect: str, plant: Plant, sus: SOSParams) -> None:
    zero = with_effect(plant, sus, effect, dict.fromkeys(CATALOGUE[effect].params, 0.0))
    P = plant.response(F)  # decoupled extra coordinates change the modal sum by round-off
    np.testing.assert_allclose(zero.response(F), P, rtol=1e-12, atol=1e-12 * np.abs(P).max())
    moved = with_effect(plant, sus, effect, CATALOGUE[effect].scale)
    assert np.max(np.abs(moved.response(F) - plant.response(F))) > 0


def test_equal_imbalances_are_a_common_gain(plant: Plant, sus: SOSParams) -> None:
    g = {f"gain_{f}": 0.03 for f in ("UL", "UR", "LL", "LR")}
    stronger = Plant.from_params(sus.updated(coil_N_per_ct=sus.coil_N_per_ct * 1.03),
                                 analytical_mechanics(sus))
    P = with_effect(plant, sus, "coil_imbalance", g).response(F)
    face = [0, 1, 2]  # SIDE has its own coil
    tiny = 1e-12 * np.abs(P).max()  # elements zero by symmetry differ in round-off only
    np.testing.assert_allclose(P[:, :, face], stronger.response(F)[:, :, face], rtol=1e-12,
                               atol=tiny)
    P = with_effect(plant, sus, "osem_imbalance", g).response(F)
    np.testing.assert_allclose(P[:, face], 1.03 * plant.response(F)[:, face], rtol=1e-12,
                               atol=tiny)


def test_delay_and_pole_multiply_the_drive(plant: Plant, sus: SOSParams) -> None:
    P0 = plant.response(F)
    P = with_effect(plant, sus, "loop_delay", {"extra_s": 2e-4}).response(F)
    np.testing.assert_allclose(P, P0 * np.exp(-S * 2e-4)[:, None, None], rtol=1e-12)
    P = with_effect(plant, sus, "actuator_pole", {"inv_f_hz": 1 / 40.0}).response(F)
    np.testing.assert_allclose(P, P0 / (1 + S / (2 * np.pi * 40.0))[:, None, None], rtol=1e-12)


def test_drive_pole_is_in_the_state_space_the_engine_integrates(plant: Plant,
                                                                sus: SOSParams) -> None:
    poled = with_effect(plant, sus, "actuator_pole", {"inv_f_hz": 1 / 25.0})
    A, B, _, C = poled.osem_state_space()
    H = np.array([C @ np.linalg.solve(s * np.eye(len(A)) - A, B) for s in S])
    P = poled.input_matrix @ H @ poled.output_matrix * np.exp(-S * poled.delay_s)[:, None, None]
    np.testing.assert_allclose(P, poled.response(F), rtol=1e-8, atol=1e-12 * np.abs(P).max())


def test_side_sensing_coupling_reads_side_in_pos(plant: Plant, sus: SOSParams) -> None:
    """Each face OSEM reading kappa * y makes POS read kappa * SIDE, exactly."""
    P = with_effect(plant, sus, "side_coupling", {"sensing": 0.02}).response(F)
    pos, side = DOFS.index("POS"), DOFS.index("SIDE")
    np.testing.assert_allclose(P[:, pos, side], 0.02 * P[:, side, side], rtol=1e-12)


def test_wire_asymmetry_couples_pos_and_yaw_symmetrically(plant: Plant, sus: SOSParams) -> None:
    K = with_effect(plant, sus, "wire_asymmetry", {"delta_m": 1e-4}).mechanics.K
    i, j = DOFS.index("POS"), DOFS.index("YAW")
    expected = -sus.mass_kg * sus.g_mps2 * 1e-4 / sus.wire_length_m
    assert K[i, j] == K[j, i] == pytest.approx(expected, rel=1e-12)


def test_bad_effects_are_named(plant: Plant, sus: SOSParams) -> None:
    with pytest.raises(EffectError, match="catalogue has"):
        with_effect(plant, sus, "gremlins", {})
    with pytest.raises(EffectError, match="extra_s"):
        with_effect(plant, sus, "loop_delay", {"delay": 1e-4})


def test_a_resonance_is_the_body_the_corpus_attaches(plant: Plant, sus: SOSParams) -> None:
    """Two paths to one physics: the catalogue's unit-mass body pulling along g, and the
    corpus's body of mass m on a spring at a face point in 3-D kinematics."""
    from twind.commissioning.hidden import attached_body

    m, y, z = 2e-4, 0.012, -0.02
    real, truth = attached_body(plant, sus, m, 7.0, 30.0, (y, z))
    g = np.sqrt(m) * np.array([1.0, z, y, 0.0])
    model = with_effect(plant, sus, "resonance", {
        "f_hz": 7.0, "q": 30.0, **{f"g_{d}": x for d, x in zip(DOFS, g, strict=True)}})
    P = real.response(F)
    np.testing.assert_allclose(model.response(F), P, rtol=1e-9, atol=1e-12 * np.abs(P).max())
    assert truth["coupled"] == ["POS", "PIT", "YAW"]
    assert np.max(np.abs(P - plant.response(F))) > 1e-3 * np.abs(P).max()


def test_effects_combine_and_a_mode_may_come_twice(plant: Plant, sus: SOSParams) -> None:
    from twind.model.effects import effect_params

    both = with_effect(plant, sus, "coil_imbalance+loop_delay",
                       {"coil_imbalance.gain_UL": 0.02, "loop_delay.extra_s": 1e-4})
    one = with_effect(with_effect(plant, sus, "coil_imbalance", {"gain_UL": 0.02}), sus,
                      "loop_delay", {"extra_s": 1e-4})
    np.testing.assert_array_equal(both.response(F), one.response(F))
    names = effect_params("resonance+resonance#2")
    assert "resonance.f_hz" in names and "resonance#2.g_PIT" in names
    two = with_effect(plant, sus, "resonance+resonance#2", {
        "resonance.f_hz": 5.0, "resonance.q": 20.0, "resonance.g_POS": 0.01,
        "resonance#2.f_hz": 9.0, "resonance#2.q": 20.0, "resonance#2.g_PIT": 1e-4})
    assert two.mechanics.dofs[-2:] == ("BODY", "BODY#2")
    for bad in ("coil_imbalance#2", "loop_delay+loop_delay", "gremlins+loop_delay"):
        with pytest.raises(EffectError):
            with_effect(plant, sus, bad, {})


@pytest.mark.parametrize("effect", list(CHANNEL_FILTERS))
def test_a_channel_filter_is_one_channel_s_stage_in_model_and_engine(
        effect: str, plant: Plant, sus: SOSParams) -> None:
    """The frequency response and the state space the engine integrates agree, the stage
    touches its own coil's column (OSEM's row) only, and none nests the nominal model."""
    zero = with_effect(plant, sus, effect, {"inv_pole_hz": 0.0, "inv_zero_hz": 0.0})
    np.testing.assert_array_equal(zero.response(F), plant.response(F))
    moved = with_effect(plant, sus, effect, {"inv_pole_hz": 1 / 20.0, "inv_zero_hz": 1 / 35.0})
    A, B, _, C = moved.osem_state_space()
    G = np.array([C @ np.linalg.solve(s * np.eye(A.shape[0]) - A, B) for s in S])
    H = plant.mechanics.admittance(S)
    G0 = plant.sensing @ H @ plant.actuation
    F_stage = ((1 + S / (2 * np.pi * 35.0)) / (1 + S / (2 * np.pi * 20.0)))[:, None]
    kind, _, name = effect.partition("_filter_")
    k = ("UL", "UR", "LL", "LR", "SIDE").index(name)
    want = G0.copy()
    if kind == "coil":
        want[:, :, k] *= F_stage
    else:
        want[:, k, :] *= F_stage
    np.testing.assert_allclose(G, want, rtol=1e-9, atol=1e-10 * np.abs(G0).max())
    R = moved.response(F)
    np.testing.assert_allclose(R, plant.input_matrix @ want @ plant.output_matrix
                               * np.exp(-S * plant.delay_s)[:, None, None],
                               rtol=1e-9, atol=1e-12 * np.abs(R).max())


@pytest.mark.parametrize("effect", ["bounce_roll", "resonance"])
def test_the_modal_admittance_is_the_inverse_at_every_frequency(effect: str, plant: Plant,
                                                                 sus: SOSParams) -> None:
    """The sum over modes against ``(M s^2 + C s + K)^-1`` from 0 to 5 kHz, also with a body
    that moves nothing at the POS mode's own frequency and width (a repeated eigenvalue)."""
    pos = plant.mechanics.index("POS")
    w2 = plant.mechanics.K[pos, pos] / plant.mechanics.M[pos, pos]
    f_pos = float(np.sqrt(w2) / (2 * np.pi))
    q = float(np.sqrt(w2) / (plant.mechanics.C[pos, pos] / plant.mechanics.M[pos, pos]))
    values = {"f_hz": f_pos, "q": q, "g_POS": 0.0, "g_PIT": 0.0, "g_YAW": 0.0, "g_SIDE": 0.0} \
        if effect == "resonance" else CATALOGUE[effect].scale
    mech = with_effect(plant, sus, effect, values).mechanics
    s = 2j * np.pi * np.concatenate([[0.0], np.logspace(-2, np.log10(5000), 400)])
    direct = np.linalg.inv(mech.M * s[:, None, None] ** 2 + mech.C * s[:, None, None] + mech.K)
    scale = np.abs(direct).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(mech.admittance(s) - direct) <= 1e-9 * scale)


def test_near_defective_modes_fall_back_to_the_inverse(plant: Plant,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Beyond the eigenvectors' condition limit the admittance inverts per frequency, with
    the same projections."""
    mech, left, right = plant.mechanics, plant.sensing, plant.actuation
    modal = mech.admittance(S, left, right)
    monkeypatch.setattr("twind.model.mechanics.MODAL_CONDITION", 0.0)
    direct = mech.admittance(S, left, right)
    assert direct.shape == modal.shape == (S.size, 5, 5)
    np.testing.assert_allclose(direct, modal, rtol=0, atol=1e-9 * np.abs(modal).max())
