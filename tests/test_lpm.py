"""The local polynomial method: unbiased where a Welch estimate leaks, and its errors as large
as the estimates' actual scatter."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from twind.analysis.estimation.lpm import LPMError, lpm, lpm_tfs
from twind.analysis.estimation.welch import welch_tf

RATE = 64.0
F0, Q = 1.0, 10.0  # width 0.1 Hz: five LPM windows of an 800 s record, two Welch bins at 0.05 Hz


def _resonance() -> tuple[np.ndarray, np.ndarray]:
    w0 = 2 * np.pi * F0
    return signal.bilinear([w0**2], [1, w0 / Q, w0**2], fs=RATE)


def _record(seconds: float, seed: int, noise: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """White excitation through the resonance, with white noise on the response; the
    filter starts at rest, so the record holds its switch-on transient."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(int(seconds * RATE))
    b, a = _resonance()
    return x, signal.lfilter(b, a, x) + noise * rng.standard_normal(x.size)


def _truth(f: np.ndarray) -> np.ndarray:
    return signal.freqz(*_resonance(), worN=f, fs=RATE)[1]


def test_lpm_errors_match_the_scatter() -> None:
    pulls = []
    for seed in range(8):
        x, y = _record(800.0, seed)
        est = lpm_tfs(x, [y], RATE, max_hz=3.0)
        keep = (est.frequency_hz > 0.2) & (est.frequency_hz < 3.0)
        z = (est.tf[0, keep] - _truth(est.frequency_hz[keep])) / est.sigma[0, keep]
        pulls.append(np.concatenate([z.real, z.imag]))
    pulls = np.concatenate(pulls)
    # sigma from q = 9 degrees of freedom: the pulls are Student-t like, var 9 / 7
    assert abs(np.mean(pulls)) < 0.05
    assert 0.95 < np.median(np.abs(pulls)) / 0.6745 < 1.2
    assert np.std(pulls) < 1.3


def test_a_window_noisier_than_the_smoothed_spectrum_keeps_its_own_error() -> None:
    """Noise 30 times the floor's power in one window's bins alone: the smoothing's
    quadratic over 7 windows gives it a third of that bump in log, errors ~3 times too
    small in sigma; the window's own residuals show the excess, and its error follows them."""
    rng = np.random.default_rng(3)
    n, width = 2**15, 15
    x = rng.standard_normal(n)
    power = np.ones(n // 2 + 1)
    w = 40  # the window of bins 1 + 15 w .. 15 w + 15
    power[1 + width * w:1 + width * (w + 1)] = 30.0
    v = np.fft.irfft(np.sqrt(power / 2) * (rng.standard_normal(power.size)
                                           + 1j * rng.standard_normal(power.size)), n)
    est = lpm_tfs(x, [2.0 * x + v * np.sqrt(n)], RATE)
    floor = np.median(est.sigma[0, w - 10:w + 10])
    # sqrt(30) = 5.5 but for the window's own scatter (3.5-6.8 over seeds 0-9); without
    # the guard 1.9
    assert est.sigma[0, w] / floor > 3.0


def test_estimates_below_max_hz_do_not_depend_on_it() -> None:
    """Cutting the record's spectrum at 2 Hz or at 3 Hz gives the same estimates and
    errors up to 2 Hz: the smoothing of the variance does not see the cut."""
    x, y = _record(400.0, 1)
    lo, hi = (lpm_tfs(x, [y], RATE, max_hz=m) for m in (2.0, 3.0))
    n = int(np.sum(lo.frequency_hz <= 2.0))
    assert np.allclose(lo.frequency_hz[:n], hi.frequency_hz[:n])
    assert np.allclose(lo.tf[:, :n], hi.tf[:, :n])
    assert np.allclose(lo.sigma[:, :n], hi.sigma[:, :n], rtol=1e-9)


def test_correlation_of_two_responses_sharing_a_noise() -> None:
    """The second response's noise is the first's a few samples later: their errors
    correlate fully, with E[e0 conj(e1)] turning by +2 pi f delay."""
    rng = np.random.default_rng(5)
    x, y = _record(400.0, 3, noise=0.0)
    n = 0.05 * rng.standard_normal(x.size + 4)
    est = lpm_tfs(x, [y + n[4:], y + n[:-4]], RATE, max_hz=3.0, correlated=[0, 1])
    keep = (est.frequency_hz > 0.5) & (est.frequency_hz < 2.5)
    rho = est.correlation[keep, 0, 1]
    assert np.all(np.abs(rho) > 0.95)
    turn = np.angle(rho * np.exp(-2j * np.pi * est.frequency_hz[keep] * 4 / RATE))
    assert np.median(np.abs(turn)) < 0.01  # the other convention: 2 x 2 pi f delay, ~1 rad


def test_the_difference_of_two_readbacks_sharing_their_noise_is_calibrated() -> None:
    """The second response reads the first's noise through a Q = 10 resonance, so their
    correlation stays near 0.99 and turns by pi across 1 Hz. The second's error given the
    first (what a fit whitened with the correlation learns from) scatters as its smoothed
    estimate says: smoothing the correlation itself got that 5 times too small here."""
    b, a = _resonance()
    w0 = 2 * np.pi * F0
    bd, ad = signal.bilinear([w0**2], [1, w0 / 10, w0**2], fs=RATE)
    left = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        x = rng.standard_normal(int(400 * RATE))
        noise = 0.05 * rng.standard_normal(x.size)
        y = signal.lfilter(b, a, x)
        est = lpm_tfs(x, [y + noise, 0.5 * y + signal.lfilter(bd, ad, noise)
                          + 0.005 * rng.standard_normal(x.size)], RATE, max_hz=3.0,
                      correlated=[0, 1])
        z = (est.tf - np.array([[1.0], [0.5]]) * _truth(est.frequency_hz)) / est.sigma
        rho = est.correlation[:, 0, 1]
        left.append((z[1] - np.conj(rho) * z[0]) / np.sqrt(1 - np.abs(rho) ** 2))
    left = np.array(left)
    f = est.frequency_hz
    for lo, hi in [(0.3, 0.8), (0.8, 1.2), (1.2, 2.5)]:
        band = (f > lo) & (f < hi)
        assert 0.75 < np.mean(np.abs(left[:, band]) ** 2) / 2 < 1.3, (lo, hi)


def test_lpm_removes_the_leakage_welch_keeps() -> None:
    """Noise-free, the LPM's error at the resonance is far below a Welch estimate's from
    the same record: what is left of Welch's is the leakage of the transient and the
    window's smoothing."""
    x, y = _record(800.0, 0, noise=0.0)
    est = lpm_tfs(x, [y], RATE, max_hz=3.0)
    near = np.abs(est.frequency_hz - F0) < 0.1
    lpm_err = np.max(np.abs(est.tf[0, near] / _truth(est.frequency_hz[near]) - 1))
    f, h, _, _ = welch_tf(x, y, RATE, int(RATE / 0.05))
    wnear = np.abs(f - F0) < 0.1
    welch_err = np.max(np.abs(h[wnear] / _truth(f[wnear]) - 1))
    assert lpm_err < 0.01 < welch_err


def test_the_kernel_says_what_an_estimate_sees() -> None:
    """A resonance of Q 60 (0.017 Hz wide) is curved over a 0.019 Hz window: the estimate
    at the window's centre misses it by percent, its kernel sum predicts it."""
    w0 = 2 * np.pi * F0
    b, a = signal.bilinear([w0**2], [1, w0 / 60, w0**2], fs=RATE)
    x = np.random.default_rng(2).standard_normal(int(800 * RATE))
    est = lpm_tfs(x, [signal.lfilter(b, a, x)], RATE, max_hz=3.0)

    def true(f: np.ndarray) -> np.ndarray:
        return signal.freqz(b, a, worN=f, fs=RATE)[1]

    near = np.abs(est.frequency_hz - F0) < 0.05
    seen = np.array([np.sum(w * true(f + est.offsets_hz))
                     for f, w in zip(est.frequency_hz[near], est.weights[near], strict=True)])
    at_centre = np.max(np.abs(est.tf[0, near] / true(est.frequency_hz[near]) - 1))
    by_kernel = np.max(np.abs(est.tf[0, near] / seen - 1))
    # what is left is the switch-on transient, curved as sharply, that the polynomial misses
    assert at_centre > 0.02 and by_kernel < at_centre / 3, (at_centre, by_kernel)


def test_windows_the_excitation_leaves_empty_have_no_estimate() -> None:
    """Between a multisine's tones the excitation's DFT is zero: no estimate there, no
    exception, and the windows it does reach are estimated as before."""
    x, y = _record(800.0, 1)
    U, Y = np.fft.rfft(x), np.fft.rfft(y)[None]
    U[2000:4000] = 0.0
    est = lpm(U, Y, RATE / x.size)
    centre = np.round(est.frequency_hz * x.size / RATE).astype(int)
    empty = (centre - 7 >= 2000) & (centre + 7 < 4000)
    assert empty.any() and np.all(np.isnan(est.tf[0, empty]))
    assert np.all(est.coherence[0, empty] == 0.0)
    assert np.all(np.isfinite(est.tf[0, centre + 7 < 2000]))


def test_lpm_refuses_what_it_cannot_estimate() -> None:
    U = np.ones(100, dtype=complex)
    with pytest.raises(LPMError, match="no degree of freedom"):
        lpm(U, U[None], 0.1, half_width=2, order=2)
    with pytest.raises(LPMError, match="responses of 99 bins"):
        lpm(U, U[None, :99], 0.1)
    with pytest.raises(LPMError, match="no window"):
        lpm(U[:10], U[None, :10], 0.1)
    with pytest.raises(LPMError, match="responses of"):
        lpm_tfs(np.ones(100), [np.ones(99)], 1.0)


def test_the_lpm_s_driven_band_is_where_the_excitation_is(tmp_path) -> None:  # noqa: ANN001
    """``twind tf``'s default band on LPM estimates: excited below 10 Hz (a 4th-order
    Butterworth), the band ends near there, not at Nyquist as the LPM's coherence alone had
    it (0.13-8185 Hz)."""
    from measurekit import record_excited_session

    from twind.analysis.estimation.tf import from_session
    from twind.config import load_config

    cfg = load_config(None, "ETMX").select("ETMX")[0]
    path = record_excited_session(cfg, tmp_path / "rec.mcap", {"POS": 2.0, "PIT": 5.0}, 60)
    lo, hi = from_session([path], estimator="lpm").coherent_band()
    assert lo < 0.5 and 5 < hi < 30, (lo, hi)
