"""Reading and writing foton filter files (twind.loop.foton_file)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from twind.errors import FotonError
from twind.loop.foton_file import (
    FilterStage,
    FotonFileWarning,
    read_filter_file,
    write_filter_file,
)

FIXTURE = Path(__file__).parent / "data" / "C1TWN.txt"
FS = 16384.0


@pytest.fixture(scope="module")
def fixture_file():
    with warnings.catch_warnings():
        # The fixture mimics a clean foton file: any warning is a bug.
        warnings.simplefilter("error")
        return read_filter_file(FIXTURE)


def stage(ff, module, index):
    (found,) = [s for s in ff.modules[module] if s.index == index]
    return found


def response(sos, freqs_hz):
    return signal.sosfreqz(sos, worN=np.asarray(freqs_hz, dtype=float), fs=FS)[1]


# ----------------------------------------------------------------------------- layout


def test_modules_rate_and_order(fixture_file):
    assert fixture_file.rate_hz == FS
    assert list(fixture_file.modules) == ["ETMX_SUSPOS", "ETMX_SUSPIT", "ETMX_SUSYAW", "ETMX_SUSSIDE", "ETMX_LSC"]
    assert [s.index for s in fixture_file.modules["ETMX_SUSPOS"]] == [0, 1, 2]
    assert [s.index for s in fixture_file.modules["ETMX_SUSPIT"]] == [0, 5]
    assert fixture_file.modules["ETMX_SUSYAW"] == []
    assert fixture_file.modules["ETMX_LSC"] == []


def test_names_designs_and_switching(fixture_file):
    lp = stage(fixture_file, "ETMX_SUSPOS", 0)
    assert lp.name == "LP30"
    assert lp.design == 'zpk([],[30],1,"n")'
    assert lp.switching == {"type": 21, "ramp": 0, "timeout": 0}
    assert (lp.input_switching, lp.output_switching) == ("zero_history", "immediate")

    bw = stage(fixture_file, "ETMX_SUSPOS", 1)
    assert bw.switching == {"type": 22, "ramp": 16384, "timeout": 0}
    assert bw.output_switching == "ramp"

    ch = stage(fixture_file, "ETMX_SUSPIT", 5)
    # A backslash continues the design onto the next '#' line; pieces join without a separator.
    assert ch.design == 'cheby1("LowPass",6,1,300)gain(1)'
    assert ch.input_switching == "always_on"

    notch = stage(fixture_file, "ETMX_SUSSIDE", 9)
    assert notch.switching == {"type": 24, "ramp": 10, "timeout": 8192}
    assert notch.output_switching == "zero_crossing"


def test_gain_only_stage_from_tab_separated_integers(fixture_file):
    x2 = stage(fixture_file, "ETMX_SUSPOS", 2)
    np.testing.assert_array_equal(x2.sos, [[2.0, 0.0, 0.0, 1.0, 0.0, 0.0]])


def test_stage_keeps_its_own_copy_of_the_sos():
    sos = np.array([[1.0, 0.0, 0.0, 1.0, 0.0, 0.0]])
    s = FilterStage(0, "unity", sos)
    sos[0, 0] = 5.0
    assert s.sos[0, 0] == 1.0


# ----------------------------------------------------------------------------- convention


def test_single_pole_sign_and_order_convention(fixture_file):
    """A prewarped 30 Hz real pole: DC gain 1, -3 dB and -45 deg at 30 Hz, checked without scipy."""
    omega = 2 * FS * math.tan(math.pi * 30 / FS)
    k = omega / (2 * FS)
    z_pole = (1 - k) / (1 + k)
    g = k / (1 + k)
    # File line: GAIN A1 A2 B1 B2 = g, -z_pole, 0, 1, 0 -> sos [g, g*1, g*0, 1, A1, A2].
    expected = [[g, g, 0.0, 1.0, -z_pole, 0.0]]
    sos = stage(fixture_file, "ETMX_SUSPOS", 0).sos
    np.testing.assert_allclose(sos, expected, rtol=1e-13, atol=0)

    def h(f_hz):
        zinv = np.exp(-2j * np.pi * f_hz / FS)
        b0, b1, b2, a0, a1, a2 = sos[0]
        return (b0 + b1 * zinv + b2 * zinv**2) / (a0 + a1 * zinv + a2 * zinv**2)

    assert abs(h(0.0)) == pytest.approx(1.0, rel=1e-12)
    assert abs(h(30.0)) == pytest.approx(1 / math.sqrt(2), rel=1e-12)
    assert np.degrees(np.angle(h(30.0))) == pytest.approx(-45.0, abs=1e-9)
    # The wrong sign on A1 would put the pole near Nyquist, the wrong order would invert it.
    assert abs(2 * g / (1 + z_pole)) < 0.01


def raw_stage(prefix):
    """Independently split a stage's GAIN and (A1 A2 B1 B2) rows out of the fixture text."""
    lines = FIXTURE.read_text().splitlines()
    (start,) = [i for i, line in enumerate(lines) if line.startswith(prefix)]
    tokens = lines[start].split()
    n = int(tokens[3])
    rows = [[float(t) for t in tokens[8:12]]]
    rows += [[float(t) for t in lines[start + k].split()] for k in range(1, n)]
    return float(tokens[7]), rows


def rcg_iir_filter(x, gain, rows):
    """fm10Gen.c iir_filter(): input scaled by gain, then direct-form-II sections a1 a2 b1 b2."""
    hist = np.zeros((len(rows), 2))
    out = np.empty(len(x))
    for n, sample in enumerate(x):
        y = sample * gain
        for k, (a1, a2, b1, b2) in enumerate(rows):
            h1, h2 = hist[k]
            new_hist = y - h1 * a1 - h2 * a2
            y = new_hist + h1 * b1 + h2 * b2
            hist[k] = (new_hist, h1)
        out[n] = y
    return out


@pytest.mark.parametrize("prefix, module, index", [
    ("ETMX_SUSPOS 0 ", "ETMX_SUSPOS", 0),
    ("ETMX_SUSPOS 1 ", "ETMX_SUSPOS", 1),
    ("ETMX_SUSSIDE 9 ", "ETMX_SUSSIDE", 9),
])
def test_sos_matches_rcg_time_domain_filter(fixture_file, prefix, module, index):
    gain, rows = raw_stage(prefix)
    x = np.random.default_rng(1).standard_normal(400)
    expected = rcg_iir_filter(x, gain, rows)
    got = signal.sosfilt(stage(fixture_file, module, index).sos, x)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12 * np.max(np.abs(expected)))


@pytest.mark.parametrize("module, index, reference", [
    ("ETMX_SUSPOS", 1, lambda: signal.butter(4, 100, fs=FS, output="sos")),
    ("ETMX_SUSPIT", 5, lambda: signal.cheby1(6, 1, 300, fs=FS, output="sos")),
    ("ETMX_SUSSIDE", 9, lambda: signal.tf2sos(*signal.iirnotch(60, 30, fs=FS))),
])
def test_response_equals_scipy_design(fixture_file, module, index, reference):
    freqs = np.logspace(-1, np.log10(FS / 2 * 0.99), 400)
    got = response(stage(fixture_file, module, index).sos, freqs)
    want = response(reference(), freqs)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-14)


# ----------------------------------------------------------------------------- round trip


def test_round_trip_is_identical(fixture_file, tmp_path):
    out = tmp_path / "C1TWN.txt"
    write_filter_file(out, fixture_file.modules, fixture_file.rate_hz)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = read_filter_file(out)
    assert again.rate_hz == fixture_file.rate_hz
    assert again.modules == fixture_file.modules
    assert list(again.modules) == list(fixture_file.modules)
    # Writing what was read back gives the same text: the writer is a fixed point.
    out2 = tmp_path / "again.txt"
    write_filter_file(out2, again.modules, again.rate_hz)
    assert out2.read_text() == out.read_text()


def test_round_trip_is_bit_exact_for_arbitrary_gains(tmp_path):
    rng = np.random.default_rng(7)
    modules = {}
    for m in range(20):
        stages = []
        for index in range(10):
            n = int(rng.integers(1, 4))
            raw = rng.uniform(-2, 2, size=(n, 4))
            gain = float(rng.choice([-1, 1]) * 10 ** rng.uniform(-9, 3))
            # Exactly what the reader builds from GAIN and (A1 A2 B1 B2) rows.
            sos = np.array([[1.0, b1, b2, 1.0, a1, a2] for a1, a2, b1, b2 in raw])
            sos[0, :3] *= gain
            stages.append(FilterStage(index, f"s{index}", sos, None, {"type": 21, "ramp": 0, "timeout": 0}))
        modules[f"MOD{m}"] = stages
    out = tmp_path / "fuzz.txt"
    write_filter_file(out, modules, FS)
    assert read_filter_file(out).modules == modules


def test_writer_normalises_scipy_sections(tmp_path):
    sos = signal.butter(4, 100, fs=FS, output="sos")
    spread = sos.copy()
    spread[0, :3] /= 4.0  # gain moved into the second section
    spread[1, :3] *= 8.0
    spread[1, 3:] *= 2.0  # and a0 != 1
    out = tmp_path / "spread.txt"
    write_filter_file(out, {"LP": [FilterStage(0, "bw", spread)]}, FS)
    (back,) = read_filter_file(out).modules["LP"]
    np.testing.assert_array_equal(back.sos[1, [0, 3]], [1.0, 1.0])
    freqs = np.logspace(-1, 3.5, 200)
    np.testing.assert_allclose(response(back.sos, freqs), response(sos, freqs), rtol=1e-12, atol=1e-16)
    assert back.switching == {"type": 21, "ramp": 0, "timeout": 0}


def test_zero_gain_stage_round_trips(tmp_path):
    off = FilterStage(3, "off", [[0.0, 0.0, 0.0, 1.0, -0.5, 0.0]], "gain(0)", {"type": 21})
    out = tmp_path / "off.txt"
    write_filter_file(out, {"M": [off]}, 2048)
    (back,) = read_filter_file(out).modules["M"]
    np.testing.assert_array_equal(back.sos, off.sos)
    assert back.design == "gain(0)"
    assert read_filter_file(out).rate_hz == 2048.0


# ----------------------------------------------------------------------------- malformed files

HEADER = ["# MODULES SUSPOS SUSPIT", "# SAMPLING RATE 16384"]  # lines 1, 2; bodies start at line 3
GOOD = "SUSPOS 0 21 1 0 0 lp 0.5 -0.5 0.0 1.0 0.0"
TWO = "SUSPOS 0 21 2 0 0 bw 1.0 -1.9 0.9 2.0 1.0"


def write_body(tmp_path, body, name="bad.txt"):
    path = tmp_path / name
    path.write_text("\n".join([*HEADER, *body]) + "\n")
    return path


@pytest.mark.parametrize("body, message", [
    ([TWO, "  -1.9 0.9 2.0"], "bad.txt:4: expected 4 coefficients per section line, got 3"),
    ([TWO, "  -1.9 0.9 2.0 1.0 7"], "bad.txt:4: expected 4 coefficients per section line, got 5"),
    (["SUSPOS 0 21 3 0 0 bw 1.0 -1.9 0.9 2.0 1.0", "-1.9 0.9 2.0 1.0"],
     "bad.txt:3: SUSPOS FM1 (index 0) declares SECTIONS=3 but only 1 of 2 section line(s) follow before the file ends"),
    ([TWO, "SUSPOS 1 21 1 0 0 g 1.0 0 0 0 0"], "bad.txt:3: SUSPOS FM1 (index 0) declares SECTIONS=2 but only 0 of 1 section line(s) follow before line 4 starts a new stage"),
    (["SUSPOS 10 21 1 0 0 lp 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: INDEX must be 0..9 (FM1..FM10), got 10"),
    (["SUSPOS -1 21 1 0 0 lp 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: INDEX must be 0..9"),
    (["SUSPOS one 21 1 0 0 lp 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: INDEX must be an integer, got 'one'"),
    (["SUSPOS 0 21 1 0 0 lp 0.5 -0.5 abc 1.0 0.0"], "bad.txt:3: A2 must be a number, got 'abc'"),
    (["SUSPOS 0 21 1 0 0 lp nan -0.5 0.0 1.0 0.0"], "bad.txt:3: GAIN must be a number, got 'nan'"),
    (["SUSPOS 0 21 1 0 0 lp 1e999 -0.5 0.0 1.0 0.0"], "bad.txt:3: GAIN overflows"),
    ([TWO, "-1.9 x 2.0 1.0"], "bad.txt:4: A2 must be a number, got 'x'"),
    (["hello world"], "bad.txt:3: expected a stage line of 12 fields (MODULE INDEX TYPE SECTIONS RAMP TIMEOUT NAME GAIN A1 A2 B1 B2), got 2"),
    ([GOOD + " 0.0"], "bad.txt:3: expected a stage line of 12 fields"),
    (["SUSPOS 0 31 1 0 0 lp 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: TYPE must be 11..14 or 21..24"),
    (["SUSPOS 0 20 1 0 0 lp 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: TYPE must be 11..14 or 21..24"),
    (["SUSPOS 0 21 0 0 0 lp 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: SECTIONS must be 1..10"),
    (["SUSPOS 0 21 11 0 0 lp 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: SECTIONS must be 1..10 (FIR stages are not supported), got 11"),
    (["SUSPOS 0 21 1 -1 0 lp 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: RAMP must not be negative"),
    (["SUSPOS 0 21 1 0 1.5 lp 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: TIMEOUT must be an integer, got '1.5'"),
    (["SUSPOS 0 21 1 0 0 " + "n" * 32 + " 0.5 -0.5 0.0 1.0 0.0"], "bad.txt:3: NAME 'nnnn"),
    (["0.1 0.2 0.3 0.4"], "bad.txt:3: section coefficient line without a stage line before it"),
    ([GOOD, "0.1 0.2 0.3 0.4"], "bad.txt:4: section coefficient line without a stage line before it"),
    ([GOOD, GOOD], "bad.txt:4: SUSPOS FM1 (index 0) is defined twice (first on line 3)"),
    (["# DESIGN   SUSPOS x zpk([],[1],1)"], "bad.txt:3: INDEX must be an integer, got 'x'"),
    (["# DESIGN   SUSPOS"], "bad.txt:3: expected '# DESIGN MODULE INDEX design-string'"),
    (["# DESIGN   SUSPOS 0 gain(1)", "# DESIGN   SUSPOS 0 gain(2)"], "bad.txt:4: second DESIGN for SUSPOS FM1 (index 0) (first on line 3)"),
    (["# SAMPLING RATE fast"], "bad.txt:3: SAMPLING RATE must be a number, got 'fast'"),
    (["# SAMPLING RATE 0"], "bad.txt:3: SAMPLING RATE must be positive"),
    (["# SAMPLING RATE 2048"], "bad.txt:3: SAMPLING RATE 2048 contradicts 16384 on line 2"),
    (["# SAMPLING SUSPOS fast"], "bad.txt:3: sampling rate of SUSPOS must be a number"),
])
def test_malformed_files_name_file_line_and_problem(tmp_path, body, message):
    path = write_body(tmp_path, body)
    with pytest.raises(FotonError) as info:
        read_filter_file(path)
    assert str(info.value).startswith(str(path.parent) + "/")
    assert message in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(FotonError, match=r"nope\.txt: cannot read filter file"):
        read_filter_file(tmp_path / "nope.txt")


def test_non_utf8_line(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_bytes(b"# MODULES A\n\xff\xfe junk\n")
    with pytest.raises(FotonError, match=r"bad\.txt:2: line is not valid UTF-8"):
        read_filter_file(path)


def test_corrupted_files_never_raise_anything_but_foton_error(tmp_path):
    text = FIXTURE.read_text()
    rng = np.random.default_rng(3)
    path = tmp_path / "mutant.txt"
    junk = ["", " ", "x", "#", "\n", "9", "-", "e", "\\", "1.0 "]
    for _ in range(300):
        chars = list(text)
        for _ in range(int(rng.integers(1, 4))):
            pos = int(rng.integers(len(chars)))
            if rng.random() < 0.5:
                del chars[pos]
            else:
                chars.insert(pos, str(rng.choice(junk)))
        path.write_text("".join(chars))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FotonFileWarning)
            try:
                read_filter_file(path)
            except FotonError:
                pass


# ----------------------------------------------------------------------------- tolerated oddities


def test_unlisted_module_is_kept_with_a_warning(tmp_path):
    path = write_body(tmp_path, [GOOD, "OTHER 4 21 1 0 0 g 2.0 0 0 0 0"])
    with pytest.warns(FotonFileWarning, match=r"bad\.txt:4: module OTHER has stages but is not listed"):
        ff = read_filter_file(path)
    assert list(ff.modules) == ["SUSPOS", "SUSPIT", "OTHER"]
    assert ff.modules["OTHER"][0].index == 4


def test_file_without_modules_line_warns_once(tmp_path):
    path = tmp_path / "bare.txt"
    path.write_text(GOOD + "\n" + GOOD.replace("SUSPOS", "SUSPIT") + "\n")
    with pytest.warns(FotonFileWarning, match=r"bare\.txt:1: no '# MODULES' line") as record:
        ff = read_filter_file(path)
    assert len(record) == 1
    assert list(ff.modules) == ["SUSPOS", "SUSPIT"]
    assert ff.rate_hz is None


def test_design_without_coefficients_is_ignored_with_a_warning(tmp_path):
    path = write_body(tmp_path, ["# DESIGN   SUSPIT 3 zpk([],[1],1,\"n\")", GOOD])
    with pytest.warns(FotonFileWarning, match=r"bad\.txt:3: DESIGN for SUSPIT FM4 \(index 3\) has no coefficient lines"):
        ff = read_filter_file(path)
    assert ff.modules["SUSPIT"] == []


def test_module_rate_disagreeing_with_file_rate_warns(tmp_path):
    path = write_body(tmp_path, ["# SAMPLING SUSPOS 2048", GOOD])
    with pytest.warns(FotonFileWarning, match=r"bad\.txt:3: SUSPOS samples at 2048 Hz, not at the file's 16384 Hz"):
        read_filter_file(path)


def test_comments_and_blank_lines_between_section_lines_are_skipped(tmp_path):
    # The RCG loader skips comment lines everywhere, also inside a stage.
    path = write_body(tmp_path, [TWO, "", "# a remark", "  -1.9 0.9 2.0 1.0"])
    (bw,) = read_filter_file(path).modules["SUSPOS"]
    assert bw.sos.shape == (2, 6)


# ----------------------------------------------------------------------------- writer errors

LP = [[0.5, 0.5, 0.0, 1.0, -0.5, 0.0]]


@pytest.mark.parametrize("modules, message", [
    ({"M": [FilterStage(0, "d", [[0.0, 1.0, 0.0, 1.0, 0.0, 0.0]])]}, "M FM1 (index 0) 'd': section 0 has b0 == 0"),
    ({"M": [FilterStage(0, "a", [[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]])]}, "section 0 has a0 == 0"),
    ({"M": [FilterStage(2, "a", LP), FilterStage(2, "b", LP)]}, "M FM3 (index 2) 'b': two stages with this index"),
    ({"M": [FilterStage(10, "a", LP)]}, "index must be 0..9"),
    ({"M": [FilterStage(0, "two words", LP)]}, "name 'two words' must be one non-empty token"),
    ({"M": [FilterStage(0, "#x", LP)]}, "not starting with '#'"),
    ({"M": [FilterStage(0, "n" * 32, LP)]}, "longer than 31 characters"),
    ({"M": [FilterStage(0, "a", LP, "zpk([],[1],1)\ngain(2)")]}, "design string must be a single line"),
    ({"M": [FilterStage(0, "a", LP, "gain(2) \\")]}, "must not end with a backslash"),
    ({"M": [FilterStage(0, "a", LP, None, {"Ramp": 3})]}, "unknown switching field(s) ['Ramp']"),
    ({"M": [FilterStage(0, "a", LP, None, {"type": 31})]}, "switching type must be 11..14 or 21..24"),
    ({"M": [FilterStage(0, "a", LP, None, {"ramp": -1})]}, "switching ramp must be a non-negative integer"),
    ({"M": [FilterStage(0, "a", LP, None, {"timeout": 0.5})]}, "switching timeout must be a non-negative integer"),
    ({"M": [FilterStage(0, "a", np.tile(LP, (11, 1)))]}, "11 sections; the RCG takes at most 10"),
    ({"bad name": []}, "module name 'bad name'"),
])
def test_writer_rejects_what_the_format_cannot_hold(tmp_path, modules, message):
    path = tmp_path / "out.txt"
    with pytest.raises(FotonError) as info:
        write_filter_file(path, modules, FS)
    assert str(info.value).startswith(str(path) + ": ")
    assert message in str(info.value)


@pytest.mark.parametrize("rate", [0, -1.0, float("nan"), "16384"])
def test_writer_rejects_bad_rate(tmp_path, rate):
    with pytest.raises(FotonError, match="sampling rate must be a positive number"):
        write_filter_file(tmp_path / "out.txt", {}, rate)


def test_writer_reports_unwritable_path(tmp_path):
    with pytest.raises(FotonError, match="cannot write filter file"):
        write_filter_file(tmp_path / "missing" / "out.txt", {"M": []}, FS)


@pytest.mark.parametrize("sos", [
    np.zeros((0, 6)), np.zeros(6), np.zeros((2, 5)), [[np.inf, 0, 0, 1, 0, 0]], [[1, 0], [1, 0, 0]], "abc",
])
def test_stage_rejects_bad_sos(sos):
    with pytest.raises(FotonError, match="sos"):
        FilterStage(0, "x", sos)
