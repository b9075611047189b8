"""Estimation: transfer functions from recordings (Welch, the local polynomial method) and
from diaggui files, with their coherence and errors, and the plant recovered from them."""

from twind.analysis.estimation import tf  # noqa: F401 - its readers register with TFSet.read
