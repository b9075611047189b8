"""awg-style excitations: waveform content, block invariance, tapers, refusals, JSON."""

from __future__ import annotations

import json
import math
import random
import re
from dataclasses import replace

import numpy as np
import pytest
from scipy import linalg, signal

from twind.excitation import (
    ExcitationError,
    ExcitationRequest,
    Limits,
    check,
    make_waveform,
)
from twind.excitation.checks import DEFAULT_LIMITS
from twind.excitation.design import noise_gain, noise_shape
from twind.excitation.waveforms import NOISE_CHUNK

CH = "C1:SUS-ETMX_SUSPOS_EXC"
FS = 2048.0  # a low model rate keeps the tests fast; nothing depends on 16384
FREE = Limits(peak=math.inf, rms=math.inf)


def _req(waveform: str, **kw: object) -> ExcitationRequest:
    return ExcitationRequest(CH, waveform, **kw)


def _render(req: ExcitationRequest, n: int | None = None, rate: float = FS) -> np.ndarray:
    check(req, FREE, rate)
    w = make_waveform(req, rate)
    return w.next(w.total_samples if n is None else n)


def _tone(x: np.ndarray, f: float, rate: float = FS) -> complex:
    """Complex amplitude of the tone at `f` in `x` (whole cycles in x, so no leakage)."""
    t = np.arange(x.size) / rate
    return complex(2.0 * np.mean(x * np.exp(-2j * math.pi * f * t)))


# -- what each waveform sends -----------------------------------------------------------------
def test_sine_has_its_frequency_and_amplitude() -> None:
    x = _render(_req("sine", amp=0.1, freq=3.0, duration=10.0))
    assert x.size == 20480
    spec = np.abs(np.fft.rfft(x)) * 2 / x.size
    f = np.fft.rfftfreq(x.size, 1 / FS)
    assert f[np.argmax(spec)] == 3.0
    assert spec.max() == pytest.approx(0.1, rel=1e-9)
    # and it is amp sin(2 pi f t) itself, starting at 0
    t = np.arange(x.size) / FS
    assert np.max(np.abs(x - 0.1 * np.sin(2 * math.pi * 3.0 * t))) < 1e-12


def test_sweep_instantaneous_frequency_follows_a_log_sweep() -> None:
    f0, f1, dur, rate = 2.0, 200.0, 20.0, 4096.0
    x = _render(_req("sweep", amp=0.3, freq=f0, f_stop=f1, duration=dur), rate=rate)
    assert x.size == dur * rate
    assert np.max(np.abs(x)) == pytest.approx(0.3, rel=1e-4)
    assert abs(x[0]) < 1e-15  # a sine sweep, not a cosine one
    # frequency from the spacing of upward zero crossings (interpolated), start to end
    up = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    t_up = (up + x[up] / (x[up] - x[up + 1])) / rate
    f_meas = 1 / np.diff(t_up)
    t_mid = 0.5 * (t_up[1:] + t_up[:-1])
    want = f0 * (f1 / f0) ** (t_mid / dur)
    assert np.max(np.abs(f_meas / want - 1)) < 0.01
    assert t_mid[0] < 0.7 and t_mid[-1] > dur - 0.01  # measured from start to end
    # at t = 0 the slope of amp sin(2 pi f0 t) gives f0 itself
    assert (x[1] - x[0]) * rate / (2 * math.pi * 0.3) == pytest.approx(f0, rel=1e-3)
    assert f_meas[-1] == pytest.approx(f1, rel=0.01)  # ends at f1


def test_multisine_peak_is_amp_and_every_tone_is_there() -> None:
    tones = (3.0, 7.0, 13.0, 29.0)
    req = _req("multisine", amp=0.25, freqs=tones, duration=math.inf)
    check(req, FREE, FS)
    w = make_waveform(req, FS)
    assert tuple(w.freqs) == tones  # on the period's grid already: not moved
    x = w.next(w.period_samples)
    assert np.max(np.abs(x)) == pytest.approx(0.25, rel=1e-12)
    amps = [abs(_tone(x, f)) for f in tones]
    assert np.allclose(amps, amps[0], rtol=1e-9)  # equal tones
    spec = np.abs(np.fft.rfft(x))
    bins = np.rint(np.array(tones) * x.size / FS).astype(int)
    others = np.delete(spec, bins)
    assert np.max(others) < 1e-9 * np.max(spec)  # nothing else
    # exactly periodic: the next period is the same samples
    assert np.array_equal(w.next(w.period_samples), x)


def test_multisine_log_spaced_tones_and_low_crest_factor() -> None:
    req = _req("multisine", amp=1.0, freq=10.0, f_stop=20.0, n_tones=50, duration=math.inf)
    check(req, FREE, FS)
    w = make_waveform(req, FS)
    want = np.geomspace(10.0, 20.0, 50)
    assert np.max(np.abs(w.freqs / want - 1)) <= 0.01
    x = w.next(w.period_samples)
    crest = np.max(np.abs(x)) / np.sqrt(np.mean(x**2))
    # all tones in phase would give sqrt(2 N) = 10; Schroeder's phases about 3
    assert crest < 3.5
    harm = _req("multisine", amp=1.0, freqs=tuple(float(k) for k in range(1, 21)),
                duration=math.inf)
    check(harm, FREE, FS)
    h = make_waveform(harm, FS)
    y = h.next(h.period_samples)
    assert np.max(np.abs(y)) / np.sqrt(np.mean(y**2)) < 2.0  # vs sqrt(40) = 6.3


def test_white_noise_rms_and_flat_spectrum() -> None:
    x = _render(_req("noise", amp=0.2, duration=60.0, seed=3))
    assert np.sqrt(np.mean(x**2)) == pytest.approx(0.2, rel=0.02)
    f, p = signal.welch(x, FS, nperseg=1024)
    flat = 2 * 0.2**2 / FS  # one-sided PSD of white noise of RMS 0.2
    assert np.mean(p[1:-1]) == pytest.approx(flat, rel=0.03)


def test_shaped_noise_rms_and_psd_follow_the_foton_shape() -> None:
    shape = 'butter("BandPass",4,20,100)'
    x = _render(_req("noise", amp=0.05, shape=shape, duration=60.0, seed=11))
    steady = x[int(FS):]  # after the filter has left rest
    assert np.sqrt(np.mean(steady**2)) == pytest.approx(0.05, rel=0.03)
    ns = noise_shape(shape, FS)
    f, p = signal.welch(steady, FS, nperseg=2048)
    _, h = signal.sosfreqz(ns.sos, worN=f, fs=FS)
    want = 2 / FS * (0.05 / ns.gain_rms) ** 2 * np.abs(h) ** 2
    band = (f > 25) & (f < 90)
    assert np.mean(p[band] / want[band]) == pytest.approx(1.0, rel=0.05)
    stop = f > 400  # follows the roll-off too: > 40 dB down out of band
    assert np.max(p[stop]) < 1e-4 * np.max(p)


@pytest.mark.parametrize("shape", ['butter("BandPass",4,20,100)', "resgain(3.2,30,40)",
                                   'zpk([],[0.5],1,"n")', 'ellip("LowPass",6,1,60,300)'])
def test_noise_gain_equals_the_exact_lyapunov_variance(shape: str) -> None:
    sos = noise_shape(shape, FS).sos
    # the cascade's state space, section by section (one high-order polynomial would be
    # too ill-conditioned for a reference)
    a, b, c, d = (np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), np.ones((1, 1)))
    for sec in sos:
        a2, b2, c2, d2 = signal.tf2ss(sec[:3], sec[3:])
        a = np.block([[a, np.zeros((a.shape[0], 2))], [b2 @ c, a2]])
        b = np.vstack([b, b2 @ d])
        c = np.hstack([d2 @ c, c2])
        d = d2 @ d
    var = (c @ linalg.solve_discrete_lyapunov(a, b @ b.T) @ c.T + d @ d.T).item()
    assert noise_gain(sos) == pytest.approx(math.sqrt(var), rel=1e-4)


def test_stream_sends_its_samples() -> None:
    s = np.random.default_rng(0).uniform(-1, 1, 5000)
    x = _render(_req("stream", samples=s))
    assert np.array_equal(x, s)


# -- blocks of any size give the same samples -----------------------------------------------
_INVARIANCE = {
    "sine": _req("sine", amp=0.1, freq=3.3, duration=9.0, ramp=1.5),
    "sine_inf": _req("sine", amp=0.1, freq=31.7, duration=math.inf, ramp=0.7),
    "sweep": _req("sweep", amp=0.2, freq=1.0, f_stop=300.0, duration=9.0, ramp=0.5),
    "multisine": _req("multisine", amp=0.3, freq=5.0, f_stop=60.0, n_tones=7, duration=9.0,
                      ramp=1.0),
    "noise": _req("noise", amp=0.4, shape="resgain(3.2,30,40)", duration=9.0, seed=5,
                  ramp=0.25),
    "noise_white_inf": _req("noise", amp=0.4, duration=math.inf, seed=6),
    "stream": _req("stream", samples=np.random.default_rng(1).normal(size=17000), ramp=1.0),
}


@pytest.mark.parametrize("name", list(_INVARIANCE))
def test_blocks_concatenate_bit_for_bit(name: str) -> None:
    req = _INVARIANCE[name]
    check(req, FREE, FS)
    n = 20000  # past the end of the finite ones, across NOISE_CHUNK boundaries
    assert n > 2 * NOISE_CHUNK
    whole = make_waveform(req, FS).next(n)
    rng = random.Random(name)
    for _ in range(3):
        w = make_waveform(req, FS)
        parts, left = [], n
        while left:
            k = min(left, rng.choice([0, 1, 2, 7, 64, 1000, 4095, 8193, rng.randrange(1, n)]))
            parts.append(w.next(k))
            left -= k
        assert np.array_equal(np.concatenate(parts), whole)
    a, b = 4321, n - 4321  # next(a) + next(b) == next(a + b) on a fresh waveform
    w = make_waveform(req, FS)
    assert np.array_equal(np.concatenate([w.next(a), w.next(b)]), whole)
    assert np.all(np.isfinite(whole)) and np.any(whole != 0)


# -- tapers, ends and stops ---------------------------------------------------------------------
def test_raised_cosine_taper_at_start_and_end() -> None:
    dur, ramp = 4.0, 0.5
    req = _req("sine", amp=1.0, freq=10.0, duration=dur, ramp=ramp)
    x = _render(req, n=int(dur * FS) + 100)
    bare = _render(replace(req, ramp=0.0))
    n, r = int(dur * FS), int(ramp * FS)
    k = np.arange(r)
    win = 0.5 * (1 - np.cos(math.pi * k / r))
    assert np.allclose(x[:r], bare[:r] * win, rtol=0, atol=1e-15)
    assert np.allclose(x[n - r:n][::-1], bare[n - r:n][::-1] * win, rtol=0, atol=1e-15)
    assert np.array_equal(x[r:n - r], bare[r:n - r])  # untouched in between
    assert x[0] == 0.0 and x[n - 1] == 0.0
    assert not np.any(x[n:])  # zeros after the end


def test_infinite_excitation_ramps_up_only_and_stop_ramps_down() -> None:
    req = _req("sine", amp=1.0, freq=10.0, duration=math.inf, ramp=1.0)
    check(req, FREE, FS)
    w = make_waveform(req, FS)
    assert w.total_samples is None and not w.done
    head = w.next(int(FS))
    assert head[0] == 0.0
    t = np.arange(int(FS), 50 * int(FS)) / FS
    body = w.next(t.size)
    assert np.max(np.abs(body - np.sin(2 * math.pi * 10.0 * t))) < 1e-9  # no end ramp
    w.stop(ramp=0.5)
    assert w.total_samples == 50 * int(FS) + int(0.5 * FS)
    tail = w.next(int(FS))
    r = int(0.5 * FS)
    k = np.arange(r)
    tt = (50 * int(FS) + k) / FS
    win = 0.5 * (1 - np.cos(math.pi * (r - 1 - k) / r))
    assert np.allclose(tail[:r], np.sin(2 * math.pi * 10.0 * tt) * win, atol=1e-9)
    assert not np.any(tail[r:]) and w.done


def test_stop_without_ramp_ends_at_once() -> None:
    w = make_waveform(_req("noise", amp=1.0, duration=math.inf), FS)
    assert np.any(w.next(10))
    w.stop()
    assert w.done and not np.any(w.next(100))


# -- refusals -------------------------------------------------------------------------------------
_NAN, _INF = float("nan"), float("inf")
_OK = Limits(peak=1.0, rms=1.0)
# (waveform, fields, key the message names, words in it)
_REFUSALS = [
    ("sine", {"freq": -1.0}, "freq", "above 0"),
    ("sine", {"freq": 0.0}, "freq", "above 0"),
    ("sine", {"freq": _NAN}, "freq", "finite"),
    ("sine", {"freq": _INF}, "freq", "finite"),
    ("sine", {}, "freq", "missing"),
    ("sine", {"freq": 1024.0}, "freq", "Nyquist"),
    ("sine", {"freq": 5.0, "amp": _NAN}, "amp", "finite"),
    ("sine", {"freq": 5.0, "amp": _INF}, "amp", "finite"),
    ("sine", {"freq": 5.0, "amp": -0.1}, "amp", ">= 0"),
    ("sine", {"freq": 5.0, "duration": -1.0}, "duration", "> 0"),
    ("sine", {"freq": 5.0, "duration": _NAN}, "duration", "> 0"),
    ("sine", {"freq": 5.0, "duration": 0.0}, "duration", "> 0"),
    ("sine", {"freq": 5.0, "duration": 1e-5}, "duration", "one sample"),
    ("sine", {"freq": 5.0, "duration": 1e300}, "duration", "too long"),
    ("sine", {"freq": 5.0, "ramp": -1.0}, "ramp", ">= 0"),
    ("sine", {"freq": 5.0, "ramp": _NAN}, "ramp", ">= 0"),
    ("sine", {"freq": 5.0, "ramp": _INF, "duration": _INF}, "ramp", "finite"),
    ("sine", {"freq": 5.0, "ramp": 5.1}, "ramp", "half the duration"),
    ("sine", {"freq": 5.0, "start_gps": _NAN}, "start_gps", "GPS"),
    ("noise", {"amp": 0.1, "seed": -1}, "seed", ">= 0"),
    ("sweep", {"freq": 1.0}, "f_stop", "missing"),
    ("sweep", {"freq": 1.0, "f_stop": 0.0}, "f_stop", "above 0"),
    ("sweep", {"freq": 1.0, "f_stop": -5.0}, "f_stop", "above 0"),
    ("sweep", {"freq": 1.0, "f_stop": 2000.0}, "f_stop", "Nyquist"),
    ("sweep", {"freq": 1.0, "f_stop": 20.0, "duration": _INF}, "duration", "finite"),
    ("multisine", {"amp": 0.1}, "n_tones", "n_tones"),
    ("multisine", {"freq": 1.0, "f_stop": 10.0, "n_tones": 1001}, "n_tones", "1000"),
    ("multisine", {"freq": 1.0, "f_stop": 10.0, "n_tones": 0}, "n_tones", "1 to"),
    ("multisine", {"freqs": tuple(np.linspace(1, 1000, 1001))}, "freqs", "1000"),
    ("multisine", {"freqs": (3.0, 5.0), "n_tones": 2}, "freqs", "either"),
    ("multisine", {"freqs": (3.0, 3.0)}, "freqs", "repeated"),
    ("multisine", {"freqs": (3.0, -5.0)}, "freqs", "above 0"),
    ("multisine", {"freqs": ()}, "freqs", "at least one"),
    ("multisine", {"freq": 10.0, "f_stop": 5.0, "n_tones": 3}, "f_stop", "above the lowest"),
    ("multisine", {"freq": 1.0, "f_stop": 1.001, "n_tones": 100}, "n_tones", "closer"),
    ("multisine", {"freqs": (1e-4,)}, "freq", "resolution"),
    ("noise", {"amp": 0.1, "shape": "zpk([1],[2]"}, "shape", "unbalanced"),
    ("noise", {"amp": 0.1, "shape": "frobnicate(3)"}, "shape", "frobnicate"),
    ("noise", {"amp": 0.1, "shape": 'zpk([],[0],1,"n")'}, "shape", "not stable"),
    ("noise", {"amp": 0.1, "shape": 'zpk([],[-3],1,"n")'}, "shape", "right half plane"),
    ("noise", {"amp": 0.1, "shape": "gain(0)"}, "shape", "no finite, nonzero"),
    ("stream", {}, "samples", "at least one"),
    ("stream", {"samples": np.zeros(0)}, "samples", "at least one"),
    ("stream", {"samples": np.array([0.0, _NAN])}, "samples", "finite"),
    ("stream", {"samples": np.array([_INF, 0.0])}, "samples", "finite"),
    # 2**30 samples as a zero-stride view: the length is refused without allocating 8 GB
    ("stream", {"samples": np.broadcast_to(0.0, (2**30,))}, "samples", "more than"),
    ("stream", {"samples": np.array([0.5, -1.5, 0.2])}, "samples", "peak 1.5"),
    ("sine", {"freq": 5.0, "amp": 1.01}, "amp", "peak"),
    ("sweep", {"freq": 5.0, "f_stop": 50.0, "amp": 1.5}, "amp", "never clipped"),
    ("noise", {"amp": 0.2}, "amp", "6 sigma"),  # RMS fine, 6 x 0.2 over the peak
    ("multisine", {"freqs": (3.0, 5.0), "amp": 1.2}, "amp", "true peak"),
    ("bogus", {}, "waveform", "not one of"),
    ("sine", {"freq": "5"}, "freq", "number"),
    ("sine", {"freq": 5.0, "amp": True}, "amp", "number"),
    ("sine", {"freq": 5.0, "duration": [1]}, "duration", "list of length 1"),
]


@pytest.mark.parametrize(("waveform", "kw", "key", "words"), _REFUSALS)
def test_every_refusal_names_its_reason(waveform: str, kw: dict, key: str, words: str) -> None:
    with pytest.raises(ExcitationError) as err:
        check(ExcitationRequest(CH, waveform, **kw), _OK, FS)
    assert err.value.key == key
    assert words in str(err.value)


def test_rms_limit_is_separate_from_the_peak_limit() -> None:
    req = _req("sine", amp=1.0, freq=5.0)
    check(req, Limits(peak=1.0, rms=0.71), FS)
    with pytest.raises(ExcitationError, match="RMS 0.707107 exceeds the limit 0.7"):
        check(req, Limits(peak=1.0, rms=0.7), FS)
    # noise: amp is the RMS
    with pytest.raises(ExcitationError, match="RMS"):
        check(_req("noise", amp=0.2), Limits(peak=10.0, rms=0.1), FS)
    with pytest.raises(ExcitationError, match="RMS 0.9 exceeds"):
        check(_req("stream", samples=np.full(100, -0.9)), Limits(peak=1.0, rms=0.8), FS)


def test_a_multisine_within_the_peak_limit_is_refused_over_the_rms_limit() -> None:
    """Four tones at a twin's default limits (peak 100, RMS 30): at amp 90 the true peak is
    90 but the period's RMS 31.8, refused by the RMS limit with that RMS; at amp 80 (RMS
    28.3) it runs. The RMS checked is that of the samples the multisine sends."""
    tones = (3.0, 7.0, 13.0, 29.0)
    req = _req("multisine", amp=90.0, freqs=tones, duration=math.inf)
    x = _render(req, make_waveform(req, FS).period_samples)
    rms = float(np.sqrt(np.mean(x**2)))
    assert np.max(np.abs(x)) == pytest.approx(90.0) and rms > DEFAULT_LIMITS.rms
    with pytest.raises(ExcitationError) as err:
        check(req, DEFAULT_LIMITS, FS)
    assert err.value.key == "amp"
    said = re.search(r"the RMS (\S+) exceeds the limit 30 ", str(err.value))
    assert said and float(said.group(1)) == pytest.approx(rms, rel=1e-5)
    check(replace(req, amp=80.0), DEFAULT_LIMITS, FS)


@pytest.mark.parametrize("channel", ["C1:SUS-ETMX_SUSPOS_IN1", "c1:sus-etmx_suspos_exc",
                                     "C1:SUS-ETMX_SUSPOS_EXC ", "SUS-ETMX_SUSPOS_EXC",
                                     "K1:VIS-SRM_EXC", "C1:SUS-ETMX-SUSPOS_EXC", "", 42])
def test_channel_must_be_an_exc_test_point(channel: object) -> None:
    with pytest.raises(ExcitationError) as err:
        check(ExcitationRequest(channel, "sine", freq=5.0), _OK, FS)  # type: ignore[arg-type]
    assert err.value.key == "channel"


@pytest.mark.parametrize("channel", ["C1:SUS-ETMX_SUSPOS_EXC", "K1:VIS-SRM_TM_TEST_P_EXC",
                                     "K1:VIS-SRM_IM_DAMP_P_EXC"])
def test_any_sites_exc_test_point_is_a_channel(channel: str) -> None:
    """Which test points exist, the serving twin says (``test_serve``); here, the form."""
    req = ExcitationRequest(channel, "sine", freq=5.0)
    check(req, _OK, FS)
    assert req.optic == channel.split("-")[1].split("_")[0]


def test_bad_rate_and_limits_are_refused_not_ignored() -> None:
    req = _req("sine", amp=0.1, freq=5.0)
    for rate in (0.0, -1.0, _NAN, _INF, "16384"):
        with pytest.raises(ExcitationError, match="rate_hz"):
            check(req, _OK, rate)  # type: ignore[arg-type]
    for limits in (Limits(_NAN, 1.0), Limits(1.0, -1.0), Limits(1.0, "x")):  # type: ignore[arg-type]
        with pytest.raises(ExcitationError, match="limits"):
            check(req, limits, FS)


def test_accepted_requests() -> None:
    for req in (_req("sine", amp=1.0, freq=5.0, ramp=5.0),  # peak == limit: allowed
                _req("noise", amp=1 / 6, shape='butter("LowPass",2,50)'),
                _req("multisine", amp=1.0, freq=1.0, n_tones=1),
                _req("stream", samples=np.full(10, -1.0), duration=_NAN),  # duration unused
                # 1.5 only where the taper makes it 0: the tapered samples are what count
                _req("stream", samples=np.r_[1.5, np.full(98, 0.5), -1.5], ramp=10 / FS)):
        check(req, _OK, FS)


# -- JSON ----------------------------------------------------------------------------------------
_ROUND_TRIP = [
    _req("sine", amp=0.1, freq=3.0, ramp=1.0, start_gps=1400000000.25),
    _req("sweep", amp=0.2, freq=0.5, f_stop=50.0, duration=120.0),
    _req("multisine", amp=0.3, freqs=(1.5, 2.5, 7.0), duration=math.inf),
    _req("multisine", amp=0.3, freq=1.0, f_stop=10.0, n_tones=5),
    _req("noise", amp=0.4, shape='butter("BandPass",4,1,30)', duration=math.inf, seed=99),
    _req("stream", samples=np.array([0.0, 1e-300, -2.5, 1 / 3])),
]


@pytest.mark.parametrize("req", _ROUND_TRIP, ids=lambda r: r.waveform)
def test_json_round_trip(req: ExcitationRequest) -> None:
    text = json.dumps(req.to_json(), allow_nan=False)  # strict JSON, inf as "inf"
    back = ExcitationRequest.from_json(json.loads(text))
    assert back == req
    assert back.to_json() == req.to_json()
    check(back, FREE, FS)


def test_from_json_names_the_key() -> None:
    good = {"channel": CH, "waveform": "sine", "freq": 3, "amp": 1}
    assert ExcitationRequest.from_json(good).freq == 3.0
    cases = [({**good, "frequency": 3}, "frequency", "unknown key"),
             ({"waveform": "sine"}, "channel", "missing"),
             ({**good, "amp": "1"}, "amp", "number"),
             ({**good, "n_tones": 2.5}, "n_tones", "integer"),
             ({**good, "seed": False}, "seed", "integer"),
             ({**good, "samples": [1, "2"]}, "samples", "numbers"),
             ({**good, "samples": [1, True]}, "samples", "boolean"),
             ({**good, "samples": [[1, 2]]}, "samples", "flat"),
             ({**good, "samples": {"a": 1}}, "samples", "list"),
             ({**good, "freqs": [1, None]}, "freqs", "element 1"),
             ({**good, "duration": "forever"}, "duration", "inf"),
             ({**good, "amp": 10**400}, "amp", "too large")]
    for obj, key, words in cases:
        with pytest.raises(ExcitationError) as err:
            ExcitationRequest.from_json(obj)
        assert err.value.key == key, obj
        assert words in str(err.value)
    with pytest.raises(ExcitationError, match="JSON object"):
        ExcitationRequest.from_json([good])  # type: ignore[arg-type]


class _HugeList(list):
    """A list claiming 2**30 elements: what a hostile length costs must not depend on it."""

    def __len__(self) -> int:
        return 2**30


_HOSTILE = [None, True, False, "", "3", "nan", "inf", "-inf", [], {}, [1, "a"], [[1.0]],
            _NAN, _INF, -_INF, -1, 0, 0.0, -1e-300, 1e-300, 1e308, 2**70, -(2**70), 10**400,
            1.5, 3, 1000, 1e6, "C1:SUS-ETMX_SUSPOS_EXC", "sine", "noise", 'zpk([],[0],1,"n")',
            "gain(", _HugeList(), [0.1] * 5, [_NAN, 1.0], [1e308, 1e308], list(range(1001))]
_KEYS = ["channel", "waveform", "amp", "freq", "f_stop", "n_tones", "freqs", "shape",
         "duration", "ramp", "start_gps", "samples", "seed"]
_BASES = [{"channel": CH, "waveform": "sine", "amp": 0.1, "freq": 3.0},
          {"channel": CH, "waveform": "sweep", "amp": 0.1, "freq": 3.0, "f_stop": 30.0},
          {"channel": CH, "waveform": "multisine", "amp": 0.1, "freq": 5.0, "f_stop": 50.0,
           "n_tones": 4},
          {"channel": CH, "waveform": "noise", "amp": 0.1, "shape": "resgain(3.2,30,40)"},
          {"channel": CH, "waveform": "stream", "samples": [0.0, 0.5, -0.5]}]


def _hostile(rng: random.Random) -> object:
    obj = dict(rng.choice(_BASES))
    for _ in range(rng.randint(1, 3)):
        roll = rng.random()
        if roll < 0.75:
            obj[rng.choice(_KEYS)] = rng.choice(_HOSTILE)
        elif roll < 0.85:
            obj[rng.choice(["frequency", "Amp", "", "samples ", "gps"])] = 1.0
        elif roll < 0.95:
            name = rng.choice(["C1:SUS-", "ETMX", "_SUS", "POS", "VERT", "_EXC", "_IN1", ":",
                               "X1", "sus"])
            obj["channel"] = "".join(rng.choice([name, "C1:SUS-ETMX_SUSPOS_EXC"])
                                     for _ in range(rng.randint(1, 3)))
        else:
            del obj[rng.choice(list(obj))]
    if rng.random() < 0.02:
        return rng.choice([None, [obj], "obj", 3])
    return obj


def test_fuzz_hostile_json_is_refused_with_excitation_error_only() -> None:
    rng = random.Random(20240611)
    limits = Limits(peak=1.0, rms=0.5)
    refused = accepted = 0
    for _ in range(300):
        obj = _hostile(rng)
        try:
            req = ExcitationRequest.from_json(obj)  # type: ignore[arg-type]
            check(req, limits, FS, max_samples=2**20)
        except ExcitationError as exc:
            assert str(exc)  # a reason, never empty
            refused += 1
            continue
        accepted += 1
        # whatever is accepted renders finite samples within the limits
        w = make_waveform(req, FS)
        x = w.next(4096)
        assert np.all(np.isfinite(x))
        if req.waveform != "noise":
            assert np.max(np.abs(x)) <= limits.peak * (1 + 1e-12)
    assert refused > 150 and accepted > 10
