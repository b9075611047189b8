"""Every command's Bode figure, inspected through matplotlib: labelled axes with units, the
frequency axis spanning the data and no more, coherence under each element, readable fonts,
what is shown in a caption, models' structural zeros drawn as zero (the diagnosis report
draws with fit's figure)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from twind.cli import main

from conftest import REFERENCE

XML = sorted(str(p) for p in (REFERENCE / "example_null").glob("*.xml"))


@pytest.fixture
def figures(monkeypatch: pytest.MonkeyPatch) -> list[Figure]:
    """The figures saved while a test runs."""
    saved: list[Figure] = []
    original = Figure.savefig

    def keep(self: Figure, *args: object, **kwargs: object) -> None:
        saved.append(self)
        original(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return saved


@pytest.mark.parametrize("command", [["model", "response"], ["tf", *XML], ["fit", *XML]],
                         ids=["model-response", "tf", "fit"])
@pytest.mark.slow
def test_bode_figures_are_labelled_and_span_their_data(command, figures, tmp_path: Path,  # noqa: ANN001
                                                       capsys) -> None:  # noqa: ANN001
    assert main([*command, "-o", str(tmp_path / "bode.png")]) == 0
    capsys.readouterr()
    assert figures
    for fig in figures:
        axes = fig.get_axes()
        f = np.concatenate([np.asarray(line.get_xdata(), float) for ax in axes
                            for line in ax.get_lines()])
        f = f[np.isfinite(f) & (f > 0)]
        for ax in axes:
            lo, hi = ax.get_xlim()
            assert f.min() * (1 - 1e-9) <= lo and hi <= f.max() * (1 + 1e-9), ax.get_title()
            assert ax.get_ylabel(), ax.get_title()
        magnitudes = [ax for ax in axes if ax.get_ylabel().startswith("|")
                      and "sigma" not in ax.get_ylabel()]
        assert magnitudes and all(ax.get_ylabel().endswith("]") for ax in magnitudes)
        units = {ax.get_ylabel().rsplit("[", 1)[1] for ax in magnitudes}
        assert units <= {"µm/µm]", "µrad/µm]", "µm/µrad]", "µrad/µrad]", "µm/ct]", "µrad/ct]"}
        bottom = [ax for ax in axes if ax.get_xlabel()]
        assert bottom and all(ax.get_xlabel() == "frequency [Hz]" for ax in bottom)
        # readable: no text under 9 pt; what is shown, and by which twind, under the panels
        sizes = [t.get_fontsize() for ax in axes for t in
                 (ax.title, ax.xaxis.label, ax.yaxis.label, *ax.get_xticklabels(),
                  *ax.get_yticklabels())]
        assert min(sizes) >= 9
        caption = fig.texts[-1].get_text()
        assert "twind " in caption and ("model " in caption or "GPS from 1416200000" in caption)
        if command[0] != "model":  # diaggui's coherence under every magnitude and phase
            coherence = [ax for ax in axes if ax.get_ylabel() == "coherence"]
            assert len(coherence) == len(magnitudes) and "C1:SUS-ETMX_SUS<DOF>" in caption
            assert all(ax.get_ylim() == (0, 1.05) and ax.get_lines() for ax in coherence)
    if command[0] == "model":  # the plant has no POS-YAW coupling: said, and no curve
        plant = next(f for f in figures if "plant" in f.texts[0].get_text())
        panel = next(ax for ax in plant.get_axes() if ax.get_title() == "POS / YAW")
        assert not panel.get_lines() and panel.texts[0].get_text() == "model: 0"
    if command[0] == "fit":  # beside the measured points, a zero model is drawn as zero
        panel = next(ax for ax in figures[0].get_axes() if ax.get_title() == "POS / YAW")
        floor = [line for line in panel.get_lines() if line.get_linestyle() == "--"]
        assert floor and np.ptp(floor[0].get_ydata()) == 0
        assert floor[0].get_ydata()[0] > panel.get_ylim()[0]  # above the axis, not on it
        assert any(t.get_text() == "model: 0" for t in panel.texts)



@pytest.mark.slow
def test_a_fit_figure_spans_the_bins_fitted_not_the_recording(figures, tmp_path: Path) -> None:
    """A recording's TFs reach Nyquist; past the excitation they are noise over nothing."""
    from dataclasses import replace

    from twind.analysis.identification.fit import fit
    from twind.analysis.estimation.tf import from_diaggui
    from twind.config import load_config
    from twind.analysis.prediction import fit_curves
    from twind.viz.plotting import plot_fit

    tfs = from_diaggui(XML)
    cfg = load_config(None, tfs.optic).select(tfs.optic)[0]
    result = fit(tfs, cfg)
    df = tfs.frequency_hz[1] - tfs.frequency_hz[0]
    beyond = tfs.frequency_hz[-1] + df * np.arange(1, 2000)
    rng = np.random.default_rng(0)

    def padded(a: np.ndarray, noise: bool) -> np.ndarray:
        shape = (beyond.size, *a.shape[1:])
        more = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) * 1e6 if noise \
            else rng.uniform(0, 0.05, shape)
        return np.concatenate([a, more.astype(a.dtype)])

    recording = replace(tfs, frequency_hz=np.concatenate([tfs.frequency_hz, beyond]),
                        tf={k: padded(v, True) for k, v in tfs.tf.items()},
                        coherence={k: padded(v, False) for k, v in tfs.coherence.items()})
    plot_fit(fit_curves(recording, cfg, result, baseline=result), str(tmp_path / "fit.png"))
    labels = figures[0].legends[0].get_texts()
    assert [t.get_text() for t in labels][:2] == ["nominal, refitted", "nominal, fitted"]
    for ax in figures[0].get_axes():
        assert ax.get_xlim()[1] <= tfs.frequency_hz[-1], ax.get_title()
        drawn = [np.max(line.get_xdata()) for line in ax.get_lines() if len(line.get_xdata())]
        assert not drawn or max(drawn) <= tfs.frequency_hz[-1], ax.get_title()
