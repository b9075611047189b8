"""Locating where a fitted model misses the data, with the search's false alarms controlled."""

from __future__ import annotations

import glob
from dataclasses import replace

import numpy as np
import pytest
from conftest import REFERENCE

from twind.analysis.estimation.tf import from_diaggui
from twind.analysis.identification.fit import fit
from twind.analysis.identification.locate import locate
from twind.config import load_config
from twind.commissioning.measurement import measure_tfs
from twind.model.plant import Plant

NULL = sorted(glob.glob(str(REFERENCE / "example_null" / "*.xml")))


@pytest.fixture(scope="module")
def etmx():  # noqa: ANN201
    return load_config(None, ["ETMX"]).optics["ETMX"]


def test_nothing_is_located_in_null_measurements(etmx) -> None:  # noqa: ANN001
    tfs = from_diaggui(NULL)
    assert locate(tfs, etmx, fit(tfs, etmx)) == []
    # the band statistic's tails are lighter than the twin's: over 180 twin nulls at these
    # settings (seeds 0-89, two noise streams) 16 located one band (Holm p 3e-4 to 0.01, at
    # most 3.6 sigma), where alpha promises 1 % (docs/limits.md); a real miss stands far out
    twin = measure_tfs(etmx, bw=0.05, averages=10, rms=3.0, seed=11)
    found = locate(twin, etmx, fit(twin, etmx))
    assert len(found) <= 1 and all(x.significance < 4 for x in found), found


def test_a_coil_imbalance_is_located_in_the_cross_couplings(etmx) -> None:  # noqa: ANN001
    """Unequal face coils turn a POS drive into torques: the largest misses are in the
    cross-couplings PIT/POS and YAW/POS."""
    plant = Plant.from_params(etmx.sus, etmx.mechanics())
    act = plant.actuation.copy()
    act[:, :4] *= 1 + np.array([0.03, -0.02, 0.01, -0.025])
    tfs = measure_tfs(etmx, bw=0.05, averages=10, rms=3.0, seed=3,
                      plant=replace(plant, actuation=act))
    found = locate(tfs, etmx, fit(tfs, etmx))
    assert found and found[0].element == "YAW/POS" and found[0].significance > 10
    top = {x.element for x in found[:4]}
    assert top <= {"YAW/POS", "PIT/POS"}, [(x.element, x.significance) for x in found]
