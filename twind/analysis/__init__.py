"""Measurement and identification: transfer functions, plant recovery."""
