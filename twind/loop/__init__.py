"""The CDS damping loop around the plant: foton filter designs and files, filter modules and
the closed loop's test-point responses."""

FOTON_READERS = ("twind", "python-foton")
"""Whose foton turns design strings into filters: twind's own, or LIGO's from the optional
extra ``twind[foton]``; chosen by ``twind --foton`` or the environment variable below."""
FOTON_VARIABLE = "TWIND_FOTON"
