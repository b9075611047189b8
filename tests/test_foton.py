"""Foton design strings: parsing against scipy and the golden controller, discretization."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from scipy import signal

from twind.errors import FotonError
from twind.loop.foton import (
    NOMINAL_FM1,
    NOMINAL_FM2,
    NOMINAL_FM3,
    ZPK,
    design_to_sos,
    parse_design,
    zpk_to_sos,
)

FS = 16384.0
TWO_PI = 2 * math.pi
F_GRID = np.logspace(-2, math.log10(2000), 400)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a / b - 1)))


def _s(f: np.ndarray) -> np.ndarray:
    return 2j * math.pi * f


def _same_roots(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.allclose(np.sort_complex(a), np.sort_complex(np.asarray(b, dtype=complex))))


def _nominal() -> ZPK:
    return parse_design(NOMINAL_FM1) * parse_design(NOMINAL_FM2) * parse_design(NOMINAL_FM3)


# -- nominal controller ----------------------------------------------------------------------
def test_nominal_filters_reproduce_golden_controller(golden: dict) -> None:
    f = np.array(golden["frequency_hz"])
    ctrl = golden["controller_diag"]
    want = np.array(ctrl["re"]) + 1j * np.array(ctrl["im"])
    assert golden["dofs"] == ["POS", "PIT", "YAW", "SIDE"]
    k = _nominal().response(f)
    for col, g in enumerate([30.0, 0.45, 0.52, 120.0]):
        assert _rel(g * k, want[:, col]) < 1e-9


def test_fm1_is_exactly_velocity_times_30hz_pole() -> None:
    w30 = TWO_PI * 30.000330908653446
    s = _s(F_GRID)
    assert _rel(parse_design(NOMINAL_FM1).response(F_GRID), s / (1 + s / w30)) < 1e-12


def test_fm2_fm3_unity_dc_and_fm3_notches(nominal: dict) -> None:
    for design in (NOMINAL_FM2, NOMINAL_FM3):
        assert abs(parse_design(design).response(0.0) - 1) < 1e-12
    fm3 = parse_design(NOMINAL_FM3)
    assert fm3.zeros.size == 16 and fm3.poles.size == 16
    assert np.allclose(fm3.zeros.real, 0)
    notches = np.array(nominal["controller"]["notch_zeros_hz"])
    assert np.max(np.abs(fm3.response(notches))) < 1e-9


# -- zpk planes --------------------------------------------------------------------------------
def test_zpk_s_plane_is_literal_and_default() -> None:
    s = _s(F_GRID)
    want = 2 * (s + 10) / (s + 100)
    assert _rel(parse_design('zpk([-10],[-100],2,"s")').response(F_GRID), want) < 1e-12
    assert _rel(parse_design("zpk([-10],[-100],2)").response(F_GRID), want) < 1e-12


def test_zpk_f_plane_keeps_sign_and_s_plane_gain() -> None:
    z = parse_design('zpk([-1],[-10],3,"f")')
    assert np.allclose(z.zeros, [-TWO_PI]) and np.allclose(z.poles, [-TWO_PI * 10])
    s = _s(F_GRID)
    assert _rel(z.response(F_GRID), 3 * (s + TWO_PI) / (s + TWO_PI * 10)) < 1e-12


def test_zpk_n_plane_flips_sign_and_normalises_dc() -> None:
    z = parse_design('zpk([1],[10],3,"n")')
    assert np.allclose(z.zeros, [-TWO_PI]) and np.allclose(z.poles, [-TWO_PI * 10])
    s = _s(F_GRID)
    assert _rel(z.response(F_GRID), 3 * (1 + s / TWO_PI) / (1 + s / (TWO_PI * 10))) < 1e-12
    assert z.response(0.0) == pytest.approx(3.0, rel=1e-14)


def test_zpk_n_plane_root_at_origin_is_unity_at_1hz() -> None:
    z = parse_design('zpk([0],[],1,"n")')
    assert abs(z.response(1.0)) == pytest.approx(1.0, rel=1e-14)
    assert parse_design('zpk([],[0],1,"n")').response(1.0) == pytest.approx(-1j, rel=1e-14)


def test_zpk_n_plane_complex_pair() -> None:
    z = parse_design('zpk([],[1+i*2;1-i*2],5,"n")')
    assert _same_roots(z.poles, -TWO_PI * np.array([1 + 2j, 1 - 2j]))
    assert z.response(0.0) == pytest.approx(5.0, rel=1e-14)


@pytest.mark.parametrize("pair", ["1+i*2;1-i*2", "1+2i;1-2i", "1+2*i;1-2*i", "1 + 2*j; 1 - 2*j",
                                  "1-i*2;1+i*2", "1+i*2,1-i*2", "1+i*2;1-i*2;"])
def test_complex_notations_agree(pair: str) -> None:
    z = parse_design(f'zpk([],[{pair}],1,"n")')
    assert _same_roots(z.poles, -TWO_PI * np.array([1 + 2j, 1 - 2j]))


def test_pure_imaginary_and_exponents() -> None:
    z = parse_design('zpk([i*1.5e1;-i*15],[2e1;2E+1],1,"n")')
    assert np.allclose(np.sort(z.zeros.imag), [-TWO_PI * 15, TWO_PI * 15])
    assert np.allclose(z.poles, -TWO_PI * 20)


@pytest.mark.parametrize("design", ['zpk([],[-10],1,"n")', "zpk([],[2],1)", "pole(-5)",
                                    "pole2(-3,2)", "rpoly([1],[1;-2],1)"])
def test_unstable_poles_are_refused_as_foton_refuses_them(design: str) -> None:
    with pytest.raises(FotonError, match="right half plane"):
        parse_design(design)


# -- gains and concatenation -------------------------------------------------------------------
@pytest.mark.parametrize(("design", "value"), [
    ("gain(3)", 3.0), ('gain(3,"scalar")', 3.0),
    ('gain(20,"dB")', 10.0), ('gain(-6.0206,"db")', 0.5),
])
def test_gain(design: str, value: float) -> None:
    z = parse_design(design)
    assert z.zeros.size == 0 and z.poles.size == 0
    assert z.gain == pytest.approx(value, rel=1e-5)


def test_concatenation_multiplies() -> None:
    base = parse_design('zpk([1],[10],1,"n")')
    want = base.response(F_GRID) * 3
    for design in ('zpk([1],[10],1,"n")gain(3)', 'zpk([1],[10],1,"n") * gain(3)',
                   'zpk([1],\n  [10],1,"n") \\\n gain(3) % trailing comment'):
        assert _rel(parse_design(design).response(F_GRID), want) < 1e-12
    assert _rel((base * parse_design("gain(3)")).response(F_GRID), want) < 1e-12


def test_empty_design_is_unity() -> None:
    z = parse_design("   ")
    assert z.gain == 1.0 and z.zeros.size == 0 and z.poles.size == 0
    assert ZPK.unity().response(np.array([1.0, 2.0])) == pytest.approx([1.0, 1.0])


# -- classic designs against scipy -------------------------------------------------------------
_TYPES = {"LowPass": "lowpass", "HighPass": "highpass",
          "BandPass": "bandpass", "BandStop": "bandstop"}


@pytest.mark.parametrize("ftype", list(_TYPES))
@pytest.mark.parametrize(("fname", "spec"), [("butter", ()), ("cheby1", (1.0,)),
                                             ("cheby2", (40.0,)), ("ellip", (1.0, 40.0))])
def test_iir_designs_match_scipy_analog(fname: str, spec: tuple[float, ...], ftype: str) -> None:
    edges = (3.0, 30.0) if ftype.startswith("Band") else (10.0,)
    args = ",".join(str(x) for x in (4, *spec, *edges))
    got = parse_design(f'{fname}("{ftype}",{args})')
    design = getattr(signal, fname)
    wn = [TWO_PI * e for e in edges] if len(edges) == 2 else TWO_PI * edges[0]
    z, p, k = design(4, *spec, wn, btype=_TYPES[ftype], analog=True, output="zpk")
    _, want = signal.freqs_zpk(z, p, k, worN=TWO_PI * F_GRID)
    assert np.allclose(got.response(F_GRID), want, rtol=1e-9, atol=1e-12 * np.max(np.abs(want)))


def test_notch_depth_and_resgain_height_at_centre() -> None:
    notch = parse_design("notch(60,10,40)")
    assert abs(notch.response(60.0)) == pytest.approx(10 ** (-40 / 20), rel=1e-12)
    res = parse_design("resgain(3.2,8,20)")
    assert abs(res.response(3.2)) == pytest.approx(10.0, rel=1e-12)
    for z, f0 in ((notch, 60.0), (res, 3.2)):
        assert z.response(0.0) == pytest.approx(1.0, rel=1e-12)
        assert abs(z.response(1e4 * f0)) == pytest.approx(1.0, rel=1e-6)
        assert np.allclose(np.abs(z.poles), TWO_PI * f0)
        assert np.allclose(np.abs(z.zeros), TWO_PI * f0)


def test_pole_zero_helpers_in_their_planes() -> None:
    s = _s(F_GRID)
    w, q = TWO_PI * 5, 3.0
    cases = {
        "pole(5)": 1 / (s + 5),
        "pole(5,2)": 2 / (s + 5),
        'pole(5,2,"f")': 2 / (s + w),
        'pole(5,2,"n")': 2 / (1 + s / w),
        'zero(5,2,"n")': 2 * (1 + s / w),
        "pole2(5,3)": 1 / (s**2 + 5 / q * s + 25),
        'pole2(5,3,2,"n")': 2 / (1 + s / (w * q) + (s / w) ** 2),
        'zero2(5,3,2,"n")': 2 * (1 + s / (w * q) + (s / w) ** 2),
        "pole2(5,0.3)": 1 / (s + 5) ** 2,
    }
    for design, want in cases.items():
        assert _rel(parse_design(design).response(F_GRID), want) < 1e-12, design


def test_a_lone_zero_gets_foton_s_pole_at_twice_the_rate() -> None:
    s, c = _s(F_GRID), 2 * FS
    want = 2 * (1 + s / (TWO_PI * 5)) * -c / (s + c)
    assert _rel(parse_design('zero(5,2,"n")', FS).response(F_GRID), want) < 1e-12
    pair = parse_design('zero2(5,3,1,"n")', FS)
    assert np.allclose(np.abs(pair.poles), c) and pair.response(0.0) == pytest.approx(1.0)


def test_rpoly_is_rational_polynomial_in_s() -> None:
    s = _s(F_GRID)
    want = 2 * (s + 3) / (s**2 + 4 * s + 5)
    assert _rel(parse_design("rpoly([1;3],[1;4;5],2)").response(F_GRID), want) < 1e-12


# -- error messages ------------------------------------------------------------------------
@pytest.mark.parametrize(("design", "fragment"), [
    ('chebby1("LowPass",4,1,10)',
     "unknown foton function 'chebby1' in design 'chebby1(\"LowPass\",4,1,10)'"),
    ('zpk([1],[2],1,"x")', 'zpk(): plane must be one of "s", "f", "n", got "x"'),
    ('zpk([1],[2],1,"n"', "unbalanced parentheses"),
    ('zpk([1],[2],1,"n"))', "unbalanced parentheses"),
    ('zpk([1,[2],1,"n")', "unbalanced parentheses"),
    ("zpk([1],[2])", "zpk() takes 3 to 4 arguments, got 2"),
    ("gain(1,2,3)", "gain() takes 1 to 2 arguments, got 3"),
    ("gain(abc)", "expected a number"),
    ('gain("3")', "must be a number"),
    ("gain(1e999)", "not finite"),
    ('zpk([1+i*2],[3],1,"n")', "no complex-conjugate partner"),
    ('butter("LowPass",2.5,10)', "order must be an integer"),
    ('butter("BandPass",2,10,10)', "f1 and f2 must differ"),
    ('butter("BandPass",2,10)', "takes f1 and f2"),
    ('butter("Sideways",2,10)', "type must be one of"),
    ("notch(-60,10,40)", "must be positive"),
    ('sos(1,[0;0;0;0],"s")', "z-plane"),
    ("zpk([1],[-2],1) junk", "expected '('"),
    ("zpk([1],[-2],1)*", "ends with '*'"),
    ("zpk([1],[2],1)&", "unexpected character"),
    ('gain(1,"dB', "unterminated string"),
])
def test_errors_name_problem_and_design(design: str, fragment: str) -> None:
    with pytest.raises(FotonError) as info:
        parse_design(design)
    assert fragment in str(info.value)
    assert repr(design) in str(info.value)


def test_fuzz_only_foton_errors() -> None:
    rng = random.Random(20240611)
    alphabet = 'zpkgainotchresbuterchyelipol2rpy0123456789 ()[];,*+-.eE"\'sfn%\\\nij'
    seeds = ['zpk([1;2+i*3;2-i*3],[10],1,"n")gain(3)',
             'butter("LowPass",4,10)*cheby1("BandPass",2,1,3,30)',
             'ellip("HighPass",3,1,40,5)notch(60,10,40)resgain(3,5,20)',
             "pole2(3,4,1)zero(3,2)rpoly([1;2],[1;3;4],2)", NOMINAL_FM2]
    parsed = 0
    for n in range(3000):
        if n % 2:
            text = "".join(rng.choice(alphabet) for _ in range(rng.randint(0, 40)))
        else:
            chars = list(rng.choice(seeds))
            for _ in range(rng.randint(1, 4)):
                k = rng.randrange(len(chars))
                op = rng.random()
                if op < 1 / 3:
                    del chars[k]
                elif op < 2 / 3:
                    chars.insert(k, rng.choice(alphabet))
                else:
                    chars[k] = rng.choice(alphabet)
            text = "".join(chars)
        try:
            zpk = parse_design(text)
        except FotonError:
            continue
        parsed += 1
        try:
            zpk_to_sos(zpk, FS)
        except FotonError:
            pass
    assert parsed > 50  # the mutations must also exercise the discretization


# -- discretization ----------------------------------------------------------------------------
def _sos_response(sos: np.ndarray, f: np.ndarray) -> np.ndarray:
    return signal.sosfreqz(sos, worN=f, fs=FS)[1]


@pytest.mark.parametrize("design", [NOMINAL_FM1, NOMINAL_FM2, NOMINAL_FM3])
def test_nominal_sos_layout_and_stability(design: str) -> None:
    sos = design_to_sos(design, FS)
    assert sos.ndim == 2 and sos.shape[1] == 6
    assert np.all(sos[:, 3] == 1.0)
    poles = np.concatenate([np.roots(sec[3:]) for sec in sos])
    assert np.max(np.abs(poles)) < 1


@pytest.mark.parametrize("design", [NOMINAL_FM1, NOMINAL_FM3])
def test_discrete_matches_continuous_below_100hz(design: str) -> None:
    f = np.linspace(0.01, 99.9, 4000)
    zpk = parse_design(design)
    assert _rel(_sos_response(zpk_to_sos(zpk, FS), f), zpk.response(f)) < 1e-4


def test_discrete_excess_poles_follow_bilinear_bound() -> None:
    # A bilinear map cannot keep high-frequency asymptotes: each excess pole is off by
    # tan(x)/x - 1 ~ x^2/3, x = pi f / fs (1.2e-4 at 100 Hz).  FM2 has 8 poles, no zeros.
    f = np.linspace(0.01, 99.9, 4000)
    for zpk in (parse_design(NOMINAL_FM2), _nominal()):
        x = math.pi * f / FS
        bound = (zpk.poles.size - zpk.zeros.size) * (np.tan(x) / x - 1) * 1.05 + 1e-5
        err = np.abs(_sos_response(zpk_to_sos(zpk, FS), f) / zpk.response(f) - 1)
        assert np.all(err < bound)
        assert np.max(err[f < 30]) < 1e-4


def test_discrete_is_prewarped_bilinear_of_each_root() -> None:
    # H_d(e^{iwT}) = H'(i 2 fs tan(w T / 2)) with every root moved to 2 fs tan(|r| / 2 fs).
    zpk = _nominal() * parse_design('zpk([0.3],[],1,"n")')

    def warp(r: np.ndarray) -> np.ndarray:
        mag = np.abs(r)
        return r * 2 * FS * np.tan(mag / (2 * FS)) / np.where(r == 0, 1, mag)

    def dc(r: np.ndarray) -> complex:
        return complex(np.prod(-r[r != 0]))

    zw, pw = warp(zpk.zeros), warp(zpk.poles)
    warped = ZPK(zw, pw, float(np.real(zpk.gain * dc(zpk.zeros) / dc(zpk.poles) * dc(pw) / dc(zw))))
    f = np.logspace(-1, 3.5, 500)
    omega_warped = 2 * FS * np.tan(math.pi * f / FS) / TWO_PI
    assert _rel(_sos_response(zpk_to_sos(zpk, FS), f), warped.response(omega_warped)) < 1e-7


def test_butter_lowpass_equals_scipy_digital_design() -> None:
    f = np.logspace(-1, 3.8, 300)
    want = _sos_response(signal.butter(4, 100, fs=FS, output="sos"), f)
    assert _rel(_sos_response(design_to_sos('butter("LowPass",4,100)', FS), f), want) < 1e-9


def test_dc_gain_exact_and_gain_only_design() -> None:
    sos = design_to_sos('zpk([1],[10;20],7,"n")', FS)
    assert _sos_response(sos, np.array([1e-9]))[0] == pytest.approx(7.0, rel=1e-9)
    assert np.array_equal(design_to_sos("gain(2)", FS), [[2.0, 0, 0, 1.0, 0, 0]])


def test_unstable_zpk_discretizes_to_unstable_sos() -> None:
    sos = zpk_to_sos(ZPK([], [62.8], 1.0), FS)
    assert np.max(np.abs(np.roots(sos[0, 3:]))) > 1


def test_discretization_errors() -> None:
    with pytest.raises(FotonError, match="zeros but only"):
        zpk_to_sos(ZPK([-1.0], [], 1.0), FS)
    with pytest.raises(FotonError, match="sample rate"):
        zpk_to_sos(ZPK.unity(), -1.0)
