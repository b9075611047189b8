"""twind diagnose, first version: null sets stay consistent; physics the twin runs but the
model leaves out is named, fitted, and the fit improves.  The "real" optics here are the
engine running a changed plant (time-domain, its own delay line and state space), built
without the effects module that explains them."""

from __future__ import annotations

import glob
import io
import json
import math
from contextlib import redirect_stdout
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from browser import tables
from conftest import REFERENCE
from diagnosekit import assert_accounted, assert_sound

from twind.analysis.diagnose import _p_value, diagnose, f_profile
from twind.analysis.diagnosis import ALPHA
from twind.analysis.identification import narrow
from twind.analysis.identification.params import param_label
from twind.analysis.separation import separating_measurement
from twind.cli import main
from twind.config import NOMINAL_ETMX, load_optic
from twind.errors import MeasurementWarning
from twind.commissioning.hidden import FACES
from twind.lab.corpus import key_z
from twind.commissioning.measurement import measure_tfs
from twind.limits import ServiceLimits
from twind.model.plant import Plant
from twind.viz.report import report_page

NULL = sorted(glob.glob(str(REFERENCE / "example_null" / "*.xml")))
KEYS = {"consistent", "chi2_nu_nominal", "chi2_nu_final", "located", "effects",
        "unexplained", "nominal_params", "summary", "p_values", "not_fitted",
        "consistency", "controller", "separations", "input_matrix"}


@pytest.fixture(scope="module")
def etmx():  # noqa: ANN201
    """The nominal ETMX, which the example set drifted from."""
    return load_optic(NOMINAL_ETMX)


def _measured(etmx, plant: Plant):  # noqa: ANN001, ANN202
    return measure_tfs(etmx, bw=0.05, averages=10, rms=3.0, seed=3, plant=plant)


def _diagnosed(tfs, cfg, **kwargs):  # noqa: ANN001, ANN003, ANN202
    """:func:`diagnose`, checked accounted for and ranked (:func:`diagnosekit.assert_sound`)."""
    d = diagnose(tfs, cfg, **kwargs)
    assert_sound(d)
    return d


@pytest.mark.slow
def test_example_null_is_consistent(tmp_path: Path) -> None:
    out = io.StringIO()
    with redirect_stdout(out):
        assert main(["diagnose", *NULL, "--json", "-o", str(tmp_path / "report"),
                     "--violin-pair", "631", "691"]) == 0
    obj = json.loads(out.getvalue())
    assert set(obj) == KEYS | {"violin_pair"}
    # ETMX's measured pair against a measurement of the nominal optic, which has no
    # POS-YAW coupling: only a tension difference splits it
    pair = obj.pop("violin_pair")
    assert pair["verdict"] == "tension"
    assert pair["fitted_sigma_m"] < pair["delta_m"] / 4
    assert obj["consistent"] and obj["effects"] == [] and obj["located"] == []
    assert not obj["input_matrix"]["checked"]  # diaggui XML holds no OSEM readings
    assert obj["nominal_params"]["Q_SIDE"]["sigma"] is None
    assert_accounted(obj["p_values"], obj["not_fitted"])
    assert {p.name for p in (tmp_path / "report").iterdir()} == {
        "nominal.png", "diagnosis.json", "index.html", "diagnosis.rrd"}
    assert main(["diagnose", *NULL, "-o", str(tmp_path / "report")]) == 2  # never overwrites
    page = tables((tmp_path / "report" / "index.html").read_text())
    assert page["verdict"][0][0].startswith("consistent with the nominal model")
    assert [row[0] for row in page["nominal"][1:]] == [param_label(n)
                                                      for n in obj["nominal_params"]]
    assert page["nominal"][1][0] == "wire length l (m)"
    assert {row[0]: row[1] for row in page["nominal"][1:]}["SIDE quality factor Q_SIDE"] == (
        "held at start")
    measured = dict(map(tuple, page["measurement"][1:]))
    assert measured["inputs"] == ", ".join(Path(p).name for p in NULL)
    assert measured["estimate"].startswith("Welch (hann), ") and "twind" in measured["read by"]
    text = (tmp_path / "report" / "index.html").read_text()
    assert "positive favours the hypothesis" in text and "held at its start" in text
    assert page["located"] == [["none: no band stands out"]]
    from rerun.chunk import RrdReader

    entities = {c.entity_path for c in RrdReader(tmp_path / "report" / "diagnosis.rrd").stream()}
    assert "/diagnose/POS_POS/measured_db" in entities
    assert "/diagnose/YAW_YAW/nominal_residual_sigma" in entities


def test_few_averages_are_warned_of(etmx) -> None:  # noqa: ANN001
    tfs = measure_tfs(etmx, bw=0.1, averages=5, rms=3.0, seed=3)
    with pytest.warns(MeasurementWarning, match="5 averages: below 10"):
        diagnose(tfs, etmx, max_effects=0)


@pytest.mark.slow
def test_an_extra_delay_is_named_with_what_it_cannot_be_told_from(etmx) -> None:  # noqa: ANN001
    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    extra = 4 / etmx.sus.sample_rate_hz  # the engine delays by whole samples
    d = _diagnosed(_measured(etmx, replace(plant, delay_s=plant.delay_s + extra)), etmx)
    assert not d.consistent
    best = d.effects[0]
    assert {best.effect, *best.equivalent} >= {"loop_delay", "actuator_pole"}
    assert len(d.separations) == len(d.effects) - 1  # and what would tell them apart
    rival = d.effects[1]
    # ... and what that costs: a sine at the EXC limit, its time for 3 sigma, which a
    # sine of half the amplitude takes four times as long to reach
    sep = d.separations[(best.effect, rival.effect)]
    assert sep.amplitude == pytest.approx(30 * 2**0.5) and 0 < sep.seconds < math.inf
    half = separating_measurement(etmx, best.step_result, rival.result,
                                  ServiceLimits(exc_peak=sep.amplitude / 2), sep.bin_hz)
    assert half.seconds == pytest.approx(4 * sep.seconds, rel=1e-9)
    assert f"{sep.seconds:.3g} s for 3 sigma" in "\n".join(d.lines())
    assert f"{rival.effect} fits nearly as well as {best.effect}" in d.summary()
    delay = next(e for e in d.effects if e.effect == "loop_delay")
    assert delay.to_json()["params"]["extra_s"] == pytest.approx(extra, rel=0.35)
    # seeds 3 and 4 of two noise streams: the nominal at chi2/nu 1.36-1.45, the final fit
    # 0.12-0.15 lower (1.23-1.30)
    assert d.final.chi2_nu < 1.4 and d.nominal.chi2_nu - d.final.chi2_nu > 0.05
    # every hypothesis keeps its p-value, the unclaimed ones too (how near they came)
    assert all(d.p_values[e.effect] == e.p_value < ALPHA for e in d.effects)
    assert set(d.p_values) - {e.effect for e in d.effects}
    # the report: every hypothesis with its p-value or its reason, the chosen first; what
    # separates rivals
    page = tables(report_page(d, []))
    rows = page["hypotheses"][1:]
    assert {r[0] for r in rows} == (set(d.p_values) | {e.effect for e in d.effects}
                                    | {x.effect for x in d.not_fitted})
    assert rows[0][:2] == [best.effect, "chosen"]
    assert {(r[0], r[1]) for r in page["separations"][1:]} == set(d.separations)


@pytest.mark.slow
def test_a_coil_imbalance_is_named_and_the_fit_collapses(etmx) -> None:  # noqa: ANN001
    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    act = plant.actuation.copy()
    gains = [0.03, -0.02, 0.01, -0.025]
    act[:, :4] *= 1 + np.array(gains)
    d = _diagnosed(_measured(etmx, replace(plant, actuation=act)), etmx)
    assert d.effects[0].effect == "coil_imbalance" and d.effects[0].delta_bic > 100
    assert d.final.chi2_nu < 1.4 and d.nominal.chi2_nu > 10
    assert d.unexplained == []
    # the pitch-like part of the gains has a sigma, a single gain (common mode) has none
    cov = d.effects[0].result.combination_covariance(
        [{"gain_UL": 0.5, "gain_UR": 0.5, "gain_LL": -0.5, "gain_LR": -0.5}, {"gain_UL": 1.0}])
    assert 0 < cov[0, 0] < 1e-4 and np.isnan(cov[1, 1])
    truth = {"gains": dict(zip(FACES, gains, strict=True))}
    assert 0 < key_z("coil_imbalance", truth, d.effects[0].result) < 4


@pytest.mark.slow
def test_a_pitched_optic_s_bounce_is_named_from_its_compliance(etmx) -> None:  # noqa: ANN001
    """Face heads tilted 0.15 rad towards VERT against the optic (3-D kinematics, the
    geometric body's VERT and ROLL: corpus.tilted_heads): the BounceRoll notches keep the
    modes' peaks out of IN1/EXC, but the bounce's compliance, rising as f^2 against the
    optic's above the pendulum modes, names bounce_roll with its coupling."""
    from twind.commissioning.hidden import tilted_heads

    plant, truth = tilted_heads(Plant.from_params(etmx.sus, etmx.mechanics()), etmx.sus,
                                0.0, 0.15)
    d = _diagnosed(_measured(etmx, plant), etmx)
    best = d.effects[0]
    assert best.effect == "bounce_roll" and best.p_value < 1e-6
    assert best.to_json()["params"]["vertical"] == pytest.approx(truth["vertical"], rel=0.35)
    assert 0 < key_z("bounce_roll", truth, best.result) < 3


@pytest.mark.slow
def test_two_effects_at_once_are_both_chosen(etmx) -> None:  # noqa: ANN001
    """A coil imbalance and an extra delay in one optic: forward selection names the
    imbalance, then the delay (or the driver pole it is not told from) given it. Allowed
    one effect only, the imbalance is partial and the delay's misfit is left unexplained."""
    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    act = plant.actuation.copy()
    act[:, :4] *= 1 + np.array([0.03, -0.02, 0.01, -0.025])
    extra = 4 / etmx.sus.sample_rate_hz
    tfs = _measured(etmx, replace(plant, actuation=act, delay_s=plant.delay_s + extra))
    d = _diagnosed(tfs, etmx)
    chosen = [e.effect for e in d.chosen]
    assert chosen[0] == "coil_imbalance" and len(chosen) == 2
    second = d.chosen[1]
    assert {second.effect, *second.equivalent} >= {"loop_delay", "actuator_pole"}
    assert all(e.p_given_others < ALPHA for e in d.chosen)
    delay = next(e for e in d.effects if e.effect == "loop_delay")
    assert delay.to_json()["params"]["extra_s"] == pytest.approx(extra, rel=0.35)
    assert d.final.chi2_nu < 1.4 and not d.unexplained
    assert d.summary().startswith("explained by coil_imbalance + ")
    one = _diagnosed(tfs, etmx, max_effects=1)
    assert [e.effect for e in one.chosen] == ["coil_imbalance"]
    assert one.chosen[0].to_json()["partial"] and one.unexplained
    assert one.summary().startswith("coil_imbalance explain(s) part of the misfit")
    assert one.lines()[0] == one.summary() == one.to_json()["summary"]


@pytest.mark.slow
def test_a_mode_in_no_list_is_found_anywhere_and_read_as_a_body(etmx) -> None:  # noqa: ANN001
    """A body of 60 mg on a spring at 7 Hz, 20 mm above the face's centre
    (corpus.attached_body: 3-D kinematics, a new coordinate of the mechanics), ringing in
    PIT/POS: a ``resonance`` anywhere in the band, not a catalogue effect, read as a body
    pulling along the beam at its point, with its mass."""
    from twind.commissioning.hidden import attached_body
    from twind.lab.corpus import body_start

    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    body, truth = attached_body(plant, etmx.sus, 6e-5, 7.0, 30.0, (0.0, 0.02))
    tfs = _measured(etmx, body)
    d = _diagnosed(tfs, etmx)
    assert [e.effect for e in d.chosen] == ["resonance"] and d.chosen[0].p_value < 1e-6
    out = d.chosen[0].to_json()
    assert out["params"]["f_hz"] == pytest.approx(truth["f_hz"], rel=0.15)
    r = out["reading"]
    assert r["along"] == "beam" and r["on_face"] and set(r["coupled"]) == {"POS", "PIT"}
    assert abs(r["z0_m"] - 0.02) < 3 * r["z0_m_sigma"]
    assert abs(r["mass_kg"] - 6e-5) < 3 * r["mass_kg_sigma"]
    # a body seen at its peak: the frequencies the data allow hold it, and little else
    assert any(lo <= truth["f_hz"] <= hi for lo, hi in r["f_hz_ranges"])
    assert sum(hi - lo for lo, hi in r["f_hz_ranges"]) < 0.1 * truth["f_hz"]
    assert "as a body" in "\n".join(d.lines()) and "the data allow f in" in "\n".join(d.lines())
    # the truth's structure profiled in f: held 5 % off, it fits worse by more than the noise
    lo, hi = f_profile(tfs, etmx, d, body_start(truth),
                       factors=(0.9, 0.95, 1.0, 1.05, 1.1))
    assert lo == hi == pytest.approx(truth["f_hz"])


@pytest.mark.slow
def test_one_readback_with_its_own_stage_is_named_with_its_corners(etmx) -> None:  # noqa: ANN001
    """The LL OSEM's readback through a pole at 25 Hz and a zero at 28 Hz that the other
    channels lack (Plant.channel_filters, integrated as states by the engine): the
    channel_filter family names the channel and both corners."""
    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    d = _diagnosed(_measured(etmx, replace(plant, channel_filters=(("osem", 2, 25.0, 28.0),))),
                 etmx)
    best = d.chosen[0].to_json()
    assert best["effect"] == "osem_filter_LL" and best["family"] == "channel_filter"
    assert best["params"]["pole_hz"] == pytest.approx(25.0, rel=0.35)
    assert best["params"]["zero_hz"] == pytest.approx(28.0, rel=0.35)
    assert d.final.chi2_nu < 1.4 < d.nominal.chi2_nu


@pytest.mark.slow
def test_the_diagnosed_model_is_pushed_into_a_running_twin(etmx) -> None:  # noqa: ANN001
    from servicekit import serving

    from twind.analysis.estimation.tf import from_diaggui
    from twind.client import TwinClient
    from twind.errors import TwindError

    d = _diagnosed(from_diaggui(NULL), etmx)
    nominal, effect = d.final_model()
    assert len(nominal) == 6 and effect is None  # example_null: the drift alone
    with serving("--optics", "ETMX") as endpoint:
        client = TwinClient([endpoint])
        client.params("ETMX", effect=effect, **nominal)
        reply = client.params("ETMX")
        assert reply.params["wire_length_m"] == pytest.approx(d.final.as_dict()["wire_length_m"])
        gains = {"gain_UL": 0.01, "gain_LR": -0.01}
        reply = client.params("ETMX", effect={"id": "coil_imbalance", "values": gains})
        assert reply.effect.to_json() == {"id": "coil_imbalance", "values": gains}
        reply = client.params("ETMX", b_m=0.00071)  # the effect stays through later changes
        assert reply.effect.id == "coil_imbalance"
        with pytest.raises(TwindError, match="catalogue has"):
            client.params("ETMX", effect={"id": "gremlins"})
        with pytest.raises(TwindError, match="states"):
            client.params("ETMX", effect={"id": "actuator_pole", "values": {"inv_f_hz": 0.01}})
        assert client.params("ETMX", effect={"id": None}).effect is None
        client.close()


@pytest.mark.slow
def test_xml_route_a_diaggui_set_written_by_the_twin_is_diagnosed(tmp_path: Path,
                                                                    etmx) -> None:  # noqa: ANN001
    """A drifted optic with a concealed coil imbalance, measured on the twin and saved as
    diaggui files like example_null: from the files alone, the imbalance is named."""
    from twind.analysis.estimation.diaggui import write_measurement_set
    from twind.analysis.estimation.tf import from_diaggui
    from twind.analysis.identification.params import param_value, with_params
    from twind.commissioning.measurement import DRIFT

    real = replace(etmx, sus=with_params(etmx.sus, {k: param_value(etmx.sus, k) * v
                                                    for k, v in DRIFT.items()}))
    plant = Plant.from_params(real.sus, real.mechanics())
    act = plant.actuation.copy()
    act[:, :4] *= 1 + 0.002 * np.array([1.0, -0.7, 0.4, -0.8])
    tfs = measure_tfs(real, bw=0.05, averages=10, rms=3.0, seed=5,
                      plant=replace(plant, actuation=act))
    files = write_measurement_set(tfs, tmp_path)
    assert sorted(p.name for p in files) == ["ETMX_PIT_exc.xml", "ETMX_POS_exc.xml",
                                             "ETMX_YAW_exc.xml"]
    d = _diagnosed(from_diaggui(files), etmx)
    assert d.effects and d.effects[0].effect == "coil_imbalance"
    assert d.final.chi2_nu < d.nominal.chi2_nu


def test_a_searched_mode_s_p_value_pays_for_each_search_s_path() -> None:
    """A mode searched for is given Davies' bound over each search, with that search's own
    path (narrow.p_value), not the chi^2 tail a mode at a known frequency would get: at a
    likelihood ratio of 20 with the two paths of a ``resonance`` search over the band (25
    and 48 rad, a null's at 0.25 Hz), the search's cost lifts p above ALPHA, which the tail
    alone stays ten times below."""
    lr, k, searched, paths = 20.0, 4, 1, [25.0, 48.0]
    p = _p_value(lr, k, paths, searched)
    assert p == pytest.approx(sum(narrow.p_value(lr, k - searched, x) for x in paths),
                              rel=1e-12)
    assert p > ALPHA > 10 * len(paths) * narrow.p_value(lr, k - searched, 0.0)
    assert _p_value(lr, k, [], searched) == pytest.approx(stats.chi2.sf(lr, k), rel=1e-12)
