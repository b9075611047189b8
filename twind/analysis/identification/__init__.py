"""Identification: an optic's physical parameters from its measured transfer functions (the
fit, its data, model and result), where a model misses (locate), the search for a narrow
mode, and the free-swinging modes (from the 40m's table, and from a ringdown)."""
