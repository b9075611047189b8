"""Single sines found in a recording with no events (awg's sines one after another, a sine
stepped by hand), demodulated to a bin at each sine's frequency. The recording is the
twin engine's, written as the data system's HDF5 at 2048 Hz; the truth is the nominal
loop's continuous model, a code path of its own."""

from __future__ import annotations

import io
import json
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
from gwpy.timeseries import TimeSeries, TimeSeriesDict
from scipy import signal

from twind import DOFS
from twind.analysis.estimation.demodulation import (
    AVERAGES,
    SETTLE,
    DemodulationError,
    demodulate,
)
from twind.analysis.estimation.tf import from_session
from twind.analysis.estimation.tfset import TFError
from twind.analysis.identification.data import FitData
from twind.analysis.identification.model import ClosedLoopModel
from twind.cli import main
from twind.config import NOMINAL_ETMX, load_optic
from twind.model.plant import Plant
from twind.simulation.engine import Engine

FREQS = (0.7, 1.1, 1.6, 2.4, 3.7, 5.5)
EXCITED = ("POS", "PIT", "YAW")
ON_S, GAP_S, AMP = 40.0, 1.0, 3.0
DAQ_RATE, GPS = 2048, 1.4e9


@pytest.fixture(scope="module")
def etmx():  # noqa: ANN201
    return load_optic(NOMINAL_ETMX)


def _recorded(etmx, plan: list[tuple[str, float, str]], path: Path) -> Path:  # noqa: ANN001
    """The engine driven by `plan` ((DOF, frequency, waveform) in turn, a gap before each),
    its test points written as ``_DQ`` channels at the data system's rate."""
    rate = etmx.sus.sample_rate_hz
    on, gap = int(ON_S * rate), int(GAP_S * rate)
    n = len(plan) * (on + gap) + gap
    exc = np.zeros((1, len(DOFS), n))
    rng = np.random.default_rng(4)
    for k, (dof, f, waveform) in enumerate(plan):
        t = np.arange(on) / rate
        x = np.sin(2 * np.pi * f * t) if waveform == "sine" else rng.standard_normal(on)
        exc[0, DOFS.index(dof), gap + k * (on + gap):][:on] = AMP * x
    engine = Engine([etmx.loop()], {etmx.name: etmx.noise}, seed=7, rate_hz=rate)
    points = {p: np.empty((len(DOFS), n)) for p in ("exc", "in1", "in2", "out")}
    for a in range(0, n, int(rate)):
        block = engine.step(min(int(rate), n - a), exc=exc[:, :, a:a + int(rate)])
        for p, x in points.items():
            x[:, a:a + block.in1.shape[-1]] = getattr(block, p)[0]
    data = TimeSeriesDict()
    for p, x in points.items():
        for i, dof in enumerate(DOFS):
            name = f"C1:SUS-{etmx.name}_SUS{dof}_{p.upper()}_DQ"
            data[name] = TimeSeries(signal.resample_poly(x[i], 1, int(rate) // DAQ_RATE),
                                    t0=GPS, sample_rate=DAQ_RATE, name=name, channel=name)
    data.write(str(path))
    return path


@pytest.fixture(scope="module")
def stepped(etmx, tmp_path_factory) -> Path:  # noqa: ANN001
    plan = [(dof, f, "sine") for dof in EXCITED for f in FREQS]
    return _recorded(etmx, plan, tmp_path_factory.mktemp("sines") / "stepped.h5")


@pytest.mark.slow
def test_stepped_sines_give_the_nominal_loop_at_their_frequencies(stepped, etmx  # noqa: ANN001
                                                                  ) -> None:
    tfs = from_session([stepped])
    assert len(tfs.found) == len(EXCITED) * len(FREQS)
    assert all(note.endswith("Hz") and ", sine at " in note for note in tfs.found)
    assert tfs.excited == list(EXCITED)
    np.testing.assert_allclose(tfs.frequency_hz, FREQS, atol=1e-4)  # refined, not binned
    data = FitData.from_tfset(tfs)
    assert data.resolution_hz == 0.0  # a sine's bin is the TF at its frequency
    T = ClosedLoopModel(etmx, data.frequency_hz).response(
        Plant.from_params(etmx.sus, etmx.mechanics()))
    T = T[:, [DOFS.index(r) for r in data.responses]][:, :, [DOFS.index(e) for e in EXCITED]]
    z = (data.H - T)[data.mask] / data.sigma[data.mask]
    assert data.mask.sum() >= 20
    # the errors hold the misfit, and are not far too large
    assert 0.3 < np.mean(np.r_[z.real, z.imag] ** 2) < 2.0, np.round(np.abs(z), 1)


def test_diagnose_runs_on_stepped_sines(stepped) -> None:  # noqa: ANN001
    out = io.StringIO()
    with redirect_stdout(out):
        assert main(["diagnose", str(stepped), "--json"]) == 0
    got = json.loads(out.getvalue())
    assert got["consistent"] and not got["effects"], got["summary"]


def test_demodulation_refines_the_frequency_and_refuses_too_few_cycles() -> None:
    rate, f0 = 2048.0, 3.3172
    t = np.arange(int(60 * rate)) / rate
    noise = 0.01 * np.random.default_rng(1).standard_normal(t.size)
    f, h, g2 = demodulate(np.sin(2 * np.pi * f0 * t), [2 * np.sin(2 * np.pi * f0 * t + 0.5)
                                                       + noise], rate, 3.32)
    assert abs(f - f0) < 1e-6
    assert abs(h[0] - 2 * np.exp(0.5j)) < 1e-3 and g2[0] > 0.999
    with pytest.raises(DemodulationError, match="blocks of 2 cycles need"):
        demodulate(np.sin(2 * np.pi * 0.3 * t[: int(20 * rate)]), [], rate, 0.3)


def test_a_sine_is_demodulated_at_its_refined_frequency_not_the_one_given() -> None:
    """A response holding, besides the sine, a line five times its size two block bins
    above it: given the sine's frequency a fifth of a block bin off, the responses are
    demodulated at the refined one, where the Hann window leaks nothing of the other line
    (demodulated at the frequency given, H would be off by 0.48, a quarter of itself)."""
    rate, f0 = 2048.0, 3.3172
    t = np.arange(int(60 * rate)) / rate
    bin_hz = rate / ((t.size - int(SETTLE * t.size)) // AVERAGES)
    x = np.sin(2 * np.pi * f0 * t)
    y = 2 * np.sin(2 * np.pi * f0 * t + 0.5) + 10 * np.sin(2 * np.pi * (f0 + 2 * bin_hz) * t)
    f, h, g2 = demodulate(x, [y], rate, f0 + 0.2 * bin_hz)
    assert abs(f - f0) < 1e-6
    assert abs(h[0] - 2 * np.exp(0.5j)) < 1e-3 and g2[0] > 0.999


def test_sines_beside_other_waveforms_are_refused(etmx, tmp_path: Path) -> None:  # noqa: ANN001
    path = _recorded(etmx, [("POS", 2.0, "sine"), ("PIT", 0.0, "noise")], tmp_path / "m.h5")
    with pytest.raises(TFError, match="sines on POS and other waveforms on PIT"):
        from_session([path])
