"""Shared fixtures: the reference data in tests/data (see its README) and the shipped configs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

# The tests run side by side (pytest-xdist, a worker per core): BLAS threads of one that
# spin while the other computes slowed the diagnosis tests two- to threefold.
threadpool_limits(limits=1, user_api="blas")

REFERENCE = Path(__file__).resolve().parent / "data"


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: a worker per core this process may run on, at most 4 (several tests
    serve twins in real time, and more workers would starve them, not speed the suite)."""
    return max(1, min(len(os.sched_getaffinity(0)), 4))


def complex_array(obj: dict) -> np.ndarray:
    """golden_tf.json's {"re": ..., "im": ...} as a complex array."""
    return np.asarray(obj["re"]) + 1j * np.asarray(obj["im"])


@pytest.fixture(scope="session")
def golden() -> dict:
    return json.loads((REFERENCE / "golden_tf.json").read_text())


@pytest.fixture(scope="session")
def nominal() -> dict:
    return json.loads((REFERENCE / "sos_etmx_nominal.json").read_text())
