"""Excitations designed from the model: the noise that makes a test point coherent in a band
(:mod:`~twind.analysis.design.coherence`), and D-optimal multisines for the fit's parameters
(:mod:`~twind.analysis.design.information`). The waveforms themselves, and the limits a twin
holds them to, are :mod:`twind.excitation`'s."""
