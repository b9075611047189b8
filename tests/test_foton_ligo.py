"""twind's foton against LIGO's own (python-foton, the optional extra ``twind[foton]``).

Over a generated set of designs using every function of foton's design language with its
optional arguments, twind and ``foton.FilterDesign`` accept and refuse the same designs,
and where both accept they make the same digital filter: the same response, poles, zeros
and gain.  Every foton file the tests use reads the same as ``foton.FilterFile``.
"""

from __future__ import annotations

import io
import math
import os
import random
import re
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
from scipy import signal
from scipy.optimize import linear_sum_assignment

from twind.cli import main
from twind.errors import FotonError
from twind.loop import FOTON_VARIABLE
from twind.loop.filtermodule import design_sections
from twind.loop.foton import NOMINAL_FM1, NOMINAL_FM2, NOMINAL_FM3, design_to_sos
from twind.loop.foton_file import FilterStage, read_filter_file, write_filter_file

if os.environ.get("TWIND_REQUIRE_FOTON"):  # CI: the extra must be there
    import foton
else:
    foton = pytest.importorskip("foton")

RATE = 16384.0
F = np.geomspace(0.01, 8000.0, 400)
FIXTURE = Path(__file__).parent / "data" / "C1TWN.txt"


def _ligo(design: str, rate: float = RATE) -> np.ndarray | None:
    """foton's sections for `design`, None where foton refuses it."""
    ligo = foton.FilterDesign("", rate=rate)
    return np.array(ligo.get_sos()) if ligo.filt.filter(design) else None


def _twind(design: str, rate: float = RATE) -> np.ndarray | None:
    try:
        return design_to_sos(design, rate)
    except FotonError:
        return None


def _roots(sos: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Zeros and poles off the origin (first-order sections hold one of each there)."""
    z = np.concatenate([np.roots(row[:3] / row[0]) for row in sos])
    p = np.concatenate([np.roots(row[3:] / row[3]) for row in sos])
    k = float(np.prod(sos[:, 0] / sos[:, 3]))
    return z[np.abs(z) > 1e-12], p[np.abs(p) > 1e-12], k


def _matched(a: np.ndarray, b: np.ndarray) -> float:
    """Largest distance between the roots of `a` and `b`, paired as closely as they go."""
    if a.size != b.size:
        return math.inf
    if a.size == 0:
        return 0.0
    rows, cols = linear_sum_assignment(np.abs(a[:, None] - b[None, :]))
    return float(np.max(np.abs(a[rows] - b[cols])))


# -- the generated designs -------------------------------------------------------------
def _n(x: float) -> str:
    return f"{x:.6g}"


def _root(rng: random.Random, plane: str, *, pole: bool) -> list[str]:
    """One real root or a conjugate pair, stable for a pole, as foton writes them."""
    top = 2e4 if plane == "s" else 3e3
    mag = math.exp(rng.uniform(math.log(0.05), math.log(top)))
    sign = -1.0 if plane in ("s", "f") else 1.0  # the stable side of the plane
    if not pole and rng.random() < 0.2:
        sign = -sign
    if not pole and rng.random() < 0.1:
        return ["0"]
    if rng.random() < 0.5:
        return [_n(sign * mag)]
    q = math.exp(rng.uniform(math.log(0.6), math.log(100)))
    re, im = sign * mag / (2 * q), mag * math.sqrt(1 - 1 / (4 * q * q))
    return [f"{_n(re)}+i*{_n(im)}", f"{_n(re)}-i*{_n(im)}"]


def _zpk(rng: random.Random) -> str:
    plane = rng.choice(["s", "f", "n", None])
    inplane = plane or "s"
    zeros = [r for _ in range(rng.randint(0, 3)) for r in _root(rng, inplane, pole=False)]
    poles = [r for _ in range(rng.randint(0, 3)) for r in _root(rng, inplane, pole=True)]
    tail = f',"{plane}"' if plane else ""
    return f"zpk([{';'.join(zeros)}],[{';'.join(poles)}],{_n(rng.uniform(-5, 5))}{tail})"


def _optional(rng: random.Random, required: list[str], optional: list[str]) -> str:
    return ",".join(required + optional[:rng.randint(0, len(optional))])


def _pole(rng: random.Random) -> str:
    fname = rng.choice(["pole", "zero", "pole2", "zero2"])
    plane = rng.choice(["s", "f", "n"])
    f = 0.0 if rng.random() < 0.05 else math.exp(rng.uniform(math.log(0.05), math.log(3e3)))
    if plane == "s":
        f *= 2 * math.pi
    required = [_n(f)]
    if fname.endswith("2"):
        required.append(_n(math.exp(rng.uniform(math.log(0.1), math.log(100)))))
    args = _optional(rng, required, [_n(rng.uniform(-3, 3)), '"' + plane + '"'])
    return f"{fname}({args})"


def _notch(rng: random.Random) -> str:
    fname = rng.choice(["notch", "resgain"])
    f = math.exp(rng.uniform(math.log(0.1), math.log(3e3)))
    q = math.exp(rng.uniform(math.log(0.3), math.log(100)))
    level = 0.0 if fname == "notch" and rng.random() < 0.3 else rng.uniform(2.0, 80.0)
    return f"{fname}({_optional(rng, [_n(f), _n(q)], [_n(level)])})"


def _iir(rng: random.Random) -> str:
    fname = rng.choice(["butter", "cheby1", "cheby2", "ellip"])
    btype = rng.choice(["LowPass", "HighPass", "BandPass", "BandStop"])
    spec = {"butter": [], "cheby1": [rng.uniform(0.1, 3)], "cheby2": [rng.uniform(20, 80)],
            "ellip": [rng.uniform(0.1, 3), rng.uniform(20, 80)]}[fname]
    edges = [math.exp(rng.uniform(math.log(0.5), math.log(3e3)))]
    if btype.startswith("Band"):
        edges.append(edges[0] * rng.uniform(1.2, 3.0))
        rng.shuffle(edges)
    # python-foton 4.1.5 aborts the process on a first-order ellip
    order = rng.randint(2 if fname == "ellip" else 1, 4 if btype.startswith("Band") else 8)
    return f'{fname}("{btype}",{",".join(_n(x) for x in (order, *spec, *edges))})'


def _gain(rng: random.Random) -> str:
    unit = rng.choice(['"dB"', '"scalar"'])
    return f"gain({_optional(rng, [_n(rng.uniform(-10, 10))], [unit])})"


def _rpoly(rng: random.Random) -> str:
    num = np.poly([-math.exp(rng.uniform(0, 6)) for _ in range(rng.randint(0, 2))])
    den = np.poly([-math.exp(rng.uniform(0, 6)) for _ in range(rng.randint(1, 3))])
    vec = lambda c: ";".join(_n(x) for x in np.atleast_1d(c))  # noqa: E731
    return f"rpoly([{vec(num)}],[{vec(den)}],{_n(rng.uniform(0.1, 5))})"


def _z_roots(rng: random.Random, n: int, *, inside: bool) -> list[complex]:
    """n z-plane roots in conjugate pairs (and one real for odd n), near z = 1 mostly."""
    out: list[complex] = []
    while len(out) < n:
        r = 1 - math.exp(rng.uniform(math.log(1e-4), math.log(1.9)))
        r = r if inside or rng.random() < 0.7 else rng.uniform(-3, 3)
        if n - len(out) >= 2 and rng.random() < 0.6:
            angle = math.exp(rng.uniform(math.log(1e-3), math.log(3.0)))
            out += [abs(r) * complex(math.cos(angle), math.sin(angle)) * (1 if r > 0 else -1)]
            out.append(out[-1].conjugate())
        else:
            out.append(complex(r))
    return out


def _zv(roots: list[complex]) -> str:
    return ";".join(f"{_n(r.real)}+i*{_n(r.imag)}" if r.imag else _n(r.real) for r in roots)


def _digital(rng: random.Random) -> str:
    fname = rng.choice(["sos", "zroots", "direct", "biquad", "comb"])
    if fname == "comb":
        f = math.exp(rng.uniform(math.log(1), math.log(3e3)))
        q = math.exp(rng.uniform(math.log(2), math.log(100)))
        amp, n = _n(rng.uniform(-60, 60)), str(rng.randint(0, 20))
        if f < 500:  # foton's gain overflows past ~35 harmonics: N given, at most 20
            return f"comb({_n(f)},{_n(q)},{amp},{rng.randint(1, 20)})"
        return f"comb({_optional(rng, [_n(f), _n(q)], [amp, n])})"
    if fname == "zroots":
        zeros = _z_roots(rng, rng.randint(0, 3), inside=False)
        poles = _z_roots(rng, rng.randint(0, 3), inside=True)
        args = _optional(rng, [f"[{_zv(zeros)}]", f"[{_zv(poles)}]"], [_n(rng.uniform(-3, 3))])
        return f"zroots({args})"
    zeros = np.poly(_z_roots(rng, 2, inside=False)).real
    poles = np.poly(_z_roots(rng, 2, inside=True)).real
    if fname == "biquad":
        coef = (*zeros * rng.uniform(0.1, 3), *poles[1:])
        return f"biquad({','.join(_n(x) for x in coef)})"
    if fname == "direct":
        return f"direct([{';'.join(map(_n, zeros))}],[{';'.join(_n(-x) for x in poles[1:])}])"
    sections = [np.concatenate([np.poly(_z_roots(rng, 2, inside=False)).real[1:],
                                np.poly(_z_roots(rng, 2, inside=True)).real[1:]])
                for _ in range(rng.randint(1, 3))]
    coef = np.concatenate(sections)
    online = rng.random() < 0.3
    if online:
        coef = np.concatenate([np.roll(sec, 2) for sec in sections])
    tail = ',"o"' if online else rng.choice(["", ',"s"'])
    return f"sos({_n(rng.uniform(0.1, 3))},[{';'.join(map(_n, coef))}]{tail})"


MAKERS = [_zpk, _pole, _notch, _iir, _gain, _rpoly, _digital]


def _designs(seed: int, n: int) -> list[str]:
    rng = random.Random(seed)
    out = []
    for _ in range(n):
        factors = [rng.choice(MAKERS)(rng) for _ in range(rng.choice([1, 1, 1, 2, 3]))]
        out.append(rng.choice(["", "*", " "]).join(factors))
    return out


DESIGNS = _designs(20261128, 500)


def test_the_generated_designs_use_every_function_and_both_verdicts() -> None:
    names = {"zpk", "pole", "zero", "pole2", "zero2", "notch", "resgain", "butter", "cheby1",
             "cheby2", "ellip", "gain", "rpoly", "sos", "zroots", "direct", "biquad", "comb",
             '"n"', '"f"', '"s"', '"o"', '"dB"'}
    assert all(any(f"{name}(" in d or name in d for d in DESIGNS) for name in names)
    refused = sum(_ligo(d) is None for d in DESIGNS)
    assert 10 < refused < len(DESIGNS) / 2


@pytest.mark.parametrize("chunk", range(4))
def test_twind_makes_the_filter_ligo_s_foton_makes(chunk: int) -> None:
    for design in DESIGNS[chunk::4]:
        ligo, ours = _ligo(design), _twind(design)
        assert (ligo is None) == (ours is None), (
            f"{design}: foton {'refuses' if ligo is None else 'accepts'}, twind "
            f"{'refuses' if ours is None else 'accepts'}")
        if ligo is None:
            continue
        _assert_same_filter(ligo, ours, design)


def _assert_same_filter(ligo: np.ndarray, ours: np.ndarray, what: str) -> None:
    """The same response, poles, zeros and gain; sections may be paired differently."""
    h_ligo = signal.sosfreqz(ligo, worN=F, fs=RATE)[1]
    h_ours = signal.sosfreqz(ours, worN=F, fs=RATE)[1]
    scale = np.max(np.abs(h_ligo))
    # rounding: foton's own reaches 1e-7 of a filter's gain (butter high-passes), and the
    # sections of a sharp resonance at 0.02 Hz hold it to ~1e-6 at 16384 Hz
    assert np.all(np.abs(h_ours - h_ligo) <= 1e-5 * np.abs(h_ligo) + 1e-7 * scale), what
    (z1, p1, k1), (z2, p2, k2) = _roots(ligo), _roots(ours)
    assert _matched(p1, p2) < 1e-6 and _matched(z1, z2) < 1e-6, what
    assert k2 == pytest.approx(k1, rel=1e-6), what


@pytest.mark.parametrize(("design", "what"), [
    ("notch(16,30,40)", "foton's Q: f over half the -3 dB width"),
    ("resgain(3,8,8)", "resgain: the inverse of a notch"),
    ("pole(5)", "pole: the s plane by default, gain 1"),
    ('zero(5,1,"n")', "a lone zero: a pole at twice the rate, sign turned"),
    ('zero2(3,10,1,"n")pole2(5,10,1,"n")', "each function its own sections"),
    ('ellip("LowPass",4,1,40,20)', "IIR designs are digital, prewarped at the edge"),
    ('zpk([-10],[10],1,"n")', 'a right-half-plane "n" zero normalised by its magnitude'),
    ('zpk([-9000],[-10],1,"f")', "a zero above Nyquist folds"),
    ("pole2(3,0.3)", "Q <= 1/2: a double real pole"),
])
def test_the_differences_the_issue_found_are_gone(design: str, what: str) -> None:
    ligo, ours = _ligo(design), _twind(design)
    assert ligo is not None and ours is not None, what
    h_ligo = signal.sosfreqz(ligo, worN=F, fs=RATE)[1]
    h_ours = signal.sosfreqz(ours, worN=F, fs=RATE)[1]
    assert np.max(np.abs(h_ours / h_ligo - 1)) < 1e-8, what


@pytest.mark.parametrize("design", [
    "pole(-5)", 'zpk([],[-10],1,"n")', "notch(16,30,2)", "notch(16,0.4)", "resgain(3,8,2)",
    "resgain(16,0.6,20)", 'zpk([1],[-2],1,"x")', "zpk([1+i*2],[-3],1)", "gain(2,\"foo\")",
    "notch(9000,30,40)", 'pole(9000,1,"f")', 'zpk([1],[-2],1,"n");gain(3)',
])
def test_what_foton_refuses_twind_refuses(design: str) -> None:
    assert _ligo(design) is None
    with pytest.raises(FotonError):
        design_to_sos(design, RATE)


# -- foton files -----------------------------------------------------------------------
def _written_by_twind(tmp_path: Path) -> Path:
    designs = [NOMINAL_FM1, NOMINAL_FM2, NOMINAL_FM3, 'butter("LowPass",4,100)',
               "notch(16,30,40)", 'zero2(3,10,1,"n")pole2(5,10,1,"n")']
    stages = [FilterStage(i, f"S{i}", design_to_sos(d, RATE), d,
                          {"type": 21 + i % 4, "ramp": 16 * i, "timeout": 8 * i})
              for i, d in enumerate(designs)]
    path = tmp_path / "C1SUSETMX.txt"
    write_filter_file(path, {"ETMX_SUSPOS": stages, "ETMX_SUSPIT": stages[:2]}, RATE)
    return path


def _rewritten(tmp_path: Path) -> Path:
    fixture = read_filter_file(FIXTURE)
    path = tmp_path / "C1TWN.txt"
    write_filter_file(path, fixture.modules, fixture.rate_hz)
    return path


@pytest.mark.parametrize("which", ["fixture", "rewritten", "written"])
def test_foton_files_read_as_foton_reads_them(which: str, tmp_path: Path) -> None:
    path = {"fixture": lambda _: FIXTURE, "rewritten": _rewritten,
            "written": _written_by_twind}[which](tmp_path)
    ours, theirs = read_filter_file(path), foton.FilterFile(str(path))
    assert sorted(ours.modules) == sorted(theirs)
    for name, stages in ours.modules.items():
        module = theirs[name]
        assert module.rate == ours.rate_hz
        assert [i for i in range(10) if not module[i].is_empty] == [s.index for s in stages]
        for stage in stages:
            section = module[stage.index]
            assert section.name == stage.name
            _assert_same_filter(np.array(section.get_sos()), stage.sos, stage.name)
            assert (section.input_switch, section.output_switch) == (
                _SWITCH_IN[stage.input_switching], _SWITCH_OUT[stage.output_switching])
            if which == "written":  # foton finds twind's designs and coefficients agree
                assert "".join(section.design.split()) == "".join(stage.design.split())


_SWITCH_IN = {"always_on": "AlwaysOn", "zero_history": "ZeroHistory"}
_SWITCH_OUT = {"immediate": "Immediately", "ramp": "Ramp", "input_crossing": "InputCrossing",
               "zero_crossing": "ZeroCrossing"}


# -- asking twind to use LIGO's foton ---------------------------------------------------
def _simulate(args: list[str]) -> dict[str, float]:
    out = io.StringIO()
    with redirect_stdout(out):
        assert main([*args, "simulate", "--duration", "1", "--seed", "3"]) == 0
    return {k: float(v) for k, v in re.findall(r"^(C1:SUS-ETMX_\S+)\s+rms\s+(\S+)",
                                               out.getvalue(), re.M)}


@pytest.mark.slow
def test_twind_runs_ligo_s_foton_when_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(FOTON_VARIABLE, "twind")  # restored after the test
    ours = design_sections(NOMINAL_FM2, RATE)
    assert not np.array_equal(ours, _ligo(NOMINAL_FM2))
    rms_ours = _simulate([])
    rms_ligo = _simulate(["--foton", "python-foton"])
    assert os.environ[FOTON_VARIABLE] == "python-foton"
    assert np.array_equal(design_sections(NOMINAL_FM2, RATE), _ligo(NOMINAL_FM2))
    assert rms_ours.keys() == rms_ligo.keys() and len(rms_ours) == 24
    for channel, value in rms_ours.items():  # the same loop, to foton's rounding
        assert rms_ligo[channel] == pytest.approx(value, rel=1e-3), channel
    with pytest.raises(FotonError, match="python-foton refuses design 'pole"):
        design_to_sos("pole(-5)", RATE, "python-foton")
    monkeypatch.setenv(FOTON_VARIABLE, "foton")
    with pytest.raises(FotonError, match="must be one of twind, python-foton"):
        design_sections(NOMINAL_FM1, RATE)
