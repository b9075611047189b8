"""Shared fixtures: the reference data in ../shared/reference and the shipped configs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference"


def complex_array(obj: dict) -> np.ndarray:
    """golden_tf.json's {"re": ..., "im": ...} as a complex array."""
    return np.asarray(obj["re"]) + 1j * np.asarray(obj["im"])


@pytest.fixture(scope="session")
def golden() -> dict:
    # no skip: a missing ../shared/reference must fail CI, not pass it quietly
    return json.loads((REFERENCE / "golden_tf.json").read_text())


@pytest.fixture(scope="session")
def nominal() -> dict:
    return json.loads((REFERENCE / "sos_etmx_nominal.json").read_text())
