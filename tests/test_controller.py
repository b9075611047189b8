"""The damping loop's controller measured from OUT/IN2 and checked against the
configuration's before the plant is read: twin measurements whose filter modules differ
from the configuration (an extra resonant gain, a gain, a stage switched off)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from twind.analysis.diagnose import diagnose
from twind.analysis.identification.controller import (
    Ratio,
    band_tests,
    check_controller,
    correct,
    corrected_module,
)
from twind.config import OpticConfig, load_config
from twind.commissioning.measurement import measure_tfs
from twind.loop.filtermodule import Stage
from twind.viz.report import report_page

EXCITED = ("POS", "PIT", "YAW")
SETTINGS = {"bw": 0.05, "averages": 10, "rms": 3.0}


@pytest.fixture(scope="module")
def etmx() -> OpticConfig:
    return load_config(None, "ETMX").select("ETMX")[0]


def with_module(cfg: OpticConfig, dof: str, **change: object) -> OpticConfig:
    """`cfg` with `dof`'s damping module changed."""
    return replace(cfg, damping={**cfg.damping, dof: replace(cfg.damping[dof], **change)})


def with_stage(cfg: OpticConfig, dof: str, design: str) -> OpticConfig:
    """`cfg` with a stage the configuration does not have switched on in `dof`'s bank."""
    m = cfg.damping[dof]
    stages = list(m.stages)
    stages[3] = Stage("extra", design=design)
    return with_module(cfg, dof, stages=tuple(stages), on=(*m.on, 4))


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_a_null_controller_is_as_configured(etmx: OpticConfig, seed: int) -> None:
    tfs = measure_tfs(etmx, EXCITED, seed=seed, **SETTINGS)
    check = check_controller(tfs, etmx)
    assert check.checked == ["POS", "PIT", "YAW", "SIDE"]
    assert check.same, check.lines()
    assert check.config.damping == etmx.damping


@pytest.mark.slow
def test_an_extra_resonant_gain_is_named_and_the_plant_stays_consistent(
        etmx: OpticConfig) -> None:
    real = with_stage(etmx, "YAW", "resgain(5,5,3.5)")
    tfs = measure_tfs(real, EXCITED, seed=21, **SETTINGS)
    d = diagnose(tfs, etmx)
    check = d.controller
    assert {x.dof for x in check.differences} == {"YAW"}
    (c,) = check.corrections
    assert c.kind == "stage" and c.explained
    assert c.peak_db == pytest.approx(3.5, abs=0.3)
    assert c.peak_hz == pytest.approx(5.0, rel=0.05)
    # the measured module against the one the twin ran, a path the fit never saw
    f = np.linspace(0.5, 20, 400)
    measured = check.config.damping["YAW"].build().response(f)
    truth = real.damping["YAW"].build().response(f)
    assert np.max(np.abs(measured / truth - 1)) < 0.02
    # nothing read as physics (a band elsewhere may stand out as on any null, 1 in ~10)
    assert not d.effects, d.lines()
    assert not [x for x in d.located if "YAW" in x.element], d.lines()
    assert "YAW: +3.5 dB at 5 Hz" in d.summary()
    assert "YAW&#x27;s damping filter differs from the configuration" in report_page(d, [])
    js = d.to_json()
    assert js["controller"]["corrections"][0]["kind"] == "stage"
    assert js["consistency"]["bands"]["p_value"] == d.p_band and d.bands > 0
    # read through the configured controller, the same data would be suspension physics
    assert not diagnose(tfs, etmx, controller=False, max_effects=1).consistent


def test_a_gain_and_a_stage_switched_off_are_told_apart(etmx: OpticConfig) -> None:
    real = with_module(with_module(etmx, "PIT", gain=etmx.damping["PIT"].gain * 1.1),
                       "POS", on=(1, 3))
    check = check_controller(measure_tfs(real, EXCITED, seed=31, **SETTINGS), etmx)
    by_dof = {c.dof: c for c in check.corrections}
    assert set(by_dof) == {"POS", "PIT"}
    assert by_dof["PIT"].kind == "gain"
    assert by_dof["PIT"].gain == pytest.approx(1.1, rel=0.01)
    assert by_dof["POS"].kind == "modules" and by_dof["POS"].on == (1, 3)
    assert by_dof["POS"].gain == pytest.approx(1.0, rel=0.01)
    assert check.config.damping["POS"].on == (1, 3)


def test_a_flipped_sign_is_read_as_a_gain_of_minus_one(etmx: OpticConfig) -> None:
    """A ratio of -1 within the noise (phases near +-pi, on either branch): a difference,
    and a gain of -1, not a cancelled phase."""
    rng = np.random.default_rng(0)
    f = np.linspace(1.0, 20.0, 400)
    noise = rng.normal(0, 0.01, f.size) + 1j * rng.normal(0, 0.01, f.size)
    ratio = Ratio("PIT", f, np.log(-np.exp(noise)), np.full(f.size, 0.01), 0.0)
    assert min(p for *_, p in band_tests(ratio)) < 1e-10
    c = correct(ratio, etmx.damping["PIT"], etmx.rate_hz, 1e-3)
    assert c.kind == "gain" and c.gain == pytest.approx(-1.0, rel=0.01) and c.explained
    assert corrected_module(etmx.damping["PIT"], c).gain == pytest.approx(
        -etmx.damping["PIT"].gain, rel=0.01)
