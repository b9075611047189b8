"""Shared fixtures: the reference data in tests/data (see its README) and the shipped configs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

REFERENCE = Path(__file__).resolve().parent / "data"


def complex_array(obj: dict) -> np.ndarray:
    """golden_tf.json's {"re": ..., "im": ...} as a complex array."""
    return np.asarray(obj["re"]) + 1j * np.asarray(obj["im"])


@pytest.fixture(scope="session")
def golden() -> dict:
    return json.loads((REFERENCE / "golden_tf.json").read_text())


@pytest.fixture(scope="session")
def nominal() -> dict:
    return json.loads((REFERENCE / "sos_etmx_nominal.json").read_text())
