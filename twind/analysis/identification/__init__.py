"""Identification: an optic's physical parameters from its measured transfer functions
(:mod:`.fit`), the bins and model it uses, and its result."""
