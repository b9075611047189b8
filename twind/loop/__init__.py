"""The CDS damping loop: input/output matrices, foton filters, filter modules, the plant it sees."""
