"""The CDS damping loop around the plant: foton filter designs and files, filter modules and
the closed loop's test-point responses."""
