"""Geometric rigid-body SOS model: reduction to T000134, asymmetries, failure modes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from twind.errors import TwindError
from twind.model.analytical import analytical_mechanics
from twind.model.compare import compare_models, eigenfrequencies_by_dof
from twind.model.geometric import (
    DOFS,
    GeometryError,
    NoEquilibriumError,
    SlackWireError,
    WireGeometry,
    geometric_mechanics,
    geometric_model,
    pendulum_centre_offset,
    potential_energy,
    wire_stiffness,
)
from twind.model.params import SOSParams
from twind.viz.plotting import plot_comparison

P = SOSParams()
M_KG, G, L, B, R1, R2 = P.mass_kg, P.g_mps2, P.wire_length_m, P.b_m, P.R1_m, P.R2_m
F_HZ = np.logspace(-1, 1, 1500)


@pytest.fixture(scope="module")
def ideal():
    return geometric_model(WireGeometry.from_params(P))


def _k(mod, row: str, col: str) -> float:
    mech = mod.mechanics
    return float(mech.K[mech.index(row), mech.index(col)])


# --- ideal geometry reduces to the analytical model -------------------------------------------

def test_ideal_equilibrium_is_the_nominal_pose(ideal):
    pose = ideal.equilibrium.pose()
    assert max(abs(v) for v in pose.values()) < 1e-12
    # each segment carries half the weight along its inclined direction
    length = np.hypot(L, R2 - R1)
    np.testing.assert_allclose(ideal.equilibrium.tensions_N, M_KG * G * length / (2 * L), rtol=1e-12)


def test_coupled_eigenfrequencies_match_analytical(ideal):
    geo = eigenfrequencies_by_dof(ideal.mechanics)
    ana = eigenfrequencies_by_dof(analytical_mechanics(P))
    for dof in ("POS", "PIT", "YAW", "SIDE"):
        assert geo[dof] == pytest.approx(ana[dof], rel=5e-3), dof
    # POS, PIT and YAW are exact; SIDE is 0.23 % low: the trapezoidal wires make the optic roll
    # as it swings sideways, adding I_roll / H^2 to the swinging mass
    for dof in ("POS", "PIT", "YAW"):
        assert geo[dof] == pytest.approx(ana[dof], rel=1e-9), dof


def test_uncoupled_frequencies_match_formulas(ideal):
    mech = ideal.mechanics
    formula = P.uncoupled_frequencies_hz()
    diag = {d: np.sqrt(mech.K[i, i] / mech.M[i, i]) / (2 * np.pi) for i, d in enumerate(mech.dofs)}
    for dof in ("POS", "PIT", "YAW"):  # g/l, m g b (l+b)/(I l), m g R1 R2/(I l)
        assert diag[dof] == pytest.approx(formula[dof], rel=1e-9), dof
    # SIDE only exists with ROLL relaxed (the wires are a four-bar linkage): static condensation
    side, roll = mech.index("SIDE"), mech.index("ROLL")
    k_side = mech.K[side, side] - mech.K[side, roll] ** 2 / mech.K[roll, roll]
    assert np.sqrt(k_side / M_KG) / (2 * np.pi) == pytest.approx(formula["SIDE"], rel=5e-3)
    geo = eigenfrequencies_by_dof(mech)
    for dof in ("SIDE", "VERT", "ROLL"):  # g/(l+b), sqrt(k/m), sqrt(k R2^2 / I_roll)
        assert geo[dof] == pytest.approx(formula[dof], rel=5e-3), dof


def test_pitch_sign_follows_osem_kinematics(ideal):
    # break-off at height b moves by x + b*PIT; the wire pulls it back with -(m g / l)(x + b PIT)
    assert _k(ideal, "POS", "PIT") == pytest.approx(+M_KG * G * B / L, rel=1e-9)
    ana = analytical_mechanics(P)
    assert ana.K[0, 1] == pytest.approx(-M_KG * G * B / L, rel=1e-9)  # T000134 pitch sign


def test_damping_reduces_to_analytical(ideal):
    ana = analytical_mechanics(P)
    geo = ideal.mechanics
    for i, dof in enumerate(ana.dofs):
        tol = 1e-9 if dof != "SIDE" else 5e-3
        assert geo.C[geo.index(dof), geo.index(dof)] == pytest.approx(ana.C[i, i], rel=tol), dof


def test_admittance_magnitudes_match_off_resonance():
    cmp = compare_models(P, F_HZ)
    worst = cmp.max_relative_difference(0.10)
    live = ~cmp.structurally_zero()
    assert live.sum() == 6  # POS/POS, POS/PIT, PIT/POS, PIT/PIT, YAW/YAW, SIDE/SIDE
    side = cmp.dofs.index("SIDE")
    others = live.copy()
    others[side, side] = False
    assert np.all(worst[others] < 0.02)
    # SIDE/SIDE: the 0.23 % eigenfrequency shift (roll of the trapezoid) gives 2.9 % just outside
    # the +-10 % band; 2 % holds outside +-20 % and the far-off-resonance offset is 0.8 %
    assert worst[side, side] < 0.03
    assert cmp.max_relative_difference(0.20)[side, side] < 0.02


def test_structural_zeros_agree(ideal):
    cmp = compare_models(P, F_HZ[::50])
    expected = np.ones((4, 4), bool)
    for a, b in [("POS", "POS"), ("POS", "PIT"), ("PIT", "POS"), ("PIT", "PIT"),
                 ("YAW", "YAW"), ("SIDE", "SIDE")]:
        expected[cmp.dofs.index(a), cmp.dofs.index(b)] = False
    np.testing.assert_array_equal(cmp.structurally_zero(), expected)


# --- the linearisation -----------------------------------------------------------------------

def _finite_difference_hessian(geom, eq):
    h = np.array([1e-6, 1e-5, 1e-5, 1e-6, 1e-6, 1e-5])  # m for translations, rad for rotations
    out = np.zeros((6, 6))
    for i in range(6):
        for j in range(6):
            ei, ej = np.eye(6)[i] * h[i], np.eye(6)[j] * h[j]
            E = lambda q: potential_energy(geom, q, eq)  # noqa: E731
            out[i, j] = (E(ei + ej) - E(ei - ej) - E(ej - ei) + E(-ei - ej)) / (4 * h[i] * h[j])
    return out


@pytest.mark.parametrize("asymmetric", [False, True])
def test_hessian_is_symmetric_and_matches_finite_differences(asymmetric):
    kwargs = dict(clamp_offsets=[(2e-4, 1e-3, 1e-3), (0, 0, 0)], com_offset=(1e-5, 2e-5, 0),
                  attach_offsets=[(0, 0, 0), (1e-4, 0, -2e-4)]) if asymmetric else {}
    geom = WireGeometry.from_params(P, **kwargs)
    eq = geometric_model(geom).equilibrium
    K = wire_stiffness(geom, eq)
    assert np.max(np.abs(K - K.T)) <= 1e-12 * np.max(np.abs(K))
    # element-wise relative to sqrt(K_ii K_jj): spans axial (2e3 N/m) to pitch (2e-3 N m/rad)
    scale = np.sqrt(np.outer(np.diag(K), np.diag(K)))
    assert np.all(np.abs(_finite_difference_hessian(geom, eq) - K) <= 1e-3 * scale)


# --- asymmetries -----------------------------------------------------------------------------

def test_com_off_wire_plane_along_beam_pitches_without_pos_yaw_coupling():
    delta = 10e-6
    mod = geometric_model(WireGeometry.from_params(P, com_offset=(delta, 0, 0)))
    pose = mod.equilibrium.pose()
    # the optic pitches until its centre of mass hangs below the break-off line (top toward +x)
    assert pose["PIT"] == pytest.approx(np.arctan(delta / B), rel=1e-6)
    assert abs(pose["POS"]) < 1e-12 and abs(pose["YAW"]) < 1e-12
    # y -> -y mirror symmetry survives (POS even, YAW odd): no POS<->YAW coupling at any order,
    # contrary to a literal reading of docs/model.md's wire_asymmetry (delta along the beam)
    assert abs(_k(mod, "POS", "YAW")) < 1e-9 * M_KG * G * delta / L
    # the break-off line now sits sqrt(b^2 + delta^2) above the centre of mass
    assert _k(mod, "POS", "PIT") == pytest.approx(M_KG * G * np.hypot(B, delta) / L, rel=1e-6)
    Y = mod.mechanics.admittance(2j * np.pi * F_HZ)
    pos, yaw = mod.mechanics.index("POS"), mod.mechanics.index("YAW")
    assert np.max(np.abs(Y[:, pos, yaw])) < 1e-9 * np.max(np.abs(Y[:, pos, pos]))


def test_wire_asymmetry_pos_yaw_coupling():
    """docs/model.md ``K_xphi = K_phix = -m g delta / l`` with delta the sideways CoM offset.

    Raising the +y clamp by ``d`` (wire cut to fit) makes the +y wire longer, hence softer along
    the beam: the pendulum centre (T/L-weighted mean of the break-off y) moves to -y, i.e. the
    centre of mass sits ``delta = R2 d / (2 l + d)`` on the +y side of it.
    """
    d = 1e-3
    mod = geometric_model(WireGeometry.from_params(P, clamp_offsets=[(0, 0, d), (0, 0, 0)]))
    delta = R2 * d / (2 * L + d)
    expected = -M_KG * G * delta / L
    assert _k(mod, "POS", "YAW") == pytest.approx(expected, rel=0.02)
    assert _k(mod, "YAW", "POS") == _k(mod, "POS", "YAW")
    assert pendulum_centre_offset(mod) == pytest.approx(delta, rel=0.02)
    # a sideways centre of mass between equal wires is no pendulum-centre offset
    even = geometric_model(WireGeometry.from_params(P, com_offset=(0, 10e-6, 0)))
    assert abs(pendulum_centre_offset(even)) < 0.01 * 10e-6
    # the general small-angle result from the equilibrium itself: K_POS,YAW = sum T_i y_i / L_i
    eq = mod.equilibrium
    y = (eq.rotation @ mod.geometry.attach_m.T)[1]
    assert _k(mod, "POS", "YAW") == pytest.approx(np.sum(eq.tensions_N * y / eq.lengths_m), rel=1e-6)

    mech = mod.mechanics
    pos, yaw = mech.index("POS"), mech.index("YAW")
    # statically a push along +x swings the softer (+y) side further: positive YAW
    assert np.linalg.inv(mech.K)[yaw, pos] > 0
    # the coupling shows in the admittance, to first order -K_xphi Y_xx Y_phiphi
    cmp = compare_models(P, F_HZ, geometry=mod.geometry)
    keep = cmp.off_resonance(0.10)
    Yg = cmp.admittance_geometric[keep]
    i_pos, i_yaw = cmp.dofs.index("POS"), cmp.dofs.index("YAW")
    first_order = -expected * Yg[:, i_pos, i_pos] * Yg[:, i_yaw, i_yaw]
    np.testing.assert_allclose(np.abs(Yg[:, i_pos, i_yaw]), np.abs(first_order), rtol=0.03)
    assert not cmp.structurally_zero()[i_pos, i_yaw]


def test_lowered_attachment_couples_with_the_longer_wire_sign():
    d = 1e-3
    mod = geometric_model(WireGeometry.from_params(P, attach_offsets=[(0, 0, -d), (0, 0, 0)]))
    eq = mod.equilibrium
    y = (eq.rotation @ mod.geometry.attach_m.T)[1]
    k_xy = _k(mod, "POS", "YAW")
    # the +y wire is longer, so the sign matches a raised +y clamp; tension shifts to the +y
    # wire (its break-off is now lower), which undoes most of the magnitude
    assert k_xy < 0
    assert k_xy == pytest.approx(np.sum(eq.tensions_N * y / eq.lengths_m), rel=1e-6)
    assert eq.tensions_N[0] > eq.tensions_N[1]


def test_com_sideways_barely_couples_parallelogram():
    delta = 10e-6
    mod = geometric_model(WireGeometry.from_params(P, com_offset=(0, delta, 0)))
    # equal wires: tensions rebalance (sum T y = 0), only their unequal stretch is left
    assert abs(_k(mod, "POS", "YAW")) < 0.01 * M_KG * G * delta / L
    t_plus, t_minus = mod.equilibrium.tensions_N
    assert t_plus > t_minus  # the wire nearer the centre of mass carries more


def test_twisted_attachment_yaws_the_optic():
    e = 1e-4  # +y break-off moved to +x, -y break-off to -x: the break-off line is yawed
    mod = geometric_model(WireGeometry.from_params(P, attach_offsets=[(e, 0, 0), (-e, 0, 0)]))
    pose = mod.equilibrium.pose()
    # the optic turns its break-off line back under the clamps: +y points move toward -x
    assert pose["YAW"] == pytest.approx(-np.arctan(e / R2), rel=1e-6)
    assert abs(pose["PIT"]) < 1e-12
    # 180-degree symmetry about z survives: still no POS<->YAW coupling
    assert abs(_k(mod, "POS", "YAW")) < 1e-12


def test_attachment_shifted_along_beam_pitches_and_yaws():
    e = 1e-4
    mod = geometric_model(WireGeometry.from_params(P, attach_offsets=[(e, 0, 0), (0, 0, 0)]))
    pose = mod.equilibrium.pose()
    # break-off line on average e/2 in front of the centre of mass: the top swings back (-PIT)
    assert pose["PIT"] == pytest.approx(-np.arctan(e / 2 / B), rel=1e-2)
    assert pose["YAW"] == pytest.approx(-np.arctan(e / 2 / R2), rel=1e-2)


# --- failures --------------------------------------------------------------------------------

def test_slack_wire_is_named():
    g = WireGeometry.from_params(P)
    three = dataclasses.replace(
        g,
        clamp_m=np.vstack([g.clamp_m, [0.0, 0.0, B + L]]),
        attach_m=np.vstack([g.attach_m, [0.0125, 0.0, 0.0]]),
        unstretched_m=np.r_[g.unstretched_m, 0.26],  # longer than it can ever be stretched to
        axial_stiffness_Npm=np.r_[g.axial_stiffness_Npm, 1000.0],
        names=g.names + ("front wire",),
    )
    with pytest.raises(SlackWireError, match="front wire is slack") as info:
        geometric_mechanics(three)
    assert isinstance(info.value, TwindError)


def test_centre_of_mass_above_break_off_has_no_stable_equilibrium():
    with pytest.raises(NoEquilibriumError, match="PIT"):
        geometric_mechanics(WireGeometry.from_params(P, com_offset=(0, 0, 2e-3)))
    with pytest.raises(NoEquilibriumError, match="tumbles"):
        geometric_mechanics(WireGeometry.from_params(P, com_offset=(1e-5, 0, 2e-3)))


def test_single_wire_has_no_yaw_stiffness():
    g = WireGeometry.from_params(P)
    one = dataclasses.replace(g, clamp_m=g.clamp_m[:1] * [1, 0, 1], attach_m=g.attach_m[:1] * [1, 0, 1],
                              unstretched_m=g.unstretched_m[:1],
                              axial_stiffness_Npm=2 * g.axial_stiffness_Npm[:1], names=("only wire",))
    with pytest.raises(NoEquilibriumError, match="YAW"):
        geometric_mechanics(one)


def test_malformed_geometry_is_a_twind_error():
    g = WireGeometry.from_params(P)
    with pytest.raises(GeometryError, match="unstretched_m"):
        dataclasses.replace(g, unstretched_m=np.ones(3))
    with pytest.raises(GeometryError, match="axial stiffness"):
        dataclasses.replace(g, axial_stiffness_Npm=np.array([1.0, -1.0]))
    with pytest.raises(GeometryError, match="com_offset"):
        WireGeometry.from_params(P, com_offset=(1.0, 2.0))
    assert issubclass(GeometryError, TwindError)


# --- plotting --------------------------------------------------------------------------------

def test_plot_comparison_writes_png(tmp_path):
    out = plot_comparison(compare_models(P, np.logspace(-1, 1, 200)), tmp_path / "cmp.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_dofs_order():
    assert DOFS == ("POS", "PIT", "YAW", "SIDE", "VERT", "ROLL")
