"""What proves twind rather than what twind is: the virtual measurement on the twin's engine,
the proof corpus and the demo, the calibration (pull and information) and speed benchmarks,
the identification campaign and the soak of the service. Nothing below imports it."""
