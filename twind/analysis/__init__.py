"""Measurement, identification and diagnosis: transfer functions (Welch, LPM, diaggui), the
plant, fits, where a model misses, the physics left out, free-swinging modes."""
